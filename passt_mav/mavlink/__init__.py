"""The controller's MAVLink layer: link, mission protocol client, vehicle control, samples.

Written to shared/ARDUPILOT_ROVER.md (ArduPilot Rover 4.x, boat frame), independently
of ``vehicle_sim``. Importing this package imports pymavlink (MAVLink 2 is selected
first); command-line modules import it inside ``run``.

    from passt_mav.mavlink import Link, LinkConfig, MissionClient, Vehicle, SampleCollector, with_home

    link = Link(LinkConfig("tcp:127.0.0.1:5760")).connect()
    vehicle = Vehicle(link)
    vehicle.mission.upload_verified(with_home(waypoints))
    vehicle.wait_ready(); vehicle.arm(); vehicle.start_mission()
    vehicle.wait_mission_complete(len(waypoints))   # then HOLD
"""

from passt_mav.mavlink.link import (
    DEFAULT_SOURCE_COMPONENT,
    DEFAULT_SOURCE_SYSTEM,
    Link,
    LinkConfig,
    LinkStats,
    Subscription,
    result_name,
    secret_from_key,
)
from passt_mav.mavlink.mission_client import MissionClient, MissionWatch, UploadResult, from_msg, to_msg, with_home
from passt_mav.mavlink.samples import SampleCollector
from passt_mav.mavlink.vehicle import ROVER_MODE_NAMES, ROVER_MODES, MissionProgress, Vehicle, mode_number

__all__ = [
    "Link",
    "LinkConfig",
    "LinkStats",
    "Subscription",
    "result_name",
    "secret_from_key",
    "DEFAULT_SOURCE_SYSTEM",
    "DEFAULT_SOURCE_COMPONENT",
    "MissionClient",
    "MissionWatch",
    "UploadResult",
    "with_home",
    "to_msg",
    "from_msg",
    "Vehicle",
    "MissionProgress",
    "ROVER_MODES",
    "ROVER_MODE_NAMES",
    "mode_number",
    "SampleCollector",
]
