"""Every exception passt_mav raises on purpose, in one place.

``PasstError`` is the root. Subclasses of :class:`UserError` describe bad input
(a file, an option, a mission config): the command line prints their message as
one line and exits with code 2. Anything else is a bug or an environment failure.

Tree::

    PasstError
    ├── UserError                      (exit code 2 on the command line)
    │   ├── FieldError                 bad field data or field file
    │   ├── MissionConfigError         bad mission YAML (names the key)
    │   ├── MissionFileError           bad .waypoints / .plan file
    │   ├── ModelError                 bad checkpoint / predictor name / shape
    │   └── PlannerError               bad planner name / reward map / start cell
    ├── ReconstructionError            GP fit failed (message says what to change)
    └── MavlinkError                   anything on the link
        ├── LinkTimeout                no answer in time (link lost or vehicle silent)
        │   └── LinkUnavailable        no vehicle at the address (refused, unreachable, no device,
        │                              no heartbeat) until the deadline: exit code 2 on the command line
        ├── MissionRejected(result)    MISSION_ACK other than ACCEPTED
        ├── MissionVerifyError         read-back differs from what was uploaded
        ├── CommandRejected(cmd, result, text)  COMMAND_ACK other than ACCEPTED
        └── VehicleNotReady            EKF/GPS not ready, not armable, ...

``geo.GeoError`` (a ``ValueError``) lives in ``geo`` because ``geo`` may not import
passt_mav; the command line treats it as a user error too.
"""

from __future__ import annotations

__all__ = [
    "PasstError",
    "UserError",
    "FieldError",
    "MissionConfigError",
    "MissionFileError",
    "ModelError",
    "PlannerError",
    "ReconstructionError",
    "MavlinkError",
    "LinkTimeout",
    "LinkUnavailable",
    "MissionRejected",
    "MissionVerifyError",
    "CommandRejected",
    "VehicleNotReady",
]


class PasstError(Exception):
    """Root of passt_mav's exceptions."""


class UserError(PasstError, ValueError):
    """Bad input from the user: one-line message, exit code 2."""


class FieldError(UserError):
    """A flow field or field file is invalid."""


class MissionConfigError(UserError):
    """A mission configuration (YAML) is invalid; the message names the key."""


class MissionFileError(UserError):
    """A waypoint file (.waypoints WPL 110 or QGC .plan) is invalid."""


class ModelError(UserError):
    """A predictor/checkpoint is invalid or does not fit the data."""


class PlannerError(UserError):
    """A planner/reward request is invalid."""


class ReconstructionError(PasstError):
    """GP reconstruction failed; the message says what to change."""


class MavlinkError(PasstError):
    """Something went wrong on the MAVLink link."""


class LinkTimeout(MavlinkError):
    """No answer within the allowed time."""


class LinkUnavailable(LinkTimeout):
    """The vehicle could not be reached at its address (refused, unreachable, no such serial device,
    nothing there sends a vehicle heartbeat); the message names the address and the cause."""


class MissionRejected(MavlinkError):
    """The vehicle answered a mission transfer with a MISSION_ACK other than ACCEPTED."""

    def __init__(self, result: int, name: str | None = None, detail: str = ""):
        self.result = int(result)
        self.name = name or f"MAV_MISSION_RESULT {result}"
        msg = f"vehicle rejected the mission: {self.name} ({self.result})"
        super().__init__(msg + (f": {detail}" if detail else ""))


class MissionVerifyError(MavlinkError):
    """The mission read back from the vehicle differs from the one uploaded."""


class CommandRejected(MavlinkError):
    """A COMMAND_LONG was answered with a result other than ACCEPTED."""

    def __init__(self, command: int | str, result: int, text: str = ""):
        self.command, self.result, self.text = command, int(result), text
        super().__init__(f"command {command} refused (result {result})" + (f": {text}" if text else ""))


class VehicleNotReady(MavlinkError):
    """The vehicle cannot do what was asked yet (EKF, GPS, arming checks)."""
