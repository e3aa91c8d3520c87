"""One MAVLink mission item, as the controller and the mission files see it.

Shared by :mod:`passt_mav.mission` (waypoint files, ``WaypointMission``) and
:mod:`passt_mav.mavlink` (upload / download / read-back verification). No MAVLink
import here: the numbers are MAVLink's (MAV_CMD, MAV_FRAME), the type is plain data.

Coordinates are WGS-84 degrees (``lat``, ``lon``) and metres (``alt``, relative to
home for the default frame). On the wire they travel as int32 degE7
(MISSION_ITEM_INT); :meth:`MissionItem.same_as` compares with the 1e-7 degree
tolerance that quantisation implies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "MissionItem",
    "MAV_CMD_NAV_WAYPOINT",
    "MAV_CMD_DO_CHANGE_SPEED",
    "MAV_FRAME_GLOBAL",
    "MAV_FRAME_GLOBAL_RELATIVE_ALT",
    "MAV_FRAME_MISSION",
    "MAV_MISSION_TYPE_MISSION",
    "MAV_MISSION_TYPE_FENCE",
    "MAV_MISSION_TYPE_RALLY",
    "GLOBAL_FRAMES",
]

MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_DO_CHANGE_SPEED = 178
MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION = 5001
MAV_FRAME_GLOBAL = 0
MAV_FRAME_MISSION = 2
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_MISSION_TYPE_MISSION = 0
MAV_MISSION_TYPE_FENCE = 1
MAV_MISSION_TYPE_RALLY = 2
#: frames whose x/y are latitude/longitude (plain and _INT variants)
GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})


@dataclass(frozen=True)
class MissionItem:
    """A mission item in MISSION_ITEM_INT terms, coordinates in float degrees.

    seq: index in the list (0 = home on ArduPilot); frame: MAV_FRAME; command: MAV_CMD;
    param1..4: command parameters (for NAV_WAYPOINT param1 = hold s, param2 = accept
    radius m); lat/lon: degrees (WGS-84), alt: m; mission_type: MAV_MISSION_TYPE.
    """

    seq: int
    frame: int = MAV_FRAME_GLOBAL_RELATIVE_ALT
    command: int = MAV_CMD_NAV_WAYPOINT
    current: int = 0
    autocontinue: int = 1
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0
    mission_type: int = MAV_MISSION_TYPE_MISSION

    @property
    def is_global(self) -> bool:
        return self.frame in GLOBAL_FRAMES

    @property
    def x_int(self) -> int:
        """latitude as int32 degE7 (or the raw x for non-global frames)."""
        return int(round(self.lat * 1e7)) if self.is_global else int(round(self.lat))

    @property
    def y_int(self) -> int:
        """longitude as int32 degE7 (or the raw y for non-global frames)."""
        return int(round(self.lon * 1e7)) if self.is_global else int(round(self.lon))

    def same_as(
        self,
        other: MissionItem,
        *,
        deg_tol: float = 1e-7,
        param_tol: float = 1e-4,
        alt_tol: float = 1e-3,
        check_frame: bool = True,
    ) -> bool:
        """Equal within wire tolerances: command, frame, lat/lon to ``deg_tol`` degrees
        (one degE7 step), params to ``param_tol`` (float32 on the wire), alt to ``alt_tol`` m."""
        if self.seq != other.seq or self.command != other.command or self.mission_type != other.mission_type:
            return False
        if check_frame and _plain_frame(self.frame) != _plain_frame(other.frame):
            return False
        for a, b in (
            (self.param1, other.param1),
            (self.param2, other.param2),
            (self.param3, other.param3),
            (self.param4, other.param4),
        ):
            if not (math.isnan(a) and math.isnan(b)) and not abs(a - b) <= param_tol * max(1.0, abs(a)):
                return False
        return (
            abs(self.lat - other.lat) <= deg_tol + 1e-12
            and abs(self.lon - other.lon) <= deg_tol + 1e-12
            and abs(self.alt - other.alt) <= alt_tol
        )


def _plain_frame(frame: int) -> int:
    """MAV_FRAME_GLOBAL_INT (5) -> GLOBAL (0), GLOBAL_RELATIVE_ALT_INT (6) -> 3, TERRAIN_ALT_INT (11) -> 10."""
    return {5: 0, 6: 3, 11: 10}.get(int(frame), int(frame))
