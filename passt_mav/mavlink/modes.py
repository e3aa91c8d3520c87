"""ArduPilot Rover's flight modes by name and number: a leaf of the MAVLink client (no project imports), so the
mission client and the vehicle (:mod:`passt_mav.mavlink.vehicle`, which re-exports them) both import it."""

from __future__ import annotations

__all__ = ["ROVER_MODES", "ROVER_MODE_NAMES"]

#: ArduPilot Rover 4.x custom modes (pymavlink still lists LEARNING = 2; Rover no longer has it)
ROVER_MODES = {
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
ROVER_MODE_NAMES = {v: k for k, v in ROVER_MODES.items()}
