"""Missions: validated YAML mission configs, waypoint missions and their files.

* :class:`MissionItem` (``items.py``) - one MAVLink mission item, shared with
  :mod:`passt_mav.mavlink`.
* :class:`WaypointMission` (``waypoints.py``) - a leg's waypoints with ArduPilot's
  seq-0 home rule, QGC WPL 110 and QGroundControl ``.plan`` export/import.
* :func:`load_mission` / :class:`MissionConfig` (``config.py``) - the mission YAML.

Only ``items`` and ``waypoints`` are imported eagerly (numpy); the config module
(pydantic, yaml) is loaded on first use of its names.
"""

from __future__ import annotations

from passt_mav.mission.items import MissionItem
from passt_mav.mission.waypoints import WaypointMission

__all__ = ["MissionItem", "WaypointMission", "MissionConfig", "load_mission"]


def __getattr__(name: str):
    if name in ("MissionConfig", "load_mission"):
        from passt_mav.mission import config

        return getattr(config, name)
    raise AttributeError(f"module 'passt_mav.mission' has no attribute {name!r}")
