"""Differential test in a current: ArduPilot Rover 4.7 SITL (``SIM_TIDE_DIR`` 90, ``SIM_TIDE_SPEED`` 0.5)
against vehicle_sim in a uniform field of the same current, one scripted flight each (plain pymavlink).

The current: 0.5 m/s flowing **west** (SITL's ``SIM_TIDE_DIR`` is where the water comes *from*, like wind:
90 = from the east; vehicle_sim ``uniform_current=(-0.5, 0.0)`` east/north m/s). Both boats have the motorboat's
navigation parameters (WP_SPEED 5 m/s, WP_RADIUS 3 m; LOIT_RADIUS 2 m). Positions are local east/north metres
from GLOBAL_POSITION_INT (equirectangular about the first fix; < 1 cm error over these few hundred metres);
times are the vehicle's own (``time_boot_ms``), so machine load does not change them (vehicle_sim is served in
the controller-driven lockstep: its clock runs only for the steps the script asks for when it has nothing to
read, :meth:`test_sitl_differential.Peer.step`).

The flight, after the vehicle is ready and armed (both boats have drifted with the current since boot):

1. HOLD for 120 s: the motor is off (Rover's ``mode_hold.cpp``), the boat drifts down-current.
2. LOITER for 120 s: the boat keeps station inside LOIT_RADIUS.
3. HOLD for 120 s again, now from a standstill against the current: the hull has to pick the current up
   against its drag, so the drift is shorter (vehicle_sim: ``BoatParams.coast_drag_per_m``).
4. A mission laid out as passt_mav lays it out (home, DO_CHANGE_SPEED 2 m/s at seq 1, then NAV_WAYPOINTs):
   four 200 m legs west, east, west, east. AUTO without anything else: legs 1-2 fly at WP_SPEED, because a
   boat enters AUTO in its loiter submode and the DO_CHANGE_SPEED before the first waypoint goes there
   (``ModeAuto::_enter``/``set_desired_speed``) and is lost. When leg 3 starts: LOITER, AUTO again and at once
   a COMMAND_LONG DO_CHANGE_SPEED 2 m/s (what the controller's leg swap now sends after AUTO): legs 3-4 at 2.

Each leg's ground speed is measured over its middle 120 m (40 m from either end). Rover holds the *ground*
speed along the bow (``AR_AttitudeControl::get_forward_speed``), so with and against the current it is the
same; the hull makes up the difference through the water (2.5 m/s against, 1.5 m/s with, at 2 m/s): a
DO_CHANGE_SPEED of 2 m/s gives 2 m/s over ground, not through the water.

Measured on Rover 4.7 SITL at speedup 50 (the ``sitl`` case re-measures on every run where the build is
present; :data:`FIRMWARE` holds the numbers; three runs): HOLD 120 s drifted 60.0-60.1 m west (north 0.0 m);
LOITER 120 s stayed within 2.7 m of its start; HOLD after LOITER drifted 48.8-49.9 m west (north -3.1 to +0.4 m,
depending on where the loiter left the bow); legs 1-4: 4.98-5.00, 4.99-5.02, 1.98-2.01, 1.98-2.01 m/s over
ground. vehicle_sim: HOLD 59.9 m west; LOITER <= 1.5 m; HOLD after LOITER 50.3 m; legs 4.99, 4.99, 2.00, 2.00.

Tolerances (each vehicle against :data:`FIRMWARE`): HOLD drifts +- 5 m west, +- 4 m north; LOITER at most
2 x LOIT_RADIUS = 4 m from its start at any time; each leg's ground speed +- 0.3 m/s.
"""

from __future__ import annotations

import contextlib
import math
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as M
from test_sitl_differential import Peer

from vehicle_sim import SimConfig, Simulator

HOME = (40.0, -63.0)
TIDE_MPS = 0.5  # SIM_TIDE_SPEED; SIM_TIDE_DIR 90: from the east, the boat drifts west
SPEEDUP = 50
STEP_S = 0.2  # vehicle seconds per lockstep step of vehicle_sim (position reports come at 1 Hz)
HOLD_S = LOITER_S = 120.0
LEG_M = 200.0
MISSION_SPEED = 2.0  # m/s, DO_CHANGE_SPEED param2
WP_SPEED = 5.0  # motorboat.parm
M_PER_DEG = 111_319.49  # equatorial metres per degree (lon scaled by cos(lat))

#: what Rover 4.7 SITL measured (module docstring); ground speeds are east-positive m/s
FIRMWARE = {
    "hold_drift": (-60.0, 0.0),  # (east, north) m in HOLD_S
    "hold_after_loiter_drift": (-49.4, 0.0),  # two runs: (-49.9, -3.1), (-48.8, +0.4)
    "loiter_max_m": 2.7,
    "leg_speeds": (-5.0, 5.0, -2.0, 2.0),  # legs 1-2 at WP_SPEED (seq-1 DO_CHANGE_SPEED lost), 3-4 commanded
}
TOL = {"hold_east_m": 5.0, "hold_north_m": 4.0, "loiter_max_m": 2 * 2.0, "speed_mps": 0.3}


class Boat(Peer):
    """A pymavlink connection, the vehicle's clock (s, from time_boot_ms) and its GLOBAL_POSITION_INT track."""

    def __init__(self, conn, wall_limit_s: float, idle_sleep_s: float, step_s: float = 0.0):
        super().__init__(conn, wall_limit_s, idle_sleep_s, step_s)
        self.origin: tuple[float, float] | None = None
        self.track: list[tuple[float, float, float]] = []  # (t s, east m, north m)
        self.ekf_flags = 0
        self.seq = -1  # MISSION_CURRENT.seq

    def _seen(self, m) -> None:
        typ = m.get_type()
        if typ == "GLOBAL_POSITION_INT" and (m.lat or m.lon):
            lat, lon = m.lat / 1e7, m.lon / 1e7
            if self.origin is None:
                self.origin = (lat, lon)
            la0, lo0 = self.origin
            self.track.append(
                (
                    m.time_boot_ms / 1000.0,
                    (lon - lo0) * M_PER_DEG * math.cos(math.radians(la0)),
                    (lat - la0) * M_PER_DEG,
                )
            )
        elif typ == "EKF_STATUS_REPORT":
            self.ekf_flags = m.flags
        elif typ == "MISSION_CURRENT":
            self.seq = m.seq

    def run_for(self, seconds: float) -> None:
        end, wall_end = self.t + seconds, time.monotonic() + self.wall_limit_s
        while self.t < end:
            if time.monotonic() > wall_end:
                raise AssertionError(f"vehicle clock stalled at {self.t:.1f} s")
            self.recv()

    def command(self, cmd: int, *params) -> int:
        ps = list(params) + [0.0] * (7 - len(params))
        self.send(M.MAVLink_command_long_message(1, 1, cmd, 0, *ps))
        return int(self.wait("COMMAND_ACK", lambda m: m.command == cmd, timeout=5, what=f"ACK {cmd}").result)

    def set_param(self, name: str, value: float) -> None:
        self.send(M.MAVLink_param_set_message(1, 1, name.encode(), float(value), M.MAV_PARAM_TYPE_REAL32))
        self.wait("PARAM_VALUE", lambda m: m.param_id == name, timeout=5, what=f"PARAM_VALUE {name}")

    def wait_ready(self) -> None:
        end = self.t + 150.0
        while not (self.ekf_flags & 16 and not self.ekf_flags & 128 and self.track):
            self.wait(("EKF_STATUS_REPORT", "GLOBAL_POSITION_INT"), timeout=max(end - self.t, 0.1), what="readiness")

    def arm(self) -> None:
        # Rover arms and disarms in the same tick when its loop stalls 0.2 s of its time (CPU failsafe; a
        # sped-up SITL on a loaded machine): arm again, as passt_mav.mavlink.Vehicle.arm does
        for _ in range(8):
            accepted = self.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
            if accepted and self.wait("HEARTBEAT", timeout=5).base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED:
                return
            self.run_for(1.0)
        raise AssertionError("the vehicle did not stay armed")

    def mode(self, custom_mode: int) -> None:
        assert self.command(M.MAV_CMD_DO_SET_MODE, 1, custom_mode) == M.MAV_RESULT_ACCEPTED
        self.wait("HEARTBEAT", lambda m: m.custom_mode == custom_mode, timeout=5, what=f"mode {custom_mode}")

    def here(self) -> tuple[float, float, float]:
        """(t, east, north) of the next position report."""
        self.wait("GLOBAL_POSITION_INT", lambda m: m.lat or m.lon, timeout=5, what="a position")
        return self.track[-1]

    def upload(self, items) -> int:
        self.send(M.MAVLink_mission_count_message(1, 1, len(items), 0))
        while True:
            m = self.wait(("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"), timeout=10, what="upload reply")
            if m.get_type() == "MISSION_ACK":
                return int(m.type)
            self.send(items[m.seq])


def _wp(seq: int, lat: float, lon: float):
    return M.MAVLink_mission_item_int_message(
        1, 1, seq, 3, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, int(round(lat * 1e7)), int(round(lon * 1e7)), 0, 0
    )


def _leg_speed(track, t0: float, t1: float, x_start: float, x_end: float) -> float:
    """Mean ground speed east (m/s) over the leg's middle: samples in [t0, t1] farther than 40 m from both ends."""
    lo, hi = sorted((x_start, x_end))
    mid = [(t, x) for t, x, _ in track if t0 <= t <= t1 and lo + 40.0 <= x <= hi - 40.0]
    assert len(mid) >= 5, f"too few samples on the leg ({len(mid)})"
    return (mid[-1][1] - mid[0][1]) / (mid[-1][0] - mid[0][0])


def fly(b: Boat) -> dict:
    """The flight of the module docstring; returns the measurements (keys of :data:`FIRMWARE`)."""
    b.wait("HEARTBEAT", timeout=10)
    b.wait_ready()
    b.arm()
    out: dict = {}
    # 1. HOLD: drift
    b.mode(4)
    t0, x0, y0 = b.here()
    b.run_for(HOLD_S)
    t1, x1, y1 = b.here()
    k = HOLD_S / (t1 - t0)  # reports come at 1 Hz: scale to exactly HOLD_S
    out["hold_drift"] = ((x1 - x0) * k, (y1 - y0) * k)
    # 2. LOITER: keep station
    b.mode(5)
    t0, x0, y0 = b.here()
    b.run_for(LOITER_S)
    out["loiter_max_m"] = max(math.hypot(x - x0, y - y0) for t, x, y in b.track if t >= t0)
    # 3. HOLD again, from a standstill against the current: the hull has to pick the current up
    b.mode(4)
    t0, x0, y0 = b.here()
    b.run_for(HOLD_S)
    t1, x1, y1 = b.here()
    k = HOLD_S / (t1 - t0)
    out["hold_after_loiter_drift"] = ((x1 - x0) * k, (y1 - y0) * k)
    # 4. the legs: west, east, west, east from where the boat is
    _, xs, ys = b.here()
    la0, lo0 = b.origin
    lat = la0 + ys / M_PER_DEG
    lon_of = lambda x: lo0 + x / (M_PER_DEG * math.cos(math.radians(la0)))  # noqa: E731
    xw, xe = xs - LEG_M, xs
    ends = [xw, xe, xw, xe]
    items = [_wp(0, lat, lon_of(xs))]
    items.append(M.MAVLink_mission_item_int_message(1, 1, 1, 2, 178, 0, 1, 1, MISSION_SPEED, -1, 0, 0, 0, 0, 0))
    items += [_wp(2 + i, lat, lon_of(x)) for i, x in enumerate(ends)]
    assert b.upload(items) == M.MAV_MISSION_ACCEPTED
    b.mode(10)
    starts = {2: b.t}
    b.wait("MISSION_CURRENT", lambda m: m.seq == 4, timeout=200, what="leg 3")  # legs 1-2 done
    starts[4] = b.t
    b.mode(5)  # leave AUTO and come back: the speed is WP_SPEED again (wp_nav.init), then the command sets it
    b.mode(10)
    assert b.command(M.MAV_CMD_DO_CHANGE_SPEED, 1, MISSION_SPEED, -1) == M.MAV_RESULT_ACCEPTED
    b.wait("STATUSTEXT", lambda m: m.text.startswith("Mission Complete"), timeout=400, what="Mission Complete")
    t_end = b.t
    xs_from = [xs, xw, xe, xw]
    times = [
        (starts[2], starts[4]),
        (starts[2], starts[4]),
        (starts[4], t_end),
        (starts[4], t_end),
    ]
    speeds = []
    for i in range(4):
        # legs 1 and 3 go west (x decreasing), 2 and 4 east: split each pair of legs at its turning point
        ta, tb = times[i]
        pair = [(t, x, y) for t, x, y in b.track if ta <= t <= tb]
        t_turn = min(pair, key=lambda r: r[1])[0]  # the west end
        window = (ta, t_turn) if i % 2 == 0 else (t_turn, tb)
        speeds.append(_leg_speed(b.track, *window, xs_from[i], ends[i]))
    out["leg_speeds"] = tuple(speeds)
    return out


def check(got: dict) -> list[str]:
    """Where ``got`` is outside the tolerances of :data:`FIRMWARE` ([] = agrees)."""
    bad = []
    for key in ("hold_drift", "hold_after_loiter_drift"):
        (dx, dy), (fx, fy) = got[key], FIRMWARE[key]
        if abs(dx - fx) > TOL["hold_east_m"] or abs(dy - fy) > TOL["hold_north_m"]:
            bad.append(f"{key} ({dx:+.1f}, {dy:+.1f}) m, firmware ({fx:+.1f}, {fy:+.1f})")
    if not got["loiter_max_m"] <= TOL["loiter_max_m"]:
        bad.append(f"LOITER went {got['loiter_max_m']:.1f} m from its start (> 2 x LOIT_RADIUS)")
    for i, (g, f) in enumerate(zip(got["leg_speeds"], FIRMWARE["leg_speeds"])):
        if abs(g - f) > TOL["speed_mps"]:
            bad.append(f"leg {i + 1} ground speed {g:+.2f} m/s, firmware {f:+.2f}")
    return bad


@contextlib.contextmanager
def _sim_boat():
    """A :class:`Boat` on vehicle_sim served in lockstep (stopped on exit)."""
    cfg = SimConfig.fast(params=(("WP_SPEED", WP_SPEED), ("WP_RADIUS", 3.0), ("CRUISE_SPEED", WP_SPEED)))
    sim = Simulator(None, home=HOME, config=cfg, uniform_current=(-TIDE_MPS, 0.0))
    sim.serve([], lockstep=True)
    conn = sim.connect_inprocess().mavlink_connection(source_system=255, source_component=190)
    try:
        yield Boat(conn, wall_limit_s=120.0, idle_sleep_s=0.0, step_s=STEP_S)
    finally:
        conn.close()
        sim.stop()


@pytest.fixture(
    params=[
        "vehicle_sim",
        pytest.param(
            "sitl",
            marks=[
                pytest.mark.sitl,
                pytest.mark.long(
                    reason="a SITL flight of ~10 min vehicle time: ~17 s wall at speedup 50 on an idle machine, more on a busy one"
                ),
            ],
        ),
    ]
)
def boat(request, tmp_path):
    if request.param == "vehicle_sim":
        with _sim_boat() as b:
            yield b
        return
    parm = tmp_path / "tide.parm"
    parm.write_text(f"SIM_TIDE_DIR 90\nSIM_TIDE_SPEED {TIDE_MPS}\n")
    sitl = request.getfixturevalue("sitl_factory")(speedup=SPEEDUP, params=parm)
    conn = sitl.mavlink()
    try:
        yield Boat(conn, wall_limit_s=90.0, idle_sleep_s=0.001)
    finally:
        conn.close()


def test_drift_station_keeping_and_leg_speeds_in_a_current(boat):
    got = fly(boat)
    assert check(got) == [], got


def test_the_check_catches_a_boat_that_holds_station_in_hold():
    """The old vehicle_sim kept station in HOLD (2 m in 120 s) and held speed through the water: the check says so."""
    got = {"hold_drift": (-2.1, 0.3), "loiter_max_m": 2.4, "leg_speeds": (-5.0, 5.0, -2.0, 2.0)}
    got["hold_after_loiter_drift"] = (-1.5, 0.2)
    assert check(got) == [
        "hold_drift (-2.1, +0.3) m, firmware (-60.0, +0.0)",
        "hold_after_loiter_drift (-1.5, +0.2) m, firmware (-49.4, +0.0)",
    ]
    got = {"hold_drift": (-60.0, 0.0), "hold_after_loiter_drift": (-50.0, 1.0), "loiter_max_m": 2.4}
    got["leg_speeds"] = (-2.5, 1.5, -2.0, 2.0)  # water speed held (not ground speed): 2 -+ the current
    assert check(got) == [
        "leg 1 ground speed -2.50 m/s, firmware -5.00",
        "leg 2 ground speed +1.50 m/s, firmware +5.00",
    ]


@pytest.mark.sitl
def test_the_controllers_leg_flies_the_mission_speed_on_the_firmware(tmp_path, sitl_factory):
    """End to end on Rover 4.7 SITL (no current): passt_mav's controller flies one leg of a mission whose
    ``vehicle.speed_mps`` is 2 m/s (the leg's DO_CHANGE_SPEED at seq 1; WP_SPEED is 5). The leg swap sends
    DO_CHANGE_SPEED as a command once AUTO runs, so the boat flies 2 m/s: the median ground speed of
    GLOBAL_POSITION_INT in AUTO (from the run's tlog) was 1.98 m/s; with the command left out it was 4.3 m/s
    (5.0 on the straight). Tolerance +- 0.3 m/s. ~8 s wall at speedup 20."""
    import statistics

    from pymavlink import mavutil
    from test_sitl import still_mission

    from passt_mav.errors import MavlinkError
    from passt_mav.mavlink import Link, LinkConfig, Vehicle
    from passt_mav.runs.rundir import RunDir
    from passt_mav.vehicle.controller import MissionController

    sitl = sitl_factory(speedup=20)
    field, cfg = still_mission(tmp_path)
    assert cfg.vehicle.speed_mps == MISSION_SPEED
    tlog = tmp_path / "flight.tlog"
    link = Link(LinkConfig(sitl.connect, connect_timeout_s=60, tlog=str(tlog))).connect()
    try:
        rd = RunDir(tmp_path / "run").create()
        ctl = MissionController(
            cfg, link, rd, field=field, predictor=None, vehicle=Vehicle(link), speedup_hint=20, ready_timeout_s=120.0
        )
        with pytest.raises(MavlinkError, match="no current samples"):  # SITL has no current sensor here
            ctl.run()
    finally:
        link.close()
    mode, speeds = None, []
    log = mavutil.mavlink_connection(str(tlog))
    while (m := log.recv_match()) is not None:
        if m.get_srcSystem() != 1:
            continue
        if m.get_type() == "HEARTBEAT":
            mode = m.custom_mode
        elif m.get_type() == "GLOBAL_POSITION_INT" and mode == 10:
            speeds.append(math.hypot(m.vx, m.vy) / 100.0)
    assert len(speeds) >= 10
    assert statistics.median(speeds) == pytest.approx(MISSION_SPEED, abs=0.3)
