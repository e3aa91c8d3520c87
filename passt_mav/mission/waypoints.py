"""Waypoint missions for ArduPilot Rover, and their files (QGC WPL 110, QGC ``.plan``).

:class:`WaypointMission` is what one PASST leg flies: waypoints ``(n, 2)`` of
``[lat, lon]`` (WGS-84 degrees), an altitude (m, relative to home; a boat ignores
it), an optional speed (m/s), an optional acceptance radius and an optional
inclusion geofence polygon ``(k, 2)`` of ``[lat, lon]``.

ArduPilot's seq-0 rule (shared/ARDUPILOT_ROVER.md): the vehicle overwrites seq 0
with its home, so :meth:`WaypointMission.items` puts a home placeholder at seq 0
(frame 0 GLOBAL, NAV_WAYPOINT at ``home`` or, without a home, at the first
waypoint) and the mission proper from seq 1: an optional DO_CHANGE_SPEED, then one
NAV_WAYPOINT (frame 3 GLOBAL_RELATIVE_ALT) per waypoint. Read back (from a vehicle
or a file) seq 0 becomes :attr:`WaypointMission.home`.

Files, written and read by hand because no maintained Python library reads and
writes both formats for plain data (pymavlink's ``mavwp`` needs MAVLink message
objects and knows only WPL; MAVSDK's importer is C++ and import-only):

* **QGC WPL 110** (``.waypoints``, https://mavlink.io/en/file_formats/): header line
  ``QGC WPL 110``, then one tab-separated line per item
  ``seq current frame command p1 p2 p3 p4 lat lon alt autocontinue``, home at seq 0.
* **QGroundControl plan** (``.plan`` JSON, QGC dev guide "Plan File Format"):
  ``mission.items`` are ``SimpleItem``s whose ``params`` are p1..p4, lat, lon, alt
  (NaN written as ``null``); home is ``mission.plannedHomePosition`` and NOT an
  item; the fence is ``geoFence.polygons[*].polygon``.

Bad files raise :class:`passt_mav.errors.MissionFileError` with one line naming
the file and the problem.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from passt_mav.errors import MissionFileError
from passt_mav.mission.items import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    MAV_FRAME_GLOBAL_RELATIVE_ALT,
    MAV_FRAME_MISSION,
    MAV_MISSION_TYPE_FENCE,
    MAV_MISSION_TYPE_MISSION,
    MissionItem,
)

__all__ = ["WaypointMission", "WPL_HEADER", "MAV_TYPE_SURFACE_BOAT", "MAV_AUTOPILOT_ARDUPILOTMEGA"]

WPL_HEADER = "QGC WPL 110"
#: QGC .plan "vehicleType" / "firmwareType" are MAV_TYPE / MAV_AUTOPILOT numbers
MAV_TYPE_SURFACE_BOAT = 11
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
_SPEED_TYPE_GROUND = 1  # DO_CHANGE_SPEED param1: 1 = ground speed (Rover)


def _latlon_array(a, what: str, *, allow_empty: bool = False) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MissionFileError(f"{what} must be numbers (n, 2) [lat, lon]: {exc}") from None
    if arr.size == 0 and allow_empty:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
        raise MissionFileError(f"{what} must have shape (n, 2) [lat, lon] with n >= 1, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise MissionFileError(f"{what} contain NaN or infinite values")
    if (np.abs(arr[:, 0]) > 90).any() or (np.abs(arr[:, 1]) > 180).any():
        raise MissionFileError(f"{what} out of range (|lat| <= 90, |lon| <= 180)")
    return arr


@dataclass(eq=False)
class WaypointMission:
    """One leg as a list of waypoints (see module docstring).

    waypoints: (n, 2) [lat, lon] degrees, n >= 1. home: (lat, lon, alt) or None
    (seq 0 then holds the first waypoint as a placeholder; the vehicle replaces it
    anyway). alt: m relative to home for every waypoint. speed: m/s, adds a
    DO_CHANGE_SPEED item at seq 1 when given. wp_radius_m: acceptance radius (m),
    written to NAV_WAYPOINT param2 for the files and for autopilots that read it; an
    ArduPilot Rover drops param2 when it stores the item and uses its WP_RADIUS
    parameter instead, so the controller sets WP_RADIUS (``Vehicle.set_wp_radius``)
    and the read-back check never expects param2 back (``mission_client.rover_stored``);
    0 = leave the vehicle's WP_RADIUS. fence: (k, 2) [lat, lon] inclusion polygon
    (k >= 3) or None.
    """

    waypoints: np.ndarray
    home: tuple[float, float, float] | None = None
    alt: float = 0.0
    speed: float | None = None
    wp_radius_m: float = 0.0
    fence: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.waypoints = _latlon_array(self.waypoints, "waypoints")
        if self.home is not None:
            h = tuple(float(x) for x in self.home)
            if len(h) == 2:
                h = (h[0], h[1], 0.0)
            if len(h) != 3 or not all(math.isfinite(x) for x in h) or abs(h[0]) > 90 or abs(h[1]) > 180:
                raise MissionFileError(f"home must be finite (lat, lon, alt) in range, got {self.home!r}")
            self.home = h
        self.alt = float(self.alt)
        if self.speed is not None:
            self.speed = float(self.speed)
            if not (math.isfinite(self.speed) and self.speed > 0):
                raise MissionFileError(f"speed must be a positive number of m/s, got {self.speed}")
        self.wp_radius_m = float(self.wp_radius_m)
        if not (math.isfinite(self.wp_radius_m) and self.wp_radius_m >= 0):
            raise MissionFileError(f"waypoint radius must be >= 0 m, got {self.wp_radius_m}")
        if self.fence is not None:
            self.fence = _latlon_array(self.fence, "fence vertices")
            if len(self.fence) < 3:
                raise MissionFileError(f"a fence polygon needs at least 3 vertices, got {len(self.fence)}")

    # -- construction ------------------------------------------------------------
    @classmethod
    def from_path(
        cls,
        grid,
        path,
        *,
        home: Sequence[float] | None = None,
        alt: float = 0.0,
        speed: float | None = None,
        wp_radius_m: float = 0.0,
        fence_margin_m: float | None = 0.0,
    ) -> WaypointMission:
        """A mission from an 8-connected grid path ``(L+1, 2)`` (row, col) on ``grid``.

        Straight runs merge into one waypoint (:func:`geo.path_to_waypoints`).
        ``fence_margin_m``: the inclusion fence is the region's outer cell edges
        grown by this many metres (:meth:`geo.RegionGrid.geofence`); ``None`` = no fence.
        Invalid paths raise :class:`geo.GeoError`.
        """
        import geo

        wps = geo.path_to_waypoints(grid, path)
        fence = None if fence_margin_m is None else grid.geofence(float(fence_margin_m))
        cells = geo.waypoint_cells(grid, path)
        return cls(
            wps,
            home=None if home is None else tuple(home),
            alt=alt,
            speed=speed,
            wp_radius_m=wp_radius_m,
            fence=fence,
            meta={"cells": cells.tolist()},
        )

    # -- MAVLink items ---------------------------------------------------------------
    @property
    def first_waypoint_seq(self) -> int:
        """Seq of the first NAV_WAYPOINT (1, or 2 after a DO_CHANGE_SPEED)."""
        return 1 if self.speed is None else 2

    def waypoint_seqs(self) -> list[int]:
        """Mission seq of each waypoint (what MISSION_ITEM_REACHED reports)."""
        s = self.first_waypoint_seq
        return list(range(s, s + len(self.waypoints)))

    def items(self) -> list[MissionItem]:
        """Mission items (mission_type 0): home placeholder at seq 0, the mission from seq 1."""
        if self.home is not None:
            hlat, hlon, halt = self.home
        else:
            hlat, hlon, halt = float(self.waypoints[0, 0]), float(self.waypoints[0, 1]), 0.0
        out = [MissionItem(seq=0, frame=MAV_FRAME_GLOBAL, command=MAV_CMD_NAV_WAYPOINT, lat=hlat, lon=hlon, alt=halt)]
        if self.speed is not None:
            out.append(
                MissionItem(
                    seq=1,
                    frame=MAV_FRAME_MISSION,
                    command=MAV_CMD_DO_CHANGE_SPEED,
                    param1=float(_SPEED_TYPE_GROUND),
                    param2=self.speed,
                    param3=-1.0,
                )
            )
        for lat, lon in self.waypoints:
            out.append(
                MissionItem(
                    seq=len(out),
                    frame=MAV_FRAME_GLOBAL_RELATIVE_ALT,
                    command=MAV_CMD_NAV_WAYPOINT,
                    param2=self.wp_radius_m,
                    lat=float(lat),
                    lon=float(lon),
                    alt=self.alt,
                )
            )
        return out

    def fence_items(self) -> list[MissionItem]:
        """Fence items (mission_type 1): one FENCE_POLYGON_VERTEX_INCLUSION per vertex,
        param1 = vertex count; empty without a fence."""
        if self.fence is None:
            return []
        k = len(self.fence)
        return [
            MissionItem(
                seq=i,
                frame=MAV_FRAME_GLOBAL,
                command=MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                param1=float(k),
                lat=float(lat),
                lon=float(lon),
                mission_type=MAV_MISSION_TYPE_FENCE,
            )
            for i, (lat, lon) in enumerate(self.fence)
        ]

    @classmethod
    def from_items(
        cls, items: Iterable[MissionItem], fence_items: Iterable[MissionItem] = (), *, source: str = "mission"
    ) -> WaypointMission:
        """Inverse of :meth:`items` (+ :meth:`fence_items`); fence items may also be mixed into
        ``items`` (told apart by ``mission_type``). Seq 0 becomes :attr:`home`.

        Accepts NAV_WAYPOINT in a global frame and DO_CHANGE_SPEED; anything else raises
        :class:`MissionFileError` (``source`` names the file in the message).
        """
        mission, fence = [], list(fence_items)
        for it in items:
            (fence if it.mission_type == MAV_MISSION_TYPE_FENCE else mission).append(it)
        if not mission:
            raise MissionFileError(f"{source}: no mission items")
        mission.sort(key=lambda it: it.seq)
        seqs = [it.seq for it in mission]
        if seqs != list(range(len(mission))):
            raise MissionFileError(f"{source}: mission item seqs must run 0..{len(mission) - 1}, got {seqs[:8]}...")
        h = mission[0]
        if not h.is_global:
            raise MissionFileError(f"{source}: seq 0 (home) must be in a global frame, got frame {h.frame}")
        home = (h.lat, h.lon, h.alt)
        wps, alts, radii, speed = [], [], [], None
        for it in mission[1:]:
            if it.mission_type != MAV_MISSION_TYPE_MISSION:
                raise MissionFileError(
                    f"{source}: item {it.seq} has mission_type {it.mission_type} (rally points are not supported)"
                )
            if it.command == MAV_CMD_NAV_WAYPOINT:
                if not it.is_global:
                    raise MissionFileError(f"{source}: waypoint {it.seq} is in frame {it.frame}, not a lat/lon frame")
                wps.append((it.lat, it.lon))
                alts.append(it.alt)
                radii.append(it.param2)
            elif it.command == MAV_CMD_DO_CHANGE_SPEED:
                speed = it.param2
            else:
                raise MissionFileError(
                    f"{source}: item {it.seq} has command {it.command}; only NAV_WAYPOINT (16) "
                    "and DO_CHANGE_SPEED (178) are supported"
                )
        if not wps:
            raise MissionFileError(f"{source}: the mission has no waypoints after home (seq 0)")
        if max(alts) - min(alts) > 1e-3 or max(radii) - min(radii) > 1e-4:
            raise MissionFileError(f"{source}: waypoints must share one altitude and one acceptance radius")
        try:
            return cls(
                np.array(wps),
                home=home,
                alt=alts[0],
                speed=speed,
                wp_radius_m=radii[0],
                fence=_fence_from_items(fence, source),
            )
        except MissionFileError as exc:
            msg = str(exc)
            raise MissionFileError(msg if msg.startswith(f"{source}:") else f"{source}: {msg}") from None

    def same_as(self, other: WaypointMission, *, deg_tol: float = 1e-7, tol: float = 1e-4) -> bool:
        """Same mission within wire tolerances (``deg_tol`` degrees, ``tol`` for alt/speed/radius)."""

        def close(a, b):
            return (a is None and b is None) or (
                a is not None and b is not None and abs(a - b) <= tol * max(1.0, abs(a))
            )

        if self.waypoints.shape != other.waypoints.shape or not np.allclose(
            self.waypoints, other.waypoints, rtol=0, atol=deg_tol
        ):
            return False
        if (self.home is None) != (other.home is None) or (self.fence is None) != (other.fence is None):
            return False
        if self.home is not None and not (
            np.allclose(self.home[:2], other.home[:2], rtol=0, atol=deg_tol) and close(self.home[2], other.home[2])
        ):
            return False
        if self.fence is not None and (
            self.fence.shape != other.fence.shape or not np.allclose(self.fence, other.fence, rtol=0, atol=deg_tol)
        ):
            return False
        return (
            close(self.alt, other.alt) and close(self.speed, other.speed) and close(self.wp_radius_m, other.wp_radius_m)
        )

    # -- QGC WPL 110 ------------------------------------------------------------------
    def wpl_text(self) -> str:
        """The mission as QGC WPL 110 text (home at seq 0 with current = 1, as QGC writes it)."""
        lines = [WPL_HEADER]
        for it in self.items():
            vals = [
                it.seq,
                1 if it.seq == 0 else 0,
                it.frame,
                it.command,
                it.param1,
                it.param2,
                it.param3,
                it.param4,
                it.lat,
                it.lon,
                it.alt,
                it.autocontinue,
            ]
            lines.append("\t".join(_num(v) for v in vals))
        return "\n".join(lines) + "\n"

    def to_wpl(self, path: str | Path) -> Path:
        """Write QGC WPL 110 (``.waypoints``); the fence is not part of that format."""
        p = Path(path)
        p.write_text(self.wpl_text())
        return p

    @classmethod
    def from_wpl(cls, path: str | Path) -> WaypointMission:
        """Read a QGC WPL 110 file (tabs or spaces between the 12 fields)."""
        p = Path(path)
        text = _read_text(p)
        return cls.from_items(_parse_wpl(text, str(p)), source=str(p))

    # -- QGroundControl .plan --------------------------------------------------------
    def plan_dict(self) -> dict[str, Any]:
        """The mission as a QGroundControl plan (JSON-able dict, the fields QGC writes)."""
        items = []
        for i, it in enumerate(self.items()[1:], start=1):  # home is plannedHomePosition, not an item
            params = [it.param1, it.param2, it.param3, it.param4, it.lat, it.lon, it.alt]
            if it.command == MAV_CMD_DO_CHANGE_SPEED:
                params[4:] = [0.0, 0.0, 0.0]
            d = {
                "autoContinue": bool(it.autocontinue),
                "command": it.command,
                "doJumpId": i,
                "frame": it.frame,
                "params": [None if (isinstance(v, float) and math.isnan(v)) else v for v in params],
                "type": "SimpleItem",
            }
            if it.command == MAV_CMD_NAV_WAYPOINT:
                d.update({"AMSLAltAboveTerrain": None, "Altitude": it.alt, "AltitudeMode": 1})
            items.append(d)
        home = self.items()[0]
        return {
            "fileType": "Plan",
            "version": 1,
            "groundStation": "QGroundControl",
            "mission": {
                "version": 2,
                "firmwareType": MAV_AUTOPILOT_ARDUPILOTMEGA,
                "vehicleType": MAV_TYPE_SURFACE_BOAT,
                "cruiseSpeed": self.speed if self.speed is not None else 2.0,
                "hoverSpeed": 5,
                "globalPlanAltitudeMode": 1,
                "plannedHomePosition": [home.lat, home.lon, home.alt],
                "items": items,
            },
            "geoFence": {
                "version": 2,
                "circles": [],
                "polygons": []
                if self.fence is None
                else [{"inclusion": True, "polygon": self.fence.tolist(), "version": 1}],
            },
            "rallyPoints": {"version": 2, "points": []},
        }

    def to_plan(self, path: str | Path) -> Path:
        """Write a QGroundControl ``.plan`` file."""
        p = Path(path)
        p.write_text(json.dumps(self.plan_dict(), indent=4) + "\n")
        return p

    @classmethod
    def from_plan(cls, path: str | Path) -> WaypointMission:
        """Read a QGroundControl ``.plan`` file (SimpleItems; one inclusion polygon at most)."""
        p = Path(path)
        try:
            d = json.loads(_read_text(p))
        except json.JSONDecodeError as exc:
            raise MissionFileError(f"{p}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
        except RecursionError:
            raise MissionFileError(f"{p}: not valid JSON (nested too deep)") from None
        return cls.from_plan_dict(d, source=str(p))

    @classmethod
    def from_plan_dict(cls, d: Any, *, source: str = "plan") -> WaypointMission:
        """The mission of a parsed QGroundControl plan ``d`` (``source`` names it in errors)."""
        if not isinstance(d, dict) or d.get("fileType") != "Plan":
            raise MissionFileError(f'{source}: not a QGroundControl plan (fileType must be "Plan")')
        m = d.get("mission")
        if not isinstance(m, dict) or not isinstance(m.get("items"), list):
            raise MissionFileError(f"{source}: mission.items is missing")
        items = _plan_items(m, source)
        fence = _plan_fence(d, source)
        mission = cls.from_items(items, source=source)
        if fence is not None:
            mission.fence = fence
            mission.__post_init__()
        return mission


# -- helpers ---------------------------------------------------------------------------


def _plan_items(m: dict, source: str) -> list[MissionItem]:
    """A plan's ``mission`` as mission items: its planned home (seq 0, lat/lon degrees, alt m), then
    its SimpleItems."""
    home = m.get("plannedHomePosition")
    if not (isinstance(home, list) and len(home) == 3 and all(isinstance(x, (int, float)) for x in home)):
        raise MissionFileError(f"{source}: mission.plannedHomePosition must be [lat, lon, alt]")
    items = [
        MissionItem(
            seq=0,
            frame=MAV_FRAME_GLOBAL,
            command=MAV_CMD_NAV_WAYPOINT,
            lat=float(home[0]),
            lon=float(home[1]),
            alt=float(home[2]),
        )
    ]
    for i, it in enumerate(m["items"]):
        items.append(_plan_simple_item(it, len(items), f"{source}: mission.items[{i}]"))
    return items


def _plan_simple_item(it: Any, seq: int, where: str) -> MissionItem:
    """Mission item ``seq`` from a plan's SimpleItem ``it`` (its 7 params: None = NaN); ``where`` names
    it in errors."""
    if not isinstance(it, dict):
        raise MissionFileError(f"{where}: not an object")
    if it.get("type") != "SimpleItem":
        raise MissionFileError(
            f"{where}: item type {it.get('type')!r} is not supported (only SimpleItem; "
            "convert surveys/patterns to waypoints in QGroundControl first)"
        )
    try:
        params = [math.nan if v is None else float(v) for v in it["params"]]
        if len(params) != 7:
            raise ValueError(f"params needs 7 values, got {len(params)}")
        return MissionItem(
            seq=seq,
            frame=int(it["frame"]),
            command=int(it["command"]),
            autocontinue=int(bool(it.get("autoContinue", True))),
            param1=params[0],
            param2=params[1],
            param3=params[2],
            param4=params[3],
            lat=params[4],
            lon=params[5],
            alt=params[6],
        )
    except KeyError as exc:
        raise MissionFileError(f"{where}: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise MissionFileError(f"{where}: {exc}") from None


def _plan_fence(d: dict, source: str) -> np.ndarray | None:
    """A plan's geofence: its one inclusion polygon's vertices (lat/lon degrees), or None."""
    gf = d.get("geoFence") or {}
    polys = gf.get("polygons", []) if isinstance(gf, dict) else None
    if not isinstance(polys, list):
        raise MissionFileError(f"{source}: geoFence.polygons must be a list")
    if gf.get("circles") if isinstance(gf, dict) else None:
        raise MissionFileError(f"{source}: geoFence circles are not supported (use one inclusion polygon)")
    incl = [pg for pg in polys if isinstance(pg, dict) and pg.get("inclusion", True)]
    if len(incl) != len(polys) or len(polys) > 1:
        raise MissionFileError(f"{source}: only one inclusion fence polygon is supported, got {len(polys)} polygon(s)")
    if polys:
        return _latlon_array(polys[0].get("polygon"), f"{source}: geoFence polygon vertices")
    return None


def _num(v) -> str:
    """Shortest text that reads back as the same number (repr of a float, int as int)."""
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return str(int(v))
    f = float(v)
    return str(int(f)) if f.is_integer() and abs(f) < 1e15 else repr(f)


def _read_text(p: Path) -> str:
    try:
        return p.read_text()
    except FileNotFoundError:
        raise MissionFileError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MissionFileError(f"{p}: cannot read ({exc})") from None


def _parse_wpl(text: str, source: str) -> list[MissionItem]:
    numbered = [(n, ln) for n, ln in enumerate(text.splitlines(), start=1) if ln.strip()]
    if not numbered or not numbered[0][1].strip().startswith("QGC WPL"):
        raise MissionFileError(f"{source}: not a QGC WPL file (first line must be '{WPL_HEADER}')")
    if numbered[0][1].split()[-1] != "110":
        raise MissionFileError(
            f"{source}: unsupported WPL version {numbered[0][1].strip()!r} (expected '{WPL_HEADER}')"
        )
    items = []
    for n, ln in numbered[1:]:
        if ln.lstrip().startswith("#"):  # comment lines, as pymavlink's mavwp writes them
            continue
        f = ln.split()
        if len(f) != 12:
            raise MissionFileError(f"{source}: line {n}: expected 12 fields, got {len(f)}")
        try:
            ints = [int(f[i]) for i in (0, 1, 2, 3, 11)]
            fl = [float(x) for x in f[4:11]]
        except ValueError as exc:
            raise MissionFileError(f"{source}: line {n}: {exc}") from None
        items.append(
            MissionItem(
                seq=ints[0],
                current=ints[1],
                frame=ints[2],
                command=ints[3],
                autocontinue=ints[4],
                param1=fl[0],
                param2=fl[1],
                param3=fl[2],
                param4=fl[3],
                lat=fl[4],
                lon=fl[5],
                alt=fl[6],
            )
        )
    return items


def _fence_from_items(items: list[MissionItem], source: str) -> np.ndarray | None:
    if not items:
        return None
    items = sorted(items, key=lambda it: it.seq)
    bad = [it.command for it in items if it.command != MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION]
    if bad:
        raise MissionFileError(
            f"{source}: fence command {bad[0]} is not supported (only inclusion polygon vertices, 5001)"
        )
    k = int(round(items[0].param1))
    if k != len(items) or any(int(round(it.param1)) != k for it in items):
        raise MissionFileError(
            f"{source}: fence vertices say {k} per polygon but {len(items)} were given "
            "(only one inclusion polygon is supported)"
        )
    return np.array([(it.lat, it.lon) for it in items], dtype=np.float64)
