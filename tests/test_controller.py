"""The mission controller end to end against vehicle_sim served in-process at high speed-up.

Setting: an 8x8 grid of ~40 m cells around the test HOME, a current that changes
everywhere at once (see :func:`wave_field`) sampled every 20 s, a 5 m/s boat flying
legs of 3 moves (~25-35 s, 1-2 snapshots per leg), sensor noise 0.01 m/s. The
predictor is *persistence*, which cannot follow the change: the pure model drifts,
and PASST re-initialised from the samples must beat it.

Speed-up 50: the simulated vehicle's mission-transfer timers (1 s re-request, 8 s
cancel) run in simulated time, so at 50x a request must be answered within ~20 ms
of wall time; above ~100x on two loaded cores uploads start to be cancelled.
"""

from __future__ import annotations

import numpy as np
import pytest
from mavlink_helpers import HOME, served, vehicle

import geo
from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.fields import FlowField
from passt_mav.mavlink.mission_client import rover_stored
from passt_mav.mission.config import validate_mission
from passt_mav.mission.waypoints import WaypointMission
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore
from passt_mav.vehicle.controller import FieldClock, MissionController, build_predictor, thin_samples, to_field_units
from vehicle_sim import SimConfig

SPEEDUP = 50.0  # the vehicle's mission-transfer timers run in sim time: see the module docstring
NOISE = 0.01
N = 8
DLAT, DLON = 0.00036, 0.00047  # ~40 m cells at 40 deg N


def wave_field() -> FlowField:
    """A current that changes everywhere at once (period 2400 s: monotonic over the ~200 s mission),
    plus fixed spatial structure: persistence drifts away from it, a few samples correct it."""
    grid = geo.RegionGrid(
        HOME[0] - DLAT * (N - 1) / 2,
        HOME[1] - DLON * (N - 1) / 2,
        HOME[0] + DLAT * (N - 1) / 2,
        HOME[1] + DLON * (N - 1) / 2,
        N,
        N,
    )
    # one hour: a 3-leg run takes ~1000 s of vehicle time, more on a loaded machine (the sim's
    # clock runs on while the controller plans and uploads); samples after the field's end have
    # no truth to be compared with (1200 s left 10 % of them out once under load)
    times = np.arange(0.0, 3600.0 + 1, 20.0)
    rr, cc = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    data = np.zeros((len(times), 2, N, N), np.float32)
    for k, t in enumerate(times):
        w = np.sin(2 * np.pi * t / 2400.0)
        data[k, 0] = 0.2 + 0.4 * w + 0.1 * np.sin(2 * np.pi * cc / N)
        data[k, 1] = -0.3 * w + 0.1 * np.cos(2 * np.pi * rr / N)
    return FlowField(data, grid, times, time_origin="2020-01-01T00:00:00Z")


def mission(tmp_path, field, **over) -> object:
    path = tmp_path / "wave.nc"
    if not path.exists():
        field.to_netcdf(path)
    g = field.grid
    data = {
        "name": "wave",
        "region": {"south": g.south, "west": g.west, "north": g.north, "east": g.east, "rows": N, "cols": N},
        "field": {"source": str(path)},
        "model": "persistence",
        "planner": {"name": "greedy", "path_length": 3},
        "legs": 3,
        "t0": 0,
        "vehicle": {"speed_mps": 5.0, "wp_radius_m": 3.0},
        "sensors": {"noise_std": NOISE},
        "geofence_margin_m": 30.0,
        "gp": {"hyper": "first_leg"},
    }
    data.update(over)
    return validate_mission(data, source="test")


def sim_config(**kw) -> SimConfig:
    return SimConfig.fast(params=(("WP_SPEED", 5.0),), current_noise_std=NOISE, current_rate_hz=1.0, seed=3, **kw)


def controller(cfg, field, link, rd, **kw) -> MissionController:
    pred, info = build_predictor(cfg.model, field, echo=lambda s: None)
    kw.setdefault("echo", print)
    kw.setdefault("field_time_at_boot", 0.0)
    return MissionController(
        cfg,
        link,
        rd,
        field=field,
        predictor=pred,
        predictor_info=info,
        vehicle=vehicle(link),
        speedup_hint=SPEEDUP,
        ready_timeout_s=10.0,
        **kw,
    )


def test_three_leg_mission_samples_uploads_and_rmse(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field)
    rd = RunDir(tmp_path / "run").create()
    raw: dict[int, dict] = {}

    def spy(m):  # what the sim sent, independently of the controller's collector
        name = m.name.rstrip("\x00") if isinstance(m.name, str) else bytes(m.name).decode().rstrip("\x00")
        raw.setdefault(int(m.time_boot_ms), {})[name] = float(m.value)

    readbacks = []
    with served(sim_config(), field=field, speedup=SPEEDUP, link_kw={"stream_rates_hz": LEAN_STREAMS}) as (_sim, link):
        link.add_listener(spy, "NAMED_VALUE_FLOAT")
        ctl = controller(cfg, field, link, rd)
        orig = ctl.vehicle.mission.download
        ctl.vehicle.mission.download = lambda *a, **k: readbacks.append(orig(*a, **k)) or readbacks[-1]
        summary = ctl.run()
        mode_after = ctl.vehicle.mode
    assert summary["status"] == "complete" and len(summary["legs"]) == 3
    # LOITER after the last leg (vehicle.on_end: loiter; a boat in HOLD would drift with the current), armed
    assert mode_after == 5
    assert summary["end"]["on_end"] == "loiter" and summary["end"]["mode"] == "LOITER" and summary["end"]["armed"]
    assert any("run complete: the boat LOITER" in e for e in summary["events"])
    # each leg after the first records the wait before it (LOITER between legs: no drift beyond the radius)
    for leg in summary["legs"][1:]:
        (w,) = leg["waits"]
        assert w["kind"] == "between legs" and w["mode"] == "LOITER" and w["vehicle_s"] > 0
        # within 2 x WP_RADIUS, plus up to one 1 Hz fix of a 5 m/s boat still running down as the wait begins
        assert w["drift_m"] <= 2 * 3.0 + 5.0
    # every uploaded mission, read back from the vehicle, equals the mission of the planned path
    assert len(readbacks) >= 3
    for leg in summary["legs"]:
        want = WaypointMission.from_path(
            field.grid, np.array(leg["path"]), speed=5.0, wp_radius_m=3.0, fence_margin_m=30.0
        ).items()
        # as the vehicle stores it (Rover keeps no acceptance radius etc.: mission_client.rover_stored)
        assert any(
            len(got) == len(want) and all(rover_stored(a).same_as(b) for a, b in zip(want[1:], got[1:]))
            for got in readbacks
        )
        assert leg["t_end"] > leg["t_start"] and leg["n_samples"] > 20
        # every reading is placed on the track (1 Hz fixes, 1 Hz readings): none dropped, all counted
        rd_ = leg["readings"]
        assert rd_["received"] >= leg["n_samples"] and rd_["dropped_gap"] == 0 and rd_["fraction_used"] == 1.0
        # the sim's sensor reads 1 Hz of vehicle time: one reading a second of the leg's vehicle time
        assert rd_["received"] == pytest.approx(leg["duration_vehicle_s"], abs=3)
    assert summary["readings_used"] == [1.0, 1.0, 1.0]
    # the store holds what the sim sent (minus at most one reading in flight at each leg switch)
    store = SampleStore(rd.samples_db, readonly=True)
    recs = store.all()
    store.close()
    tb = np.array([r.time_boot_ms for r in recs])
    assert len(set(tb.tolist())) == len(tb)
    sent = {t for t, h in raw.items() if len(h) == 2}
    assert set(tb.tolist()) <= sent
    # the spy listened from the start; the controller's collector from its run(): compare over its span
    assert len({t for t in sent if tb.min() <= t <= tb.max()} - set(tb.tolist())) <= 3
    # values = the field at the sample's position and (mapped) time, within the sim's noise
    clock = FieldClock(0.0, 1.0)
    truth = field.sample_latlon(clock.field_time(tb), [r.lat for r in recs], [r.lon for r in recs])
    meas = np.array([(r.u, r.v) for r in recs])
    ok = np.isfinite(truth).all(axis=1)
    assert ok.mean() > 0.95
    err = meas[ok] - truth[ok]
    assert np.abs(err).max() < 6 * NOISE and err.std() == pytest.approx(NOISE, rel=0.35)
    # the raw values the sim sent equal the stored ones
    for r in recs[:50]:
        assert raw[r.time_boot_ms]["CUR_U"] == pytest.approx(r.u) and raw[r.time_boot_ms]["CUR_V"] == pytest.approx(r.v)
    # persistence drifts on the moving wave; PASST re-initialised from the samples beats it
    last = summary["legs"][-1]
    assert last["rmse_passt"] < last["rmse_model"]
    # run directory contents
    for i in range(3):
        for f in (
            rd.waypoints_file(i),
            rd.plan_file(i),
            rd.estimate_file(i),
            rd.prediction_file(i),
            rd.timings_file(i),
        ):
            assert f.exists(), f
        wpl = WaypointMission.from_wpl(rd.waypoints_file(i))  # WPL holds no fence: compare the waypoints
        assert np.allclose(wpl.waypoints, summary["legs"][i]["waypoints"], atol=1e-7) and wpl.speed == 5.0
    assert rd.read_summary()["rmse"]["passt"] == [x["rmse_passt"] for x in summary["legs"]]


def test_thinning_averages_per_cell_and_snapshot_bin():
    field = wave_field()
    g = field.grid
    lat, lon = g.cell_to_latlon(np.array([2, 2, 2, 5]), np.array([3, 3, 3, 1]))
    t = np.array([0.0, 5.0, 30.0, 1.0])  # bins: 0, 0, 2 (dt 20 -> round(1.5)=2), 0
    s = thin_samples(g, t, lat, lon, [1.0, 3.0, 5.0, 7.0], [0.0, 1.0, 2.0, 3.0], t_start=0.0, dt=20.0)
    got = sorted(zip(s.r.round(6), s.c.round(6), s.t, s.u, s.v))
    assert got == [(2.0, 3.0, 2.5, 2.0, 0.5), (2.0, 3.0, 30.0, 5.0, 2.0), (5.0, 1.0, 1.0, 7.0, 3.0)]


def test_clock_and_units():
    c = FieldClock(300.0, 200.0)  # the scaled cylinder: 200 s per field time unit
    assert c.field_time(40_000) == pytest.approx(300.0 + 40.0 / 200.0)
    mg = geo.MetricRegionGrid(0, 9, 0, 9, 10, 10, anchor_lat=40, anchor_lon=-63, rotation_deg=30.0, scale=10.0)
    u, v = mg.velocity_to_local(0.4, -0.2)
    back = to_field_units(mg, 0.5 * u, 0.5 * v, velocity_scale=0.5)
    assert np.allclose(back, (0.4, -0.2))


def test_vehicle_outside_region_refused_before_any_upload(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field)
    rd = RunDir(tmp_path / "run").create()
    far = (HOME[0] + 0.02, HOME[1])  # ~2 km north of the region
    from mavlink_helpers import inprocess_factory, link_config

    from passt_mav.errors import UserError
    from passt_mav.mavlink import Link
    from vehicle_sim import Simulator

    sim = Simulator(field, home=far, config=sim_config())
    link = Link(link_config(stream_rates_hz=LEAN_STREAMS), connection_factory=inprocess_factory(sim))
    sim.serve([], speedup=SPEEDUP)
    try:
        link.connect()
        ctl = controller(cfg, field, link, rd)
        with pytest.raises(UserError, match="outside the mission region"):
            ctl.run()
        assert ctl.vehicle.mode != 10 and sim.autopilot.store.count(0) == 1  # home only: nothing uploaded
    finally:
        link.close()
        sim.stop()
    assert rd.read_summary()["status"] == "aborted"


def test_leg_deadline_counts_vehicle_time_not_wall_time(monkeypatch):
    """A starved simulator runs slower than its speed-up: the leg's limit is in vehicle seconds, the wall
    clock only backs it up (ten times more generous); after a reboot what was left counts again."""
    import time as _time

    from passt_mav.vehicle.controller import _Deadline

    class FakeLink:
        up = 100.0

        def vehicle_uptime_s(self):
            return self.up

    now = [1000.0]
    monkeypatch.setattr(_time, "monotonic", lambda: now[0])
    link = FakeLink()
    d = _Deadline(link, budget_s=60.0, speedup=20.0)  # 60 vehicle s = 3 wall s at the nominal speed-up
    now[0] += 20.0  # 20 wall s pass but the vehicle only lived 10 s: not late
    link.up = 110.0
    assert not d.passed()
    link.up = 161.0  # 61 vehicle s: late, whatever the wall clock says
    assert d.passed()
    d2 = _Deadline(link, budget_s=60.0, speedup=20.0)
    link.up = 200.0
    assert not d2.passed()
    link.up = 5.0  # rebooted 39 vehicle s into the leg: 21 s of budget left from its new clock
    d2.extend(2.0, rebooted=True)
    link.up = 25.0
    assert not d2.passed()
    link.up = 27.0
    assert d2.passed()
    d3 = _Deadline(link, budget_s=60.0, speedup=20.0)
    assert not d3.wall_passed()
    now[0] += 10 * 60.0 / 20.0 + 60.0 + 1.0  # past the old backstop, but a clock standing still for 91 s only
    assert not d3.passed()
    now[0] += _Deadline.STALL_WALL_S  # the vehicle's clock stopped: the wall back-up fires
    assert d3.passed()
    assert d3.stalled_s > _Deadline.STALL_WALL_S


def test_leg_deadline_backstop_ignores_a_vehicle_slower_than_its_hint(monkeypatch):
    """A lockstep simulator on a loaded machine runs far slower than ``--speedup-hint`` (60x for a hint of
    2000): its legs are timed by its own clock, and the wall backstop fires only for a clock that stopped."""
    import time as _time

    from passt_mav.vehicle.controller import _Deadline

    class FakeLink:
        up = 0.0

        def vehicle_uptime_s(self):
            return self.up

    now = [0.0]
    monkeypatch.setattr(_time, "monotonic", lambda: now[0])
    link = FakeLink()
    d = _Deadline(link, budget_s=600.0, speedup=2000.0)  # old backstop: 10 x 0.3 s + 60 s = 63 wall s
    for _ in range(590):  # 590 wall s at 1 vehicle s per wall s: 3.3 % of the hint
        now[0] += 1.0
        link.up += 1.0
        assert not d.passed()
    link.up += 11.0  # 601 vehicle s: the leg's own limit
    assert d.vehicle_passed() and not d.wall_passed()
