"""Mission controller, ready for a real boat: the field clock from the vehicle's UTC, a link lost
during the leg swap, an autopilot that reboots mid-leg (resume, or HOLD), and ``resume`` after the
controller died in a later leg (the state reloaded from the run directory's estimate).

Same setting as tests/test_controller.py (8x8 grid of ~40 m cells, persistence, greedy legs of 3
moves, simulator served in-process at 50x). The wave field's time origin is 2020-01-01T00:00:00Z.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np
import pytest
from mavlink_helpers import served
from test_controller import controller, mission, sim_config, wave_field
from test_controller_faults import _modes

from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.errors import UserError
from passt_mav.fields.field import load_field
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore
from passt_mav.vehicle.controller import utc_epoch

AUTO, HOLD, LOITER = 10, 4, 5
ORIGIN = utc_epoch("2020-01-01T00:00:00Z")
LEAN = {"stream_rates_hz": LEAN_STREAMS}


def _when(ctl, cond, timeout: float = 20.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return False


def _in_leg(ctl, leg: int, reached: int = 1):
    return lambda: (
        ctl.collector is not None
        and ctl.collector.leg == leg
        and ctl.vehicle.mode == AUTO
        and len(ctl.vehicle.progress.reached) >= reached
    )


# -- field time from UTC ---------------------------------------------------------------------------
def test_field_time_from_the_vehicles_utc(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    rd = RunDir(tmp_path / "run").create()
    # the vehicle booted at 2020-01-01T00:05:00Z: field time 300 s at boot
    with served(sim_config(), field=field, start_time=300.0, epoch0=ORIGIN + 300.0, link_kw=LEAN) as (_sim, link):
        ctl = controller(cfg, field, link, rd, echo=None, field_time_at_boot=None)
        summary = ctl.run()
    clk = summary["clock"]
    assert clk["source"] == "utc" and clk["t_boot0"] == pytest.approx(300.0, abs=0.01)
    leg = summary["legs"][0]
    assert 300.0 <= leg["t_start"] < 300.0 + 60.0  # planned at the vehicle's hour (snapshot 15), not at t0
    # the samples, mapped through the UTC clock, agree with the field the sensor measured (noise 0.01)
    with SampleStore(rd.samples_db, readonly=True) as st:
        recs = st.for_leg(0)
    t = 300.0 + np.array([r.time_boot_ms for r in recs]) / 1000.0
    truth = field.sample_latlon(t, [r.lat for r in recs], [r.lon for r in recs])
    meas = np.array([(r.u, r.v) for r in recs])
    assert np.sqrt(np.nanmean((meas - np.asarray(truth).reshape(meas.shape)) ** 2)) < 0.03


def test_utc_clock_required_but_the_vehicle_has_none_is_a_one_line_error(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    cfg = cfg.model_copy(update={"field": cfg.field.model_copy(update={"clock": "utc"})})
    rd = RunDir(tmp_path / "run").create()
    with served(sim_config(utc_clock=False), field=field, link_kw=LEAN) as (_sim, link):
        ctl = controller(cfg, field, link, rd, echo=None, field_time_at_boot=None)
        with pytest.raises(UserError, match="field.clock is utc but the vehicle sends no UTC"):
            ctl.run()


def test_auto_clock_falls_back_to_boot_and_says_why(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    rd = RunDir(tmp_path / "run").create()
    lines: list[str] = []
    with served(sim_config(), field=field, link_kw=LEAN) as (_sim, link):  # UTC = now: years after the field
        ctl = controller(cfg, field, link, rd, echo=lines.append, field_time_at_boot=None)
        summary = ctl.run()
    assert summary["status"] == "complete" and summary["clock"]["source"] == "boot"
    assert summary["clock"]["t_boot0"] == 0.0
    assert any("lies outside the field's snapshots" in s for s in lines)


# -- the link dies during the leg swap --------------------------------------------------------------
def test_link_lost_during_the_swap_reconnects_and_redoes_the_swap(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=2)
    rd = RunDir(tmp_path / "run").create()
    with served(sim_config(), field=field, link_kw=LEAN) as (sim, link):
        ctl = controller(cfg, field, link, rd, echo=None)
        mc = ctl.vehicle.mission
        orig = mc.upload
        calls = {"n": 0}

        def upload(items, *a, **k):  # leg 2's first upload: the transport dies after MISSION_COUNT went out
            calls["n"] += 1
            if ctl.collector.leg is None and len(ctl.leg_records) == 1 and calls.setdefault("cut", 0) == 0:
                calls["cut"] = 1
                link.conn.mav.mission_count_send(1, 1, len(items), 0)
                link.conn.close()
            return orig(items, *a, **k)

        mc.upload = upload
        summary = ctl.run()
        stored = sim.autopilot.store.count(0)
    assert summary["status"] == "complete" and [x["index"] for x in summary["legs"]] == [0, 1]
    ev = " | ".join(summary["events"])
    assert "link lost during the swap" in ev and calls["cut"] == 1
    assert stored == len(summary["legs"][1]["waypoints"]) + 2  # home + speed + leg 2's waypoints
    assert summary["legs"][1]["n_samples"] > 5


# -- the autopilot reboots mid-leg ------------------------------------------------------------------
@contextlib.contextmanager
def _reboot_mid_leg(field, cfg, rd, action=None, **ctl_kw):
    """(sim, link, ctl, faults): a controller on the simulator in lockstep (:func:`test_resilience.flight`)
    whose autopilot reboots (``action(sim)``; default a 2 s restart) once leg 0 flies in AUTO past its second
    item on a verified mission: the fault is fired from the simulator's stepping at that mission event
    (:class:`test_resilience.Faults`), never from a wall-clock thread, so a loaded machine cannot let the leg
    end before it."""
    from test_resilience import Faults, _chaos_controller, _flying, flight

    act = action or (lambda sim: sim.reboot(downtime_s=2.0))
    with flight(field, link_kw={"timeout_s": 1.0}) as (sim, link, box):
        faults = Faults(sim, box)
        ctl = _chaos_controller(box, cfg, field, link, rd, **ctl_kw)
        faults.at("reboot", _flying(box, 0, 2), lambda: act(sim))
        yield sim, link, ctl, faults


def test_reboot_mid_leg_is_not_a_pilot_resumes_at_the_interrupted_item(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=2)
    rd = RunDir(tmp_path / "run").create()
    lines: list[str] = []
    with _reboot_mid_leg(field, cfg, rd, echo=lines.append, pause_timeout_s=5.0) as (sim, link, ctl, faults):
        modes = _modes(link)  # (a miss of the reboot fails fast: 5 s paused)
        summary = ctl.run()
        boots = sim.autopilot.boot_count
    assert list(faults.fired) == ["reboot"]
    assert boots == 1 and summary["status"] == "complete" and len(summary["legs"]) == 2
    ev = " | ".join(summary["events"])
    assert "vehicle rebooted" in ev and "resumed after the reboot at item" in ev and "stored mission verified" in ev
    from passt_mav.runs.live import read_events

    kinds = [e["kind"] for e in read_events(rd.root)[0]]  # the live view's alerts (issue 29)
    assert kinds.index("reboot") < kinds.index("reboot_recovered") and "pilot_takeover" not in kinds
    assert "left AUTO" not in ev and not any("pilot has control" in s for s in lines)
    assert "speed not set again" not in ev  # DO_CHANGE_SPEED (item 1, behind the resumed item) sent as a command
    assert 16 in modes  # it really came back INITIALISING
    item = int(ev.split("resumed after the reboot at item ")[1].split("/")[0])
    assert item >= 3  # two waypoints were reached before the reboot: it did not start over at 1
    # samples of both boots are stored, the later ones under boot 1, and the leg's GP used them
    with SampleStore(rd.samples_db, readonly=True) as st:
        leg0 = st.for_leg(0)
    assert {s.boot for s in leg0} == {0, 1}
    assert summary["clock"]["later_boots"] and summary["clock"]["later_boots"][0] > 0
    assert summary["legs"][0]["rmse_passt"] is not None


def test_reboot_that_lost_the_mission_re_uploads_it_then_resumes(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    rd = RunDir(tmp_path / "run").create()

    def lost(sim):
        sim.reboot(downtime_s=1.0)
        sim.autopilot.store.clear(0)  # the eeprom lost the mission (home stays)

    with _reboot_mid_leg(field, cfg, rd, lost, echo=None, pause_timeout_s=5.0) as (sim, _link, ctl, faults):
        summary = ctl.run()
        stored = sim.autopilot.store.count(0)
    assert list(faults.fired) == ["reboot"] and summary["status"] == "complete"
    ev = " | ".join(summary["events"])
    assert "resumed after the reboot at item" in ev and "(mission re-uploaded)" in ev
    assert stored == len(summary["legs"][0]["waypoints"]) + 2


def test_reboot_mid_leg_with_on_reboot_hold_stops_in_hold(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=2, vehicle={"speed_mps": 5.0, "wp_radius_m": 3.0, "on_reboot": "hold"})
    rd = RunDir(tmp_path / "run").create()
    with _reboot_mid_leg(field, cfg, rd, echo=None, pause_timeout_s=5.0) as (sim, _link, ctl, faults):
        summary = ctl.run()
        assert list(faults.fired) == ["reboot"]
        assert sim.autopilot.mode == LOITER and not sim.autopilot.armed  # its wait_mode
    assert summary["status"] == "paused" and summary["legs"] == []
    assert "on_reboot is 'hold': stopped in LOITER" in summary["events"][-1]


# -- resume after the controller died in a later leg --------------------------------------------------
@pytest.mark.parametrize("reboot_between", [False, True], ids=["same_boot", "vehicle_rebooted_meanwhile"])
def test_resume_after_a_kill_in_leg_2_reloads_the_estimate_and_keeps_samples(tmp_path, reboot_between):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=3)
    rd = RunDir(tmp_path / "run").create()
    with served(sim_config(), field=field, link_kw=LEAN) as (sim, link):
        ctl = controller(cfg, field, link, rd, echo=None)
        fly = ctl._fly

        def dying_fly(i, *a):  # the process dies mid-leg 2 (index 1) once samples of it are stored
            if i == 1:
                _when(ctl, lambda: ctl.store.count(1) >= 3)
                raise KeyboardInterrupt("killed")
            return fly(i, *a)

        ctl._fly = dying_fly
        with pytest.raises(KeyboardInterrupt):
            ctl.run()
        assert rd.read_leg(1)["status"] == "flying" and rd.read_leg(0)["status"] == "complete"
        with SampleStore(rd.samples_db, readonly=True) as st:
            before = {(s.time_boot_ms, s.boot) for s in st.for_leg(1)}
        est0 = load_field(rd.estimate_file(0)).data[0]
        if reboot_between:  # the autopilot restarts while no controller runs: its clock starts again at 0
            sim.reboot(downtime_s=1.0)
            _when(ctl, lambda: sim.autopilot.t > 3.0 and not link.lost, 10)
        lines: list[str] = []
        ctl2 = controller(cfg, field, link, rd, echo=lines.append, resume=True)
        seen = {}
        plan = ctl2.loop.plan_leg

        def spy(state, *a, **k):  # the state the resumed run plans leg 2 from
            seen.setdefault("state", np.array(state))
            return plan(state, *a, **k)

        ctl2.loop.plan_leg = spy
        summary = ctl2.run()
    assert summary["status"] == "complete" and [x["index"] for x in summary["legs"]] == [0, 1, 2]
    assert any("resuming" in s and "1 leg(s) done" in s for s in lines)
    assert any(e.startswith("resumed after leg 1") for e in summary["events"])
    # planned from leg 0's estimate (persistence: the forecast to now is the estimate itself)
    np.testing.assert_allclose(seen["state"], est0, rtol=0, atol=1e-6, equal_nan=True)
    with SampleStore(rd.samples_db, readonly=True) as st:
        after = {(s.time_boot_ms, s.boot) for s in st.for_leg(1)}
        leg2 = st.for_leg(2)
    assert len(before) >= 3 and before <= after  # the interrupted flight's samples count for the re-flown leg
    assert summary["legs"][1]["n_samples"] >= len(after)
    # the resumed session numbers its boots after the stored ones: a rebooted vehicle's new times
    # cannot collide with (and be dropped as duplicates of) the first session's
    assert {b for _, b in before} == {0} and {b for _, b in after} == {0, 1}
    assert {s.boot for s in leg2} == {1} and len(leg2) > 5
    rebooted = any("rebooted since the run stopped" in e for e in summary["events"])
    assert rebooted == reboot_between
    if reboot_between:  # the boot clock continues from the last sample (the time off is not counted)
        assert summary["clock"]["later_boots"][0] > summary["clock"]["t_boot0"]


def test_collector_counts_a_reboot_and_keeps_the_new_boots_readings_apart():
    from pymavlink.dialects.v20 import ardupilotmega as M

    from passt_mav.mavlink import SampleCollector

    out, seen = [], []
    c = SampleCollector(out.append, on_reboot=lambda *a: seen.append(a))

    def reading(tb, u):
        c.handle(M.MAVLink_global_position_int_message(tb, 400000000, -630000000, 0, 0, 0, 0, 0, 0))
        c.handle(M.MAVLink_named_value_float_message(tb, b"CUR_U", u))
        c.handle(M.MAVLink_named_value_float_message(tb, b"CUR_V", 0.0))

    c.handle(M.MAVLink_system_time_message(int((1.6e9 + 10.0) * 1e6), 10_000))
    reading(10_000, 0.1)
    reading(12_000, 0.2)
    c.handle(M.MAVLink_global_position_int_message(9_000, 0, 0, 0, 0, 0, 0, 0, 0))  # 3 s back: not yet a reboot
    assert seen == []
    c.handle(M.MAVLink_global_position_int_message(50, 0, 0, 0, 0, 0, 0, 0, 0))  # rebooted, no fix yet
    assert seen == [(1, 12_000, 50)] and c.boot == 1
    c.handle(M.MAVLink_system_time_message(int((1.6e9 + 40.0) * 1e6), 2_000))
    reading(10_000, 0.3)  # the same time_boot_ms as before the reboot: a new reading, not a duplicate
    assert [(r["time_boot_ms"], r["boot"], r["u"]) for r in out] == [
        (10_000, 0, 0.1),
        (12_000, 0, 0.2),
        (10_000, 1, 0.3),
    ]
    assert c.boots[0]["utc_boot"] == pytest.approx(1.6e9) and c.boots[1]["utc_boot"] == pytest.approx(1.6e9 + 38.0)
