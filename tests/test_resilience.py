"""Nothing lost, nothing stopped (issue 46): link outages ridden out, stop signals, overruns, field gaps.

Setting of tests/test_controller.py (8x8 grid of ~40 m cells, persistence, greedy legs of 3 moves, a
5 m/s boat), but the simulator runs in lockstep (:func:`mavlink_helpers.lockstep_connection`): it
advances only while the controller's reader finds nothing to read, so simulated time follows the
controller whatever the machine's load. Outages are the simulator's radio (``LinkConfig.arm_drops``:
seconds of simulated time after the vehicle's first arming, both ways, on every link to it, also the
ones a reconnect opens). Every reading the vehicle sent is in the simulator's own tlog (written before
the radio loses a frame): that is the known answer the store and the controller's accounting are
checked against.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time

import numpy as np
import pytest
from mavlink_helpers import HOME, link_config, lockstep_connection
from test_controller import controller, mission, sim_config, wave_field
from test_controller_faults3 import _in_leg, _when

from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.mavlink import Link
from passt_mav.runs.live import read_events
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore
from passt_mav.vehicle.signals import Stopped, StopSignals, exit_code
from vehicle_sim import LinkConfig as SimLinkConfig
from vehicle_sim import SimConfig, Simulator
from vehicle_sim.boat import BoatParams

AUTO, HOLD = 10, 4
AUTOSTEP_S = 0.05  # simulated seconds per idle poll of the controller's reader


def paced(ep, max_rate: float | None):
    """:func:`lockstep_connection` on ``ep`` whose simulator runs at most ``max_rate`` x the wall clock (an idle
    poll waits ``AUTOSTEP_S / max_rate`` s): the controller notices a lost link after ``link_lost_s`` of wall
    time, so a radio drop of D simulated seconds certainly outlasts that when D > link_lost_s x max_rate.
    A loaded machine only slows the simulator further (the drop lasts longer in wall time)."""
    conn = lockstep_connection(ep, AUTOSTEP_S)
    if max_rate:
        recv = conn.recv

        def recv_paced(n=None):
            data = recv(n)
            if not data:
                time.sleep(AUTOSTEP_S / max_rate)
            return data

        conn.recv = recv_paced
    return conn


@contextlib.contextmanager
def lockstep(
    field,
    *,
    sim_cfg: SimConfig | None = None,
    radio: SimLinkConfig | None = None,
    sim_field="same",
    tlog=None,
    max_rate: float | None = None,
    link_kw: dict | None = None,
):
    """(sim, link, radio) with the simulator in lockstep behind the link (writing the telemetry log ``tlog``;
    ``max_rate``: :func:`paced`); ``radio["cfg"]`` is the impairment of every link the controller opens from
    now on (a test may swap it)."""
    sim = Simulator(field if sim_field == "same" else sim_field, home=HOME, config=sim_cfg or sim_config())
    box = {"cfg": radio}
    link = Link(
        link_config(stream_rates_hz=LEAN_STREAMS, tlog=None if tlog is None else str(tlog), **(link_kw or {})),
        connection_factory=lambda: paced(sim.connect_inprocess(box["cfg"]), max_rate),
    )
    link.connect()
    try:
        yield sim, link, box
    finally:
        link.close()
        sim.stop()


def sent_readings(tlog) -> list[int]:
    """``time_boot_ms`` of every CUR_U reading the simulator sent (its tlog: before the radio's losses)."""
    from pymavlink import mavutil

    out = []
    mlog = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    while (m := mlog.recv_match(type="NAMED_VALUE_FLOAT")) is not None:
        if m.get_srcSystem() == 1 and str(m.name).rstrip("\x00") == "CUR_U":
            out.append(int(m.time_boot_ms))
    return out


def stored(rd) -> list:
    with SampleStore(rd.samples_db, readonly=True) as st:
        return st.all()


# -- 1. outages -----------------------------------------------------------------------------------
def test_outage_of_two_minutes_is_ridden_out_and_the_lost_readings_accounted(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1, vehicle={"speed_mps": 5.0, "wp_radius_m": 3.0})
    rd = RunDir(tmp_path / "run").create()
    tlog = tmp_path / "sim.tlog"
    # 120 s of vehicle time without a frame either way, from 12 s after arming: mid-leg 0 (~30 s)
    radio = SimLinkConfig(arm_drops=((12.0, 120.0),))
    # (at most 100x: the 120 s drop outlasts the 0.5 s wall of link_lost_s however fast the machine)
    with lockstep(field, sim_cfg=sim_config(tlog=str(tlog)), radio=radio, max_rate=100) as (sim, link, _):
        ctl = controller(cfg, field, link, rd, echo=None)
        summary = ctl.run()
        assert ctl.vehicle.mode == HOLD
        armed = sim.autopilot.first_armed_clock
    assert summary["status"] == "complete" and len(summary["legs"]) == 1
    leg = summary["legs"][0]
    (out,) = leg["outages"]
    assert out["back_utc"] is not None and out["during"] == "leg"
    # the vehicle's clock over the outage: the drop's 120 s plus the time to notice it and reconnect
    assert 120.0 <= out["vehicle_s"] < 400.0, out
    assert out["tb_from_s"] <= armed + 12.0 + 1.0 and out["tb_to_s"] >= armed + 132.0
    assert summary["outages"] == [out]
    # every reading the vehicle sent is in the store, or was sent during the outage (and counted lost)
    sent = sent_readings(tlog)
    have = {s.time_boot_ms for s in stored(rd)}
    lost = [t for t in sent if t not in have]
    lo, hi = out["tb_from_s"] * 1000, out["tb_to_s"] * 1000
    flown = [t for t in lost if min(have) <= t <= max(have)]  # (before the leg: the EKF wait, not stored)
    assert all(lo <= t <= hi for t in flown), [t for t in flown if not lo <= t <= hi][:5]
    in_window = [t for t in lost if armed * 1000 + 12000 <= t < armed * 1000 + 132000]
    assert len(in_window) >= 110  # ~1 Hz sensor over the 120 s drop
    rdg = leg["readings"]
    assert rdg["lost_in_outages_vehicle_s"] == pytest.approx(out["vehicle_s"])
    # the controller's count of readings missing from the leg (its gaps at the sensor's spacing): exact
    assert rdg["missing"] == len(flown) >= 110
    kinds = [e["kind"] for e in read_events(rd.root)[0]]
    assert kinds.index("leg_start") < kinds.index("link_lost") < kinds.index("link_back") < kinds.index("leg_end")


def test_outage_past_the_window_stops_cleanly_and_resume_finishes(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=2, vehicle={"speed_mps": 5.0, "wp_radius_m": 3.0, "link_loss_window_s": 120})
    rd = RunDir(tmp_path / "run").create()
    lines: list[str] = []
    # the radio dies for good 12 s after arming: no reconnect can succeed (whatever the machine's speed)
    radio = SimLinkConfig(arm_drops=((12.0, 1e9),))
    with lockstep(field, radio=radio) as (_sim, link, box):
        ctl = controller(cfg, field, link, rd, echo=lines.append)
        summary = ctl.run()
        assert summary["status"] == "paused" and summary["legs"] == []
        assert "link-loss window" in summary["events"][-1] and "--resume" in summary["events"][-1]
        attempts = [s for s in lines if "reconnect attempt" in s]
        assert len(attempts) >= 2 and all("giving up in" in s for s in attempts[:-1])
        (out,) = summary["outages"]
        assert out["back_utc"] is None and out["wall_s"] >= 120 / 50  # the window: 120 vehicle s at hint 50
        assert rd.read_leg(0)["status"] == "flying"  # the leg in flight stays for --resume to re-plan
        # the radio comes back (a new one): --resume continues the run on the same vehicle
        box["cfg"] = None
        link.reconnect(attempts=3)
        ctl2 = controller(cfg, field, link, rd, echo=None, resume=True)
        s2 = ctl2.run()
    assert s2["status"] == "complete" and [x["index"] for x in s2["legs"]] == [0, 1]
    assert any("link-loss window" in e for e in s2["events"])  # the first attempt's events are kept


# -- 2. stop signals --------------------------------------------------------------------------------
def test_stop_signals_raise_once_outside_a_file_write_and_after_it_inside():
    said: list[str] = []
    before = signal.getsignal(signal.SIGINT)  # Python's default, or SIG_IGN in a pytest-xdist worker
    with StopSignals(echo=said.append) as stop:
        with pytest.raises(Stopped) as ei:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # the handler runs at once in the main thread
        assert ei.value.name == "SIGINT" and exit_code(ei.value.signum) == 130
    assert signal.getsignal(signal.SIGINT) is before  # put back
    with StopSignals(echo=said.append) as stop:
        done = []
        with pytest.raises(Stopped) as ei, stop.critical():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            done.append("file written")  # the write is not cut short
        assert done == ["file written"] and ei.value.name == "SIGTERM" and exit_code(ei.value.signum) == 143
        os.kill(os.getpid(), signal.SIGHUP)  # a second signal while stopping: acknowledged only
        time.sleep(0.05)
    assert said[-1].startswith("SIGHUP received: stopping already")


def _signal_when_in_leg(ctl, signum, *, after_reached: int = 1):
    """From a thread: ``signum`` to this process once leg 0 flies in AUTO and has reached an item."""

    def run():
        end = time.monotonic() + 60
        while time.monotonic() < end:
            p = ctl.vehicle.progress
            if ctl.collector is not None and ctl.collector.leg == 0 and len(p.reached) >= after_reached:
                os.kill(os.getpid(), signum)
                return
            time.sleep(0.005)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


@pytest.mark.parametrize("signum, on_signal, mode", [(signal.SIGTERM, "hold", HOLD), (signal.SIGHUP, "auto", AUTO)])
def test_signal_mid_leg_stops_cleanly(tmp_path, signum, on_signal, mode):
    field = wave_field()
    vehicle_cfg = {"speed_mps": 5.0, "wp_radius_m": 3.0, "on_signal": on_signal}
    cfg = mission(tmp_path, field, legs=2, vehicle=vehicle_cfg)
    rd = RunDir(tmp_path / "run").create()
    # (reply timeouts of 1 s wall: the HOLD must not time out on a loaded machine)
    with lockstep(field, link_kw={"timeout_s": 1.0}) as (sim, link, _):
        with StopSignals(echo=lambda s: None) as stop:
            ctl = controller(cfg, field, link, rd, echo=None, signals=stop)
            th = _signal_when_in_leg(ctl, signum)
            summary = ctl.run()
            th.join(5)
        assert stop.received == signum
        time.sleep(0.05)
        assert sim.autopilot.mode == mode  # HOLD, or left flying its leg with on_signal: auto
    name = signal.Signals(signum).name
    s = rd.read_summary()  # written, with the status a supervisor can read
    assert s["status"] == summary["status"] == "stopped" and s["stopped_by"] == name
    assert s["n_samples"] == len(stored(rd)) > 0  # the store flushed: every sample counted is in it
    assert rd.read_leg(0)["status"] == "flying"  # the leg in flight, left for --resume
    ev = read_events(rd.root)[0]
    assert [e["kind"] for e in ev][-2:] == ["stopped", "run_end"] and name in ev[-2]["text"]


# -- 6. overruns ----------------------------------------------------------------------------------------
def test_overrun_leg_is_cut_and_the_next_leg_planned(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=2)
    rd = RunDir(tmp_path / "run").create()
    # a hull that makes 0.5 m/s in still water against the mission's 5 m/s: a leg takes ~10x its plan
    slow = sim_config(boat=BoatParams(max_speed=0.5))
    lines: list[str] = []
    with lockstep(field, sim_cfg=slow, sim_field=None) as (_sim, link, _):
        ctl = controller(cfg, field, link, rd, echo=lines.append)
        summary = ctl.run()
    assert summary["status"] == "complete" and len(summary["legs"]) == 2
    for leg in summary["legs"]:
        o = leg["overrun"]
        assert o is not None and o["factor"] == 2.0 and 1 <= o["cut_at_item"] <= o["items"]
        planned = 2.0 * o["expected_vehicle_s"] + 30.0
        # cut where the rule says: past the planned time, not much later (the 0.1 s wait of the loop)
        assert planned <= leg["duration_vehicle_s"] < planned + 15.0, (planned, leg["duration_vehicle_s"])
        assert leg["n_samples"] > 0
    assert sum("overrun" in s for s in lines) == 2
    assert sum("overrun" in e for e in summary["events"]) == 2


# -- 5. field gaps that come and go ---------------------------------------------------------------------
def test_state_at_fills_a_gap_from_the_nearest_time_never_zero():
    import geo
    from passt_mav.fields import FlowField

    grid = geo.RegionGrid(40.0, -63.0, 40.01, -62.99, 2, 3)
    data = np.arange(5 * 2 * 2 * 3, dtype=np.float32).reshape(5, 2, 2, 3) + 1.0
    data[:, :, 0, 0] = np.nan  # land: missing at every time
    data[2, :, 0, 1] = np.nan  # missing at t=2 only: neighbours 1 and 3 tie, the earlier wins
    data[0:3, :, 1, 2] = np.nan  # missing at t=0..2: nearest with data is t=3
    f = FlowField(data, grid, np.arange(5.0) * 3600, time_origin="2020-01-01T00:00:00Z")
    s = f.state_at(2)
    assert np.isnan(s[:, 0, 0]).all()
    np.testing.assert_array_equal(s[:, 0, 1], data[1, :, 0, 1])
    np.testing.assert_array_equal(s[:, 1, 2], data[3, :, 1, 2])
    np.testing.assert_array_equal(s[:, 1, 0], data[2, :, 1, 0])  # a cell with data keeps its own
    assert np.isfinite(s[:, ~f.land_mask]).all()


# -- the command line: exit codes, nothing half-written, nothing touched -------------------------------
def _cli_run(monkeypatch, sim, mission_path, out, *extra: str, opened: list | None = None) -> int:
    """``passt-mav run MISSION --out OUT ...`` with the transport replaced by a lockstep in-process link to ``sim``
    (``opened`` collects one entry per transport the command opens)."""
    from passt_mav.cli import main
    from passt_mav.mavlink import link as link_mod

    def open_(self):
        if opened is not None:
            opened.append(self.connect)
        return lockstep_connection(sim.connect_inprocess(), AUTOSTEP_S)

    monkeypatch.setattr(link_mod.LinkConfig, "open", open_)
    args = ["run", str(mission_path), "--connect", "tcp:127.0.0.1:5760", "--out", str(out)]
    return main([*args, "--speedup-hint", "20", "--no-report", "--quiet", *extra])


def _mission_file(tmp_path, field, **over):
    """The test mission (tests/test_controller.mission) as a YAML file, its field beside it."""
    import yaml

    cfg = mission(tmp_path, field, **over)
    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump(cfg.model_dump(mode="json", exclude_none=True), sort_keys=False))
    return path


def test_cli_sigterm_mid_leg_exits_143_in_hold_with_summary(tmp_path, monkeypatch):
    field = wave_field()
    path = _mission_file(tmp_path, field, legs=2)
    sim = Simulator(field, home=HOME, config=sim_config())
    out = tmp_path / "run"

    def killer():  # SIGTERM, as systemd sends it, once leg 0 is planned and the boat flies it
        end = time.monotonic() + 60
        while time.monotonic() < end:
            if sim.autopilot.mode == AUTO and (out / "legs" / "000" / "prediction.nc").exists():
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(0.005)

    th = threading.Thread(target=killer, daemon=True)
    th.start()
    try:
        rc = _cli_run(monkeypatch, sim, path, out)
    finally:
        th.join(5)
        sim.stop()
    rd = RunDir(out)
    s = rd.read_summary()
    assert rc == 143 and s["status"] == "stopped" and s["stopped_by"] == "SIGTERM"
    assert sim.autopilot.mode == HOLD
    assert s["n_samples"] == len(stored(rd))
    assert rd.read_leg(0)["status"] == "flying"


def test_cli_field_that_cannot_fly_never_touches_the_vehicle(tmp_path, monkeypatch, capsys):
    field = wave_field()
    # t0 past the field's last snapshot: refused before any transport is opened, and nothing left behind
    path = _mission_file(tmp_path, field, t0=field.n_times - 1)
    sim = Simulator(field, home=HOME, config=sim_config())
    opened: list[str] = []
    try:
        rc = _cli_run(monkeypatch, sim, path, tmp_path / "run", opened=opened)
    finally:
        sim.stop()
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "outside the field's" in err[0]
    assert opened == [] and sim.autopilot.store.count(0) <= 1 and not sim.autopilot.armed
    assert not (tmp_path / "run").exists()


def test_hf_radar_region_with_gaps_that_come_and_go_plans_and_flies(tmp_path, monkeypatch, hf_radar_path):
    """The MARACOOS HF-radar file where the radar's coverage comes and goes: at t0 (02:00 UTC) two columns of the
    region hold data, the rest only from 04:00. ``plan`` and ``run`` refused it (NaN in the state); the state's
    gaps are now filled from the nearest snapshot with data (FlowField.state_at) and a leg flies."""
    import yaml

    import geo
    from passt_mav.cli import main
    from passt_mav.fields.importers import import_currents

    grid = geo.RegionGrid(37.70, -74.50, 37.76, -74.44, 6, 6)  # ~1.1 km cells: a leg of minutes
    field = import_currents(hf_radar_path, grid)
    t0 = 2
    miss = field.mask
    gaps = miss[t0] & ~miss.all(axis=0)
    assert 0 < gaps.sum() < gaps.size and not miss.all(axis=0).any()  # gaps at t0 in cells with data later
    assert np.isfinite(field.state_at(t0)).all()
    field.to_netcdf(tmp_path / "radar.nc")
    g = grid
    data = {
        "name": "radar",
        "region": {"south": g.south, "west": g.west, "north": g.north, "east": g.east, "rows": 6, "cols": 6},
        "field": {"source": "radar.nc"},
        "model": "persistence",
        "planner": {"name": "greedy", "path_length": 2},
        "legs": 1,
        "t0": t0,
        "vehicle": {"speed_mps": 8.0, "wp_radius_m": 20.0},
        "geofence_margin_m": 500.0,
    }
    path = tmp_path / "radar.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["plan", str(path), "--out", str(tmp_path / "plan")]) == 0
    home = tuple(float(x) for x in grid.cell_to_latlon(3, 0))  # a cell with data at t0
    sim = Simulator(
        field,
        home=home,
        config=SimConfig.fast(params=(("WP_SPEED", 8.0),), current_rate_hz=1.0, seed=1),
        start_time=float(field.times[t0]),
    )
    try:
        rc = _cli_run(monkeypatch, sim, path, tmp_path / "run")
    finally:
        sim.stop()
    s = RunDir(tmp_path / "run").read_summary()
    assert rc == 0 and s["status"] == "complete" and s["legs"][0]["n_samples"] > 0, s.get("events")


# -- the chaos run (acceptance) ------------------------------------------------------------------------
class _Killed(BaseException):  # noqa: N818 - the process dying (as the kill/resume tests of test_controller_faults3)
    pass


def _reboot_when(ctl, sim, link, leg: int):
    """A thread restarting the simulator once leg ``leg`` has reached its second item, not while the radio is
    down (a restart nobody hears is another test)."""
    flying = _in_leg(ctl, leg, 2)

    def run():
        if _when(ctl, lambda: flying() and not link.lost and not sim.links[-1].is_down(sim.t), 60):
            sim.reboot(downtime_s=2.0)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def _sim_boots(tlog) -> list[list[int]]:
    """The simulator's readings (tlog) split by boot: ``time_boot_ms`` going back starts a new one."""
    boots: list[list[int]] = [[]]
    for t in sent_readings(tlog):
        if boots[-1] and t < boots[-1][-1]:
            boots.append([])
        boots[-1].append(t)
    return boots


@pytest.mark.slow  # its simulator restart is fired by a wall-clock thread: under parallel load (CI with xdist,
# after the lockstep link was merged) leg 1 overran before the restart came; passes run alone, not yet load-proof
def test_chaos_six_legs_drops_restart_kill_resume_and_sigterm(tmp_path):
    """One 6-leg mission on the lockstep simulator: radio drops of 10, 45 and 300 s, the simulator restarting
    mid-leg 2, the controller dying mid-leg 3 (resumed), a SIGTERM mid-leg 5 (resumed to the end). Every reading
    the vehicle sent within a leg's span is in the store or counted missing by that leg's record, and the
    replay of the run reproduces every leg's path and RMSE."""
    from passt_mav.analysis.replay import replay

    field = wave_field()
    # the window is not under test here: a paced simulator on a loaded machine may take minutes of wall time
    # for the 300 s drop (it runs only while the reader polls, not during the reconnects' back-off)
    vehicle_cfg = {"speed_mps": 5.0, "wp_radius_m": 3.0, "link_loss_window_s": 36000}
    cfg = mission(tmp_path, field, legs=6, vehicle=vehicle_cfg)
    rd = RunDir(tmp_path / "run").create()
    tlog = tmp_path / "sim.tlog"
    # (drops counted from the first arming on the simulator's clock, which its restart sets back)
    radio = SimLinkConfig(arm_drops=((20.0, 10.0), (60.0, 45.0), (110.0, 300.0)))
    runs = []
    # (reply timeouts of 1 s wall: the simulator runs at most 60x, less on a loaded machine)
    cfgs = {"sim_cfg": sim_config(tlog=str(tlog)), "radio": radio, "tlog": rd.tlog, "max_rate": 60}
    cfgs["link_kw"] = {"timeout_s": 1.0}
    with lockstep(field, **cfgs) as (sim, link, _):
        # 1. drops, a simulator restart in leg 2 (not while the radio is down), the controller killed in leg 3
        ctl = controller(cfg, field, link, rd, echo=None)
        th = _reboot_when(ctl, sim, link, 1)
        fly = ctl._fly

        def dying_fly(i, *a):
            if i == 2:
                _when(ctl, lambda: ctl.store.count(2) >= 3, 60)
                raise _Killed()
            return fly(i, *a)

        ctl._fly = dying_fly
        with pytest.raises(_Killed):
            ctl.run()
        th.join(5)
        runs.append(rd.read_summary())
        assert [x["index"] for x in runs[0]["legs"]] == [0, 1] and rd.read_leg(2)["status"] == "flying"
        # 2. resumed; SIGTERM in leg 5 (index 4)
        if link.lost:
            link.reconnect(wait_s=30)
        with StopSignals(echo=lambda s: None) as stop:
            ctl = controller(cfg, field, link, rd, echo=None, resume=True, signals=stop)
            th = threading.Thread(
                target=lambda: _when(ctl, _in_leg(ctl, 4), 60) and os.kill(os.getpid(), signal.SIGTERM), daemon=True
            )
            th.start()
            runs.append(ctl.run())
            th.join(5)
        assert runs[1]["status"] == "stopped" and runs[1]["stopped_by"] == "SIGTERM"
        assert [x["index"] for x in runs[1]["legs"]] == [0, 1, 2, 3]
        # 3. resumed to the end
        if link.lost:
            link.reconnect(wait_s=30)
        ctl = controller(cfg, field, link, rd, echo=None, resume=True)
        runs.append(ctl.run())
    final = runs[-1]
    assert final["status"] == "complete" and [x["index"] for x in final["legs"]] == list(range(6))
    ev = " | ".join(final["events"])
    assert "leg 2: vehicle rebooted" in ev and "resumed after leg 2" in ev and "stopped by SIGTERM" in ev
    outages = [o for r in runs for o in r["outages"]]
    assert all(o.get("back_utc") for o in outages), outages  # every outage noticed was ridden out
    # every reading within a leg's span (per boot) is stored or counted missing by the leg. The sensor reads
    # at 1 Hz of vehicle time (SimConfig current_rate_hz): a reading every 1000 ms, sent on every link the
    # vehicle has heard from (none while the controller reconnects or is dead: those are lost too)
    boots = _sim_boots(tlog)
    recs = stored(rd)
    for leg in final["legs"]:
        i = int(leg["index"])
        sensor_ticks = unseen_sent = 0
        for b in {r.boot for r in recs if r.leg == i}:
            have = sorted(r.time_boot_ms for r in recs if r.leg == i and r.boot == b)
            sim_boot = max(boots, key=lambda ts, h=set(have): len(h.intersection(ts)))
            assert set(have) <= set(sim_boot)  # nothing stored that the vehicle did not send
            span = [t for t in sim_boot if have[0] <= t <= have[-1]]
            assert all((t - have[0]) % 1000 == 0 for t in span)  # one sensor clock
            unseen_sent += len(set(span) - set(have))
            sensor_ticks += (have[-1] - have[0]) // 1000 + 1 - len(have)
        rdg = leg["readings"]
        assert rdg["missing"] == sensor_ticks >= unseen_sent, (i, rdg, sensor_ticks, unseen_sent)
    # the drops cost readings, and they were counted (the 10 s drop falls in leg 1; where the 45 s and 300 s
    # drops fall depends on the restart, which sets the simulator's clock back: not asserted)
    assert sum(x["readings"]["missing"] for x in final["legs"]) >= 10
    res = replay(rd.root, out=False)
    # every attempt: the 6 legs and the 2 interrupted attempts (legs 3 and 5), each path as recorded
    assert res.reproduced is True and [x.index for x in res.legs] == [0, 1, 2, 2, 3, 4, 4, 5]
    assert all(x.path_identical for x in res.legs) and all(x.rmse_identical for x in res.legs if x.n_gp_points)


# -- 4. damaged runs ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def flown_run(tmp_path_factory):
    """A complete 2-leg run (lockstep), its run directory with summary, store and telemetry log."""
    tmp = tmp_path_factory.mktemp("damaged")
    field = wave_field()
    cfg = mission(tmp, field, legs=2)
    rd = RunDir(tmp / "run").create()
    rd.mission_file.write_text(_mission_file(tmp, field, legs=2).read_text())
    with lockstep(field, tlog=rd.tlog) as (_sim, link, _):
        summary = controller(cfg, field, link, rd, echo=None).run()
    assert summary["status"] == "complete"
    return rd.root


def _damaged_copy(src, dst, *, store: bool, tlog: bool):
    """A copy of run ``src`` with its store truncated to half and/or 30 % cut from the end of its log."""
    import shutil

    shutil.copytree(src, dst)
    for name, cut, on in (("samples.sqlite", 0.5, store), ("flight.tlog", 0.7, tlog)):
        if on:
            p = dst / name
            with open(p, "r+b") as f:
                f.truncate(int(p.stat().st_size * cut))
    return dst


def test_damaged_run_report_says_what_is_missing_and_never_complete(flown_run, tmp_path, capsys):
    from passt_mav.cli import main

    run = _damaged_copy(flown_run, tmp_path / "run", store=True, tlog=True)
    assert main(["report", str(run)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    dmg = [x for x in out if x.startswith("damaged run:")]
    assert len(dmg) == 1 and "samples.sqlite unreadable" in dmg[0] and "flight.tlog" in dmg[0]
    page = (run / "report" / "report.html").read_text()
    assert "Status: damaged (recorded complete)" in page and "Status: complete" not in page
    # the intact run is complete, and says nothing of damage
    assert main(["report", str(flown_run)]) == 0
    assert "damaged run:" not in capsys.readouterr().out
    assert "Status: complete" in (flown_run / "report" / "report.html").read_text()


def test_damaged_store_replay_and_export_use_the_log(flown_run, tmp_path, capsys):
    import json as _json

    from passt_mav.cli import main

    run = _damaged_copy(flown_run, tmp_path / "run", store=True, tlog=False)
    rc = main(["replay", str(run), "--json"])
    text = capsys.readouterr().out
    res = _json.loads(text[text.index("{") :])
    assert rc == 0 and res["reproduced"] is True  # the log alone holds every leg
    assert any("damaged run: samples.sqlite unreadable" in n for n in res["notes"])
    assert main(["export", str(run), "--format", "csv", "--out", str(tmp_path / "s.csv")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("damaged run: samples.sqlite unreadable") and "telemetry log" in lines[0]
    assert len((tmp_path / "s.csv").read_text().splitlines()) > 10
