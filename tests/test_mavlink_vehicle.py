"""Vehicle control against the simulator: readiness, arming, modes, a whole mission."""

from __future__ import annotations

import pytest
from mavlink_helpers import served, vehicle, waypoints
from pymavlink.dialects.v20 import ardupilotmega as M
from pyproj import Geod

from passt_mav.errors import CommandRejected, UserError, VehicleNotReady
from passt_mav.mavlink import ROVER_MODES, mode_number, with_home
from vehicle_sim import SimConfig

GEOD = Geod(ellps="WGS84")
FAST_BOAT = SimConfig.fast(params=(("WP_SPEED", 5.0),))


def test_mode_numbers_follow_rover_4():
    assert mode_number("auto") == 10 and mode_number("HOLD") == 4 and mode_number(15) == 15 and mode_number("11") == 11
    assert ROVER_MODES["INITIALISING"] == 16 and "LEARNING" not in ROVER_MODES
    with pytest.raises(UserError, match="valid"):
        mode_number("LEARNING")


@pytest.mark.parametrize("use_mission_start", [False, True])
def test_three_waypoint_mission_ready_arm_auto_complete_then_hold(use_mission_start):
    with served(FAST_BOAT) as (sim, link):
        v = vehicle(link)
        wps = waypoints([(3e-4, 0.0), (3e-4, 4e-4), (-2e-4, 4e-4)])
        # the boat's true track, every physics step (telemetry fixes arrive at a rate that
        # depends on how the sim thread catches up under load: 5 m/s between 1 Hz fixes)
        true_track = []
        update = sim.autopilot.update

        def update_and_record(h):
            update(h)
            true_track.append(sim.autopilot.position())

        sim.autopilot.update = update_and_record
        v.mission.upload_verified(with_home(wps))
        v.wait_ready(timeout=5)
        v.arm(timeout=5)
        assert v.armed and sim.autopilot.armed
        with link.subscribe("GLOBAL_POSITION_INT") as track:
            v.start_mission(use_mission_start=use_mission_start)
            assert v.mode_name == "AUTO"
            p = v.wait_mission_complete(3, timeout=10)
            fixes = track.drain()
        assert p.reached == [1, 2, 3]
        assert v.mode == ROVER_MODES["HOLD"] and sim.autopilot.mode == ROVER_MODES["HOLD"]
        # the boat really came to the last waypoint: its true closest approach is within
        # WP_RADIUS (2 m) + one physics step at 5 m/s. Its position after HOLD depends on how
        # much simulated time the HOLD command took to arrive at 50x under load, so the
        # closest approach is tested, on the true track rather than on load-dependent fixes.
        assert len(fixes) >= 3
        lats, lons = zip(*true_track)
        _, _, dist = GEOD.inv(lons, lats, [wps[-1].lon] * len(lats), [wps[-1].lat] * len(lats))
        assert min(dist) < 2.0 + 5.0 * FAST_BOAT.physics_dt + 0.05
        assert "Mission Complete" in [t for _, _, t in link.texts]


def test_arm_before_init_is_refused_with_the_statustext():
    with served(SimConfig.fast(arm_ready_s=1e6)) as (sim, link):
        v = vehicle(link)
        with pytest.raises(CommandRejected) as ei:
            v.arm(timeout=0.3)  # keeps retrying "not initialised" until the deadline
        assert ei.value.result == M.MAV_RESULT_FAILED
        assert "Arm: System not initialised" in ei.value.text
        assert not sim.autopilot.armed


def test_arm_retries_while_initialising_then_succeeds():
    with served(SimConfig.fast(arm_ready_s=20.0)) as (sim, link):  # 20 s sim = 0.4 s wall
        v = vehicle(link)
        v.arm(timeout=5)
        assert sim.autopilot.armed and sim.t >= 20.0
        assert any("not initialised" in t for _, t in sim.autopilot.texts)
        v.disarm()
        assert not sim.autopilot.armed and not v.armed


def test_auto_while_armed_before_ekf_ready_is_refused():
    with served(SimConfig.fast(ekf_gps_s=1e6)) as (sim, link):
        v = vehicle(link)
        v.mission.upload(with_home(waypoints([(3e-4, 0.0)])))
        v.arm(timeout=5)
        with pytest.raises(CommandRejected) as ei:
            v.set_mode("AUTO")
        assert ei.value.result == M.MAV_RESULT_FAILED and "Flight mode change failed" in ei.value.text
        assert sim.autopilot.mode != ROVER_MODES["AUTO"]
        with pytest.raises(VehicleNotReady, match="EKF"):
            v.wait_ready(timeout=0.2)
        v.set_mode("HOLD")  # position-free modes still work
        assert v.mode_name == "HOLD"


def _cpu_failsafe(sim, times: int):
    """Make the sim's autopilot behave like ArduPilot Rover whose main loop stalled at arming:
    ACCEPTED, "Throttle armed", then at once "Throttle disarmed" (the CPU failsafe), ``times`` times."""
    real = sim.autopilot.arm
    calls = []

    def arm(link=None, force=False):
        calls.append(sim.t)
        r = real(link, force)
        if r == M.MAV_RESULT_ACCEPTED and len(calls) <= times:
            sim.autopilot.text(link, M.MAV_SEVERITY_INFO, "Throttle armed")
            sim.autopilot.disarm()
            sim.autopilot.text(link, M.MAV_SEVERITY_INFO, "Throttle disarmed")
        return r

    sim.autopilot.arm = arm
    return calls


def test_arm_accepted_then_disarmed_at_once_is_armed_again():
    with served() as (sim, link):
        calls = _cpu_failsafe(sim, times=1)
        v = vehicle(link)
        v.wait_ready(timeout=5)  # an arming before the vehicle is ready is refused (and retried): not counted here
        v.arm(timeout=5)
        assert len(calls) == 2 and sim.autopilot.armed and v.armed


def test_arm_that_never_sticks_fails_after_three_attempts_with_a_clear_message():
    with served() as (sim, link):
        calls = _cpu_failsafe(sim, times=99)
        v = vehicle(link)
        v.wait_ready(timeout=5)  # an arming before the vehicle is ready is refused (and retried): not counted here
        with pytest.raises(CommandRejected, match="accepted arming 3 times but disarmed again"):
            v.arm(timeout=5)
        assert len(calls) == 3 and not sim.autopilot.armed
