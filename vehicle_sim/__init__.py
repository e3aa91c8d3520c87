"""An ArduPilot-Rover-compatible MAVLink boat simulator that replays current fields.

Point a ground station or script at it exactly as at ArduPilot SITL
(``vehicle-sim --field builtin:ocean --listen tcp:127.0.0.1:5760``), or drive it
in-process from tests (:class:`Simulator`, lockstep, no sockets).

Package layout: :mod:`~vehicle_sim.boat` (pure kinematics and current sampling),
:mod:`~vehicle_sim.mission_server` (mission protocol), :mod:`~vehicle_sim.autopilot`
(modes, arming, commands, parameters, telemetry, failsafe), :mod:`~vehicle_sim.link`
(framing via pymavlink, signing, impairment, tlog), :mod:`~vehicle_sim.sim`
(clock and transports), :mod:`~vehicle_sim.fleet` (several boats on one field and one
clock, ``vehicle-sim --boats N``), :mod:`~vehicle_sim.inprocess` (a ``mavutil`` connection
class over an in-process link), :mod:`~vehicle_sim.cli` (``vehicle-sim``).
"""

from vehicle_sim.autopilot import MODE_NAMES, MODES, Autopilot
from vehicle_sim.boat import BoatParams, CurrentModel
from vehicle_sim.config import LinkConfig, SimConfig
from vehicle_sim.fleet import Fleet
from vehicle_sim.sim import InProcessEndpoint, Simulator

__all__ = [
    "Simulator",
    "Fleet",
    "SimConfig",
    "LinkConfig",
    "BoatParams",
    "CurrentModel",
    "Autopilot",
    "InProcessEndpoint",
    "MODES",
    "MODE_NAMES",
]
