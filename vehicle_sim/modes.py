"""ArduPilot Rover's flight modes as the simulator plays them: the custom-mode numbers (Rover 4.x) and
the sets of modes that need an absolute position, keep station or take RC input.

HOLD is not a station-keeping mode: Rover's ``mode_hold.cpp`` sets throttle 0 and centres the steering,
so a boat in HOLD drifts with the current (shared/ARDUPILOT_ROVER.md); LOITER keeps station inside
``LOIT_RADIUS``. AUTO keeps station in its loiter submode (vehicle_sim.autopilot)."""

from __future__ import annotations

__all__ = ["MODES", "MODE_NAMES", "SETTABLE", "NEEDS_POSITION", "STATION_KEEPING", "MANUAL_INPUT"]

#: mode name -> HEARTBEAT custom_mode (ArduPilot Rover)
MODES = {
    "MANUAL": 0,
    "ACRO": 1,
    "STEERING": 3,
    "HOLD": 4,
    "LOITER": 5,
    "FOLLOW": 6,
    "SIMPLE": 7,
    "DOCK": 8,
    "CIRCLE": 9,
    "AUTO": 10,
    "RTL": 11,
    "SMART_RTL": 12,
    "GUIDED": 15,
    "INITIALISING": 16,
}
MODE_NAMES = {v: k for k, v in MODES.items()}
SETTABLE = frozenset(v for k, v in MODES.items() if k != "INITIALISING")
NEEDS_POSITION = frozenset(
    MODES[k] for k in ("AUTO", "GUIDED", "LOITER", "RTL", "SMART_RTL", "CIRCLE", "FOLLOW", "DOCK")
)
#: modes that keep the boat inside LOIT_RADIUS of where they began (HOLD drifts: motor off)
STATION_KEEPING = frozenset(MODES[k] for k in ("LOITER", "CIRCLE", "FOLLOW", "DOCK"))
MANUAL_INPUT = frozenset(MODES[k] for k in ("MANUAL", "ACRO", "STEERING"))
