"""Boat physics and the current sensor against closed-form answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from simclient import SimClient

import geo
from passt_mav.fields import FlowField
from vehicle_sim import MODES, BoatParams, CurrentModel, SimConfig, Simulator
from vehicle_sim.boat import BoatState, guidance, step_boat

HOME = (40.0, -63.0)
M_PER_DEG_LAT = 111_035.0  # WGS84 meridian arc per degree near 40 N (pyproj: 111034.6)


def uniform_field(u, v, half_deg=0.05, n=5):
    grid = geo.RegionGrid(HOME[0] - half_deg, HOME[1] - half_deg, HOME[0] + half_deg, HOME[1] + half_deg, n, n)
    data = np.zeros((2, 2, n, n), np.float32)
    data[:, 0], data[:, 1] = u, v
    return FlowField(data, grid, np.array([0.0, 86400.0]), time_origin="2020-01-01T00:00:00Z")


def sim_with(field=None, nav="pursuit", **kw):
    cfg = SimConfig.fast(boat=BoatParams(nav=nav), **kw)
    sim = Simulator(field, home=HOME, config=cfg)
    sim.run_until(2.0)
    return sim, SimClient(sim)


def go(sim, c, north_m, dt=0.1):
    lat = HOME[0] + north_m / M_PER_DEG_LAT
    assert c.upload([SimClient.waypoint(0, *HOME), SimClient.waypoint(1, lat, HOME[1])]).type == 0
    assert c.arm().result == 0
    assert c.set_mode(MODES["AUTO"]).result == 0
    t0 = sim.t
    track = []
    while sim.autopilot.mission_state != "complete" and sim.t - t0 < 2000:
        sim.step(dt)
        track.append((sim.t - t0, sim.autopilot.boat.x, sim.autopilot.boat.y))
    return sim.t - t0, np.array(track)


def test_zero_current_1km_takes_1000_over_wp_speed():
    sim, c = sim_with()
    t, _ = go(sim, c, 1000.0)
    assert t == pytest.approx(1000.0 / 2.0, rel=0.05)
    assert t == pytest.approx((1000.0 - 2.0) / 2.0, abs=2.0)  # tighter: minus WP_RADIUS, plus the 0.5 s speed lag


def _pursuit_offset(r, a, k):
    """Offset (m) across the leg of a pursuit boat at distance ``r`` (m) from the waypoint (see below)."""
    s = (a / r) ** (2 * k)
    return r * (s - 1) / (s + 1)


def test_cross_current_uncompensated_follows_the_pursuit_curve():
    """Bow on the waypoint, current w across the leg, speed V held over ground along the bow (Rover's
    speed controller: ground velocity projected on the heading; the hull makes up the rest).

    The ground velocity is then V toward the waypoint plus the current's component across the bow,
    so the distance r to the waypoint shrinks at exactly V (the leg takes (a - WP_RADIUS) / V) and the
    bearing angle theta off the leg obeys r dtheta/dr = -k / cos(theta), k = w/V: sec + tan = (a/r)^k,
    i.e. the offset is y = r tanh(k ln(a/r)) = r (s - 1)/(s + 1), s = (a/r)^(2k).
    """
    a, V, w = 500.0, 2.0, 0.5
    k = w / V
    sim, c = sim_with(uniform_field(w, 0.0))
    t, track = go(sim, c, a)
    assert t == pytest.approx((a - 2.0) / V, abs=2.0)  # WP_RADIUS 2 m, plus the 0.5 s speed lag
    rr = np.linspace(1.0, a, 20000)
    assert track[:, 1].max() == pytest.approx(_pursuit_offset(rr, a, k).max(), rel=0.03)  # drift east, down-current
    # the whole curve, at a few distances from the waypoint
    for frac in (0.8, 0.5, 0.2):
        r = np.hypot(track[:, 1], a - track[:, 2])
        i = np.argmin(np.abs(r / a - frac))
        assert track[i, 1] == pytest.approx(_pursuit_offset(r[i], a, k), abs=1.5)


def test_cross_current_crosstrack_option_holds_the_line():
    """Crabbing on the line with V held over ground along the bow: the steady heading phi off the line has
    V sin(phi) + w cos(phi)^2 = 0 (no ground velocity across the line), and the speed along the line is
    (V - w sin(phi)) cos(phi): 2.058 m/s for V = 2, w = 0.5 (the hull runs 2.12 m/s through the water)."""
    a, V, w = 500.0, 2.0, 0.5
    sim, c = sim_with(uniform_field(w, 0.0), nav="crosstrack")
    t, track = go(sim, c, a)
    assert np.abs(track[:, 1]).max() < 2.0
    s = (V - math.sqrt(V * V + 4 * w * w)) / (2 * w)  # sin(phi): root of w s^2 - V s - w = 0 in [-1, 0]
    along = (V - w * s) * math.sqrt(1 - s * s)
    assert along == pytest.approx(2.058, abs=0.001)
    assert t == pytest.approx(a / along, rel=0.02)


def test_manual_drifts_with_the_current():
    sim, c = sim_with(uniform_field(0.3, -0.2))
    assert c.arm().result == 0  # armed in MANUAL, no RC input: no thrust
    x0, y0 = sim.autopilot.boat.x, sim.autopilot.boat.y
    sim.step(100.0)
    b = sim.autopilot.boat
    assert (b.x - x0, b.y - y0) == pytest.approx((30.0, -20.0), abs=0.3)


@pytest.mark.parametrize(("before", "drift_m"), [("MANUAL", 60.0), ("LOITER", 50.0)])
def test_hold_drifts_with_the_current(before, drift_m):
    """HOLD stops the motor (Rover's mode_hold.cpp: throttle 0): in a uniform 0.5 m/s current flowing west
    (SITL's SIM_TIDE_DIR 90: the water comes from the east) 120 s of HOLD carry a boat that was already
    drifting (armed in MANUAL, no RC input) 60 m west; one that was keeping station in LOITER first has to
    pick the current up against its hull's drag (BoatParams.coast_drag_per_m) and goes ~50 m. Rover 4.7
    SITL: 60.0 m and 49.9 m (tests/test_sitl_current.py). Tolerance +- 5 m."""
    sim, c = sim_with(uniform_field(-0.5, 0.0))
    assert c.arm().result == 0
    if before == "LOITER":
        assert c.set_mode(MODES["LOITER"]).result == 0
    sim.step(60.0)
    assert c.set_mode(MODES["HOLD"]).result == 0
    x0, y0 = sim.autopilot.boat.x, sim.autopilot.boat.y
    sim.step(120.0)
    b = sim.autopilot.boat
    assert b.x - x0 == pytest.approx(-drift_m, abs=5.0)
    assert abs(b.y - y0) < 1.0


def test_motor_off_coasts_like_the_sitl_hull():
    """With the motor off the hull slows by quadratic drag alone, dv/dt = -k v^2 (k = 0.25 /m): from 5 m/s
    v(t) = 5 / (1 + 1.25 t); Rover 4.7 SITL's motorboat (HOLD after 5 m/s in still water) read 1.54, 0.83 and
    0.37 m/s after 2, 4 and 10 s and had coasted 18.7 m after 60 s (here ln(1 + 75) / 0.25 = 17.3 m)."""
    p = BoatParams()
    s = BoatState(speed=5.0)
    got = {}
    for k in range(600):
        step_boat(s, 0.0, 3.0, (0.0, 0.0), 0.1, p, motor_off=True)  # cmd_speed ignored with the motor off
        got[round((k + 1) * 0.1, 1)] = (s.speed, s.y)
    for t, sitl_v in ((2.0, 1.54), (4.0, 0.83), (10.0, 0.37)):
        assert got[t][0] == pytest.approx(5.0 / (1 + 1.25 * t), rel=0.01)
        assert got[t][0] == pytest.approx(sitl_v, abs=0.12)
    assert got[60.0][1] == pytest.approx(math.log(1 + 0.25 * 5 * 60) / 0.25, rel=0.02)  # 0.1 s steps
    assert got[60.0][1] == pytest.approx(18.7, abs=2.0)


@pytest.mark.parametrize("mode", ["LOITER", "CIRCLE"])
def test_loiter_keeps_station_against_current(mode):
    """LOITER (and CIRCLE, as the simulator plays it) keep the boat within LOIT_RADIUS (2 m) plus one
    overshoot; Rover 4.7 SITL in a 0.5 m/s current: 1.7 m after 120 s, 2.7 m at most."""
    sim, c = sim_with(uniform_field(0.6, 0.3))
    assert c.arm().result == 0
    assert c.set_mode(MODES[mode]).result == 0
    x0, y0 = sim.autopilot.boat.x, sim.autopilot.boat.y
    dmax = 0.0
    for _ in range(3000):
        sim.step(0.1)
        b = sim.autopilot.boat
        dmax = max(dmax, math.hypot(b.x - x0, b.y - y0))
    assert dmax < 2.0 + 1.0  # LOIT_RADIUS 2 m plus what one overshoot at 0.67 m/s adds
    assert dmax > 1.0  # it does drift inside the circle (motor off there)


def test_loiter_in_a_uniform_current_stays_within_twice_loit_radius():
    """120 s of LOITER in a uniform 0.5 m/s current (SITL's SIM_TIDE_SPEED 0.5, SIM_TIDE_DIR 90): the boat
    stays within 2 x LOIT_RADIUS (2 m) of where LOITER began."""
    sim, c = sim_with(uniform_field(-0.5, 0.0))
    assert c.arm().result == 0
    assert c.set_mode(MODES["LOITER"]).result == 0
    x0, y0 = sim.autopilot.boat.x, sim.autopilot.boat.y
    dmax = 0.0
    for _ in range(1200):
        sim.step(0.1)
        b = sim.autopilot.boat
        dmax = max(dmax, math.hypot(b.x - x0, b.y - y0))
    assert 1.0 < dmax < 2 * 2.0


def test_disarmed_in_auto_drifts():
    sim, c = sim_with(uniform_field(0.0, 0.5))
    c.set_mode(MODES["AUTO"])
    y0 = sim.autopilot.boat.y
    sim.step(20)
    assert sim.autopilot.boat.y - y0 == pytest.approx(10.0, abs=0.1)


def linear_field():
    """u, v linear in lon/lat and time: bilinear + linear-in-time interpolation is exact."""
    n = 6
    grid = geo.RegionGrid(HOME[0] - 0.01, HOME[1] - 0.01, HOME[0] + 0.01, HOME[1] + 0.01, n, n)
    lats, lons = grid.centres_latlon()
    times = np.array([0.0, 600.0, 1200.0])
    data = np.zeros((3, 2, n, n), np.float32)
    for i, tt in enumerate(times):
        data[i, 0] = 0.2 + 10.0 * (lons - HOME[1]) + tt / 6000.0
        data[i, 1] = -0.1 + 15.0 * (lats - HOME[0]) - tt / 12000.0
    return FlowField(data, grid, times, time_origin="2020-01-01T00:00:00Z")


def _samples(c):
    gpi = {m.time_boot_ms: m for _, m in c.log if m.get_type() == "GLOBAL_POSITION_INT"}
    cu = {m.time_boot_ms: m.value for _, m in c.log if m.get_type() == "NAMED_VALUE_FLOAT" and m.name == "CUR_U"}
    cv = {m.time_boot_ms: m.value for _, m in c.log if m.get_type() == "NAMED_VALUE_FLOAT" and m.name == "CUR_V"}
    out = []
    for ms in sorted(cu):
        assert ms in cv and ms in gpi, "CUR_U/CUR_V without a GLOBAL_POSITION_INT at the same time_boot_ms"
        g = gpi[ms]
        out.append((ms / 1000.0, g.lat / 1e7, g.lon / 1e7, cu[ms], cv[ms]))
    return np.array(out)


def _run_survey(sim, c):
    items = [SimClient.waypoint(0, *HOME)] + [
        SimClient.waypoint(i + 1, HOME[0] + d[0], HOME[1] + d[1])
        for i, d in enumerate([(0.003, 0.0), (0.003, 0.004), (-0.002, 0.004)])
    ]
    assert c.upload(items).type == 0
    c.arm()
    c.set_mode(MODES["AUTO"])
    c.collect(300.0, dt=0.1)


def test_current_sensor_reads_the_field_at_the_boat():
    field = linear_field()
    sim, c = sim_with(field)
    _run_survey(sim, c)
    s = _samples(c)
    assert len(s) >= 295  # 1 Hz
    truth = field.sample_latlon(s[:, 0], s[:, 1], s[:, 2])  # start_time = first snapshot = 0
    assert np.abs(s[:, 3] - truth[:, 0]).max() < 1e-4
    assert np.abs(s[:, 4] - truth[:, 1]).max() < 1e-4
    assert np.ptp(s[:, 3]) > 0.05  # the boat did see a varying field


def test_current_sensor_noise_is_seeded_gaussian():
    field = linear_field()
    runs = []
    for _ in range(2):
        sim, c = sim_with(field, current_noise_std=0.05, seed=7)
        _run_survey(sim, c)
        runs.append(_samples(c))
    s = runs[0]
    np.testing.assert_array_equal(runs[0], runs[1])  # same seed, same readings
    truth = field.sample_latlon(s[:, 0], s[:, 1], s[:, 2])
    res = np.concatenate([s[:, 3] - truth[:, 0], s[:, 4] - truth[:, 1]])
    assert res.std() == pytest.approx(0.05, rel=0.15)
    assert abs(res.mean()) < 0.01


def test_gps_noise_moves_the_reported_fix_not_the_measurement():
    """With GPS noise the sensor still measures where the boat is; only the fix it is paired with is off
    (by ~gps_noise_m), and the current noise (same seed) is unchanged: the two generators are separate."""
    field = linear_field()
    runs = []
    for gps in (0.0, 4.0):
        sim, c = sim_with(field, current_noise_std=0.05, seed=7, gps_noise_m=gps)
        _run_survey(sim, c)
        runs.append((_samples(c), sim))
    (a, _), (b, _sim_b) = runs
    n = min(len(a), len(b))
    np.testing.assert_array_equal(a[:n, 3:], b[:n, 3:])  # same readings: same true track, same current noise
    d_north = (b[:n, 1] - a[:n, 1]) * 111_000.0
    d_east = (b[:n, 2] - a[:n, 2]) * 111_000.0 * np.cos(np.radians(HOME[0]))
    err = np.concatenate([d_north, d_east])
    # ~300 s with a 60 s correlation time: ~10 independent values per axis, so a loose band around 4 m
    assert 1.5 < err.std() < 7.0 and np.abs(err).max() < 25.0


def test_metric_field_rotation_velocity_and_time_scale():
    g = geo.MetricRegionGrid(
        0.0, 10.0, 0.0, 10.0, 11, 11, anchor_lat=HOME[0], anchor_lon=HOME[1], rotation_deg=90.0, scale=50.0
    )
    data = np.zeros((2, 2, 11, 11), np.float32)
    data[0, 0] = 0.0
    data[1, 0] = 1.0  # u ramps 0 -> 1 (inflow direction) over one time unit
    field = FlowField(data, g, np.array([0.0, 1.0]), None, "1")
    cm = CurrentModel(field, velocity_scale=0.5, time_scale=10.0)
    u, v = cm.at(
        5.0, HOME[0], HOME[1]
    )  # field time 0.5 -> u_data = 0.5; x 0.5 m/s per unit; rotated 90 deg CCW -> north
    assert (u, v) == pytest.approx((0.0, 0.25), abs=1e-9)
    # clamped in time: after the last snapshot it holds the last one
    assert cm.at(1000.0, HOME[0], HOME[1]) == pytest.approx((0.0, 0.5), abs=1e-9)
    # outside the region (a 500 m square): still water
    assert cm.at(5.0, HOME[0] + 0.01, HOME[1]) == (0.0, 0.0)


def test_missing_cells_are_still_water():
    f = uniform_field(0.4, 0.0)
    f.data[:, :, 2, 2] = np.nan
    cm = CurrentModel(f)
    assert cm.at(0.0, HOME[0], HOME[1]) == (0.0, 0.0)
    lat, lon = f.grid.cell_to_latlon(0, 0)
    assert cm.at(0.0, float(lat), float(lon)) == pytest.approx((0.4, 0.0))


def test_turn_rate_limit_and_speed_lag():
    p = BoatParams(max_turn_rate_dps=30.0, speed_tau_s=1.0, max_accel=10.0)
    s = BoatState(heading=0.0)
    for _ in range(10):
        step_boat(s, math.pi / 2, 2.0, (0.0, 0.0), 0.1, p)
    assert math.degrees(s.heading) == pytest.approx(30.0, abs=1e-6)
    assert s.speed == pytest.approx(2.0 * (1 - math.exp(-1.0)), rel=1e-6)
    h, sp = guidance(BoatState(x=0, y=0), (10.0, 10.0), 2.0, (0, 0), p)
    assert math.degrees(h) == pytest.approx(45.0) and sp == 2.0


def test_scalar_current_sampler_matches_flowfield_interp():
    rng = np.random.default_rng(0)
    f = linear_field()
    f.data[:] += rng.normal(0, 0.3, f.data.shape).astype(np.float32)
    f.data[1, :, 2, 3] = np.nan
    cm = CurrentModel(f)
    R, C = f.grid.shape
    ts = np.concatenate([rng.uniform(-100, 1300, 400), f.times])
    rs = np.concatenate([rng.uniform(-0.5, R - 0.5, 400), [0, R - 1, 0]])
    cs = np.concatenate([rng.uniform(-0.5, C - 0.5, 400), [C - 1, 0, 0]])
    for t, r, c in zip(ts, rs, cs):
        ref = f.interp(t, r, c)
        got = cm._interp1(float(t), float(r), float(c))
        if np.isnan(ref).any():
            assert np.isnan(got).any()
        else:
            assert got == pytest.approx(tuple(ref), abs=1e-9)
