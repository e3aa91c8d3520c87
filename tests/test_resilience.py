"""Nothing lost, nothing stopped (issue 46): link outages ridden out, stop signals, overruns, field gaps.

Setting of tests/test_controller.py (8x8 grid of ~40 m cells, persistence, greedy legs of 3 moves, a
5 m/s boat), but the simulator is served in the controller-driven lockstep (``LinkConfig.lockstep_s``: its
clock runs only while the controller waits for the vehicle), so simulated time follows the controller
whatever the machine's load. The tests of radio drops and of a kill or a signal fired at a mission event
(:class:`Faults`) serve it on the wall clock at a speed-up instead (:func:`flight`; ``SPEEDUP``): a vehicle's
clock runs on while the controller cannot reach it (in lockstep a drop would lose the controller's steps and
stop it), and such a fault holds the clock from the simulator's own thread until the controller's thread has
taken it (in lockstep the controller's step would wait for that thread). Outages are the simulator's radio
(``LinkConfig.arm_drops``:
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
from mavlink_helpers import HOME, link_config
from test_controller import SPEEDUP, controller, mission, sim_config, wave_field
from test_controller_faults3 import _in_leg

from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.errors import UserError
from passt_mav.mavlink import Link
from passt_mav.runs.live import read_events
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore
from passt_mav.vehicle.signals import Stopped, StopSignals, exit_code
from vehicle_sim import LinkConfig as SimLinkConfig
from vehicle_sim import SimConfig, Simulator
from vehicle_sim.boat import BoatParams
from vehicle_sim.inprocess import InProcessMavfile

AUTO, HOLD, LOITER = 10, 4, 5
STEP_S = 0.5  # vehicle seconds per step of the controller-driven lockstep
PACE = 1e4  # at most this many vehicle seconds per wall second in lockstep: the steps as fast as they come


class Faults:
    """Faults fired from the simulator's stepping, at mission events, never from a wall-clock thread.

    Before each physics step of the simulator (in its serving thread: :func:`flight`) every pending fault
    whose condition holds runs there, at that simulated instant: the simulator cannot run past a mission event
    without its fault. A loaded machine changes how fast the simulator runs, never where in the mission a
    fault falls. Faults that need the controller's own thread (a signal, a death) hold the simulator's clock
    until that thread has taken them: on the wall clock only (in lockstep the controller waits for its step).

    Radio drops (:meth:`drop`) are windows of simulated time on every link to the vehicle, also those opened
    during them (the ``drops`` of :class:`vehicle_sim.LinkConfig`); a drop's steps take at least
    :attr:`DROP_WALL_S` of wall time in all, so even a 10 s drop outlasts the controller's ``link_lost_s``
    (0.5 s of wall time) however fast the machine: the controller notices every drop while it flies a leg.
    """

    DROP_WALL_S = 1.5  # the least wall time a drop lasts (3 x link_lost_s of :func:`mavlink_helpers.link_config`)
    HOLD_WALL_S = 60.0  # the longest the clock is held for the controller's thread to take a fault

    def __init__(self, sim, box: dict):
        self.sim, self.box = sim, box
        self.pending: list[tuple[str, object, object]] = []
        self.fired: dict[str, float] = {}  # fault -> the simulator's clock (s) it fired at
        self._drop: tuple[float, float] | None = None  # (start, duration) of the last drop, simulated s
        box["faults"] = self

    def at(self, name: str, cond, action) -> None:
        """Run ``action()`` before the first step at which ``cond()`` holds."""
        self.pending.append((name, cond, action))

    def tick(self) -> None:
        if threading.current_thread() is threading.main_thread():
            return
        for f in list(self.pending):
            name, cond, action = f
            if cond():
                self.pending.remove(f)
                self.fired[name] = self.sim.t
                action()

    def before_step(self, dt: float) -> None:
        """Fire what is due, then (in a drop) wait ``dt`` / the drop's length x :attr:`DROP_WALL_S`."""
        self.tick()
        if self.dropping():
            time.sleep(dt * self.DROP_WALL_S / self._drop[1])

    def dropping(self) -> bool:
        return self._drop is not None and self.sim.t < self._drop[0] + self._drop[1]

    def drop(self, duration_s: float) -> None:
        """Every link to the vehicle (now, and any opened meanwhile) loses every frame both ways from now for
        ``duration_s`` simulated seconds."""
        import dataclasses

        window = (self.sim.t, float(duration_s))
        with self.sim._lock:
            for ln in self.sim.links:
                ln.config = dataclasses.replace(ln.config, drops=(*ln.config.drops, window))
        cfg = self.box.get("cfg") or self.sim.link_config
        self.box["cfg"] = dataclasses.replace(cfg, drops=(*cfg.drops, window))
        self._drop = window

    def hold_until(self, taken, what: str) -> None:
        """Hold the simulator's clock until ``taken()`` (the controller's thread took the fault)."""
        end = time.monotonic() + self.HOLD_WALL_S
        while not taken():
            if time.monotonic() > end:
                raise AssertionError(f"the controller did not take {what} within {self.HOLD_WALL_S:g} s")
            time.sleep(0.002)


@contextlib.contextmanager
def flight(
    field,
    *,
    sim_cfg: SimConfig | None = None,
    radio: SimLinkConfig | None = None,
    sim_field="same",
    tlog=None,
    link_kw: dict | None = None,
    wall_clock: float | None = None,
):
    """(sim, link, box): the simulator behind the link (writing the telemetry log ``tlog``), served in the
    controller-driven lockstep, or at ``wall_clock`` x the wall clock (a speed-up); a :class:`Faults` in
    ``box["faults"]`` fires before each of its physics steps (module docstring); ``box["cfg"]`` is the
    impairment of every link the controller opens from now on (a test may swap it)."""
    sim = Simulator(field if sim_field == "same" else sim_field, home=HOME, config=sim_cfg or sim_config())
    box = {"cfg": radio}
    kw = dict(stream_rates_hz=LEAN_STREAMS, tlog=None if tlog is None else str(tlog), **(link_kw or {}))
    tick = sim._tick

    def tick_after_faults(h: float) -> None:
        if (faults := box.get("faults")) is not None:
            faults.before_step(h)
        tick(h)

    sim._tick = tick_after_faults
    if wall_clock:
        step, h, due = sim.step, sim.config.physics_dt, [0.0]

        def whole_steps(dt=None):
            # whole physics steps, as in lockstep: the sensor's 1 Hz readings stay 1000 ms apart on one clock
            due[0] += h if dt is None else dt
            while due[0] >= h - 1e-9:
                step(h)
                due[0] -= h

        sim.step = whole_steps
        sim.serve([], speedup=wall_clock)
    else:
        sim.serve([], lockstep=True)
        kw.update(lockstep_s=STEP_S, lockstep_pace=PACE)
    link = Link(link_config(**kw), connection_factory=lambda: InProcessMavfile(sim.connect_inprocess(box["cfg"])))
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
    # (the window is not under test here: it is kept on the wall clock while the vehicle is silent, 600 vehicle s
    # at the hint of 50 are 12 s of wall time, and a loaded machine took longer to step the 120 s drop through
    # the reconnects' polls: the run paused)
    vehicle_cfg = {"speed_mps": 5.0, "wp_radius_m": 3.0, "link_loss_window_s": 36000}
    cfg = mission(tmp_path, field, legs=1, vehicle=vehicle_cfg)
    rd = RunDir(tmp_path / "run").create()
    tlog = tmp_path / "sim.tlog"
    # 120 s of vehicle time without a frame either way, from 12 s after arming: mid-leg 0 (~30 s)
    radio = SimLinkConfig(arm_drops=((12.0, 120.0),))
    # on the wall clock (a drop: module docstring): at 100x the 120 s drop lasts 1.2 s of wall time, past the
    # 0.5 s of link_lost_s (a loaded machine only makes it longer)
    with flight(field, sim_cfg=sim_config(tlog=str(tlog)), radio=radio, wall_clock=100.0) as (sim, link, _):
        ctl = controller(cfg, field, link, rd, echo=None)
        summary = ctl.run()
        assert ctl.vehicle.mode == LOITER  # the end of the run: vehicle.on_end loiter
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
    with flight(field, radio=radio, wall_clock=SPEEDUP) as (_sim, link, box):  # a drop: module docstring
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


def test_a_stop_signal_in_a_queue_wait_is_raised_after_the_wait_and_the_queue_stays_sound():
    """SIGTERM while the main thread waits in ``queue.get`` (a ``Condition.wait``): Stopped comes once the wait
    is over, out of the queue's code, never inside it (raised there, the ``with`` around the wait released the
    queue's lock while the link's reader thread held it, and the reader died: ``release unlocked lock``)."""
    import queue
    import traceback

    q: queue.Queue = queue.Queue()

    def get():  # as passt_mav.mavlink.routing.Subscription.get waits for a message: None after the timeout
        try:
            return q.get(timeout=1.0)
        except queue.Empty:
            return None

    said: list[str] = []
    threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGTERM)).start()
    with StopSignals(echo=said.append):
        t0 = time.monotonic()
        with pytest.raises(Stopped) as ei:
            get()
        waited = time.monotonic() - t0
    frames = traceback.extract_tb(ei.value.__traceback__)
    assert not any(f.filename in (queue.__file__, threading.__file__) for f in frames), frames
    assert 0.9 <= waited < 3.0 and said[0].startswith("SIGTERM received")  # the wait ran its course
    assert not q.mutex.locked()
    worker = threading.Thread(target=lambda: (q.put(1), q.put(2)))  # another thread uses the queue as before
    worker.start()
    worker.join(5)
    assert q.get(timeout=1) == 1 and q.get(timeout=1) == 2


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


@pytest.mark.parametrize("signum, on_signal, mode", [(signal.SIGTERM, "hold", LOITER), (signal.SIGHUP, "auto", AUTO)])
def test_signal_mid_leg_stops_cleanly(tmp_path, signum, on_signal, mode):
    field = wave_field()
    vehicle_cfg = {"speed_mps": 5.0, "wp_radius_m": 3.0, "on_signal": on_signal}
    cfg = mission(tmp_path, field, legs=2, vehicle=vehicle_cfg)
    rd = RunDir(tmp_path / "run").create()
    # (reply timeouts of 1 s wall: the HOLD must not time out on a loaded machine)
    with flight(field, link_kw={"timeout_s": 1.0}) as (sim, link, _):
        with StopSignals(echo=lambda s: None) as stop:
            ctl = controller(cfg, field, link, rd, echo=None, signals=stop)
            th = _signal_when_in_leg(ctl, signum)
            summary = ctl.run()
            th.join(5)
        assert stop.received == signum
        time.sleep(0.05)
        assert sim.autopilot.mode == mode  # its wait_mode (LOITER), or left flying its leg with on_signal: auto
        if mode == AUTO:
            # a second controller, started afresh while the boat flies that leg, refuses to take it over: one
            # line, and the vehicle still flies the mission in AUTO (nothing was sent to it)
            other = RunDir(tmp_path / "other").create()
            # the boat flies on for 2 s first: the link's last heartbeat (the clock held since the stop) may
            # predate AUTO, and a new controller's link would hear the heartbeats of a vehicle flying on
            assert link.lockstep is not None and link.lockstep.step(2.0)
            with pytest.raises(UserError, match="armed in AUTO, flying a mission"):
                controller(cfg, field, link, other, echo=None).run()
            assert sim.autopilot.mode == AUTO and sim.autopilot.armed
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
    with flight(field, sim_cfg=slow, sim_field=None) as (_sim, link, _):
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
    """``passt-mav run MISSION --out OUT --lockstep ...`` with the transport replaced by an in-process link to
    ``sim``, served here in lockstep (``opened`` collects one entry per transport the command opens)."""
    from passt_mav.cli import main
    from passt_mav.mavlink import link as link_mod

    def open_(self):
        if opened is not None:
            opened.append(self.connect)
        return InProcessMavfile(sim.connect_inprocess())

    sim.serve([], lockstep=True)
    monkeypatch.setattr(link_mod.LinkConfig, "open", open_)
    args = ["run", str(mission_path), "--connect", "tcp:127.0.0.1:5760", "--out", str(out), "--lockstep", str(STEP_S)]
    return main([*args, "--speedup-hint", "1000000", "--no-report", "--quiet", *extra])


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
    assert sim.autopilot.mode == LOITER  # stopped in its wait_mode
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


def _sim_boots(tlog) -> list[list[int]]:
    """The simulator's readings (tlog) split by boot: ``time_boot_ms`` going back starts a new one."""
    boots: list[list[int]] = [[]]
    for t in sent_readings(tlog):
        if boots[-1] and t < boots[-1][-1]:
            boots.append([])
        boots[-1].append(t)
    return boots


def _flying(box: dict, leg: int, reached: int = 1):
    """The controller now in ``box["ctl"]`` waits in its flying loop (:meth:`VehicleSession.fly`) for leg ``leg``,
    which flies in AUTO past ``reached`` items, on a live link, the mission on the vehicle read back (a drop then
    is noticed as an outage of the leg, not spent inside the read-back's retries)."""

    def cond():
        ctl = box["ctl"]
        flying = box.get("fly") == leg and _in_leg(ctl, leg, reached)()
        return flying and not ctl.session.verify_pending and not ctl.link.lost

    return cond


def _chaos_controller(box: dict, *args, **kw):
    """:func:`test_controller.controller`, in ``box["ctl"]``, noting in ``box["fly"]`` the leg it flies."""
    ctl = box["ctl"] = controller(*args, **kw)
    fly = ctl._fly

    def noted_fly(i, *a):
        box["fly"] = i
        try:
            return fly(i, *a)
        finally:
            box["fly"] = None

    ctl._fly = noted_fly
    return ctl


def _dies_in_leg(ctl, faults: Faults, leg: int) -> None:
    """``ctl`` dies (raises :class:`_Killed`, as a killed process stops) in leg ``leg`` once the collector has
    handed 3 of its readings to the store's writer (the interrupted attempt has samples): the fault is fired
    from the stepping, the controller's thread raises, the simulator's clock held until it has."""
    kill, killed = threading.Event(), threading.Event()

    def kill_now():
        kill.set()
        faults.hold_until(killed.is_set, "the kill")

    faults.at("kill", lambda: ctl.collector is not None and ctl.collector.leg_counts(leg)["emitted"] >= 3, kill_now)
    fly = ctl._fly

    def dying_fly(i, *a):
        if i == leg:
            assert kill.wait(Faults.HOLD_WALL_S), "the kill never came"
            killed.set()
            raise _Killed()
        return fly(i, *a)

    ctl._fly = dying_fly


@pytest.mark.long(
    reason="six legs through link drops, a simulator restart, a kill, a resume and SIGTERM, at 10x the wall clock: ~1 min"
)
def test_chaos_six_legs_drops_restart_kill_resume_and_sigterm(tmp_path):
    """One 6-leg mission on the simulator (wall clock), every fault at a mission event (:class:`Faults`): radio drops
    of 10 s (leg 1), 45 s (leg 3 re-flown) and 300 s (leg 4), the simulator restarting mid-leg 2, the controller
    dying mid-leg 3 (resumed), a SIGTERM mid-leg 5 (resumed to the end). Every reading the vehicle sent within a
    leg's span is in the store or counted missing by that leg's record, every drop was noticed and ridden out,
    and the replay of the run reproduces every leg's path and RMSE."""
    from passt_mav.analysis.replay import replay

    field = wave_field()
    # the window is not under test here: a loaded machine may take minutes of wall time for the 300 s drop
    vehicle_cfg = {"speed_mps": 5.0, "wp_radius_m": 3.0, "link_loss_window_s": 36000}
    cfg = mission(tmp_path, field, legs=6, vehicle=vehicle_cfg)
    rd = RunDir(tmp_path / "run").create()
    tlog = tmp_path / "sim.tlog"
    runs = []
    # drops and Faults: on the wall clock (module docstring), at 10x: the controller's own work (the read-back
    # before the drop's mission event) then costs the vehicle little time on a loaded machine, and the 10 s
    # drop falls well inside leg 1, which flies on after it (at 20x and 50x it reached the leg's end at a load
    # average of 5); reply timeouts of 1 s wall
    cfgs = {"sim_cfg": sim_config(tlog=str(tlog)), "tlog": rd.tlog, "link_kw": {"timeout_s": 1.0}}
    with flight(field, **cfgs, wall_clock=10.0) as (sim, link, box):
        faults = Faults(sim, box)
        # 1. a 10 s drop in leg 1, a simulator restart in leg 2, the controller killed in leg 3
        ctl = _chaos_controller(box, cfg, field, link, rd, echo=None)
        faults.at("drop 10 s", _flying(box, 0), lambda: faults.drop(10.0))
        faults.at("restart", _flying(box, 1, 2), lambda: sim.reboot(downtime_s=2.0))
        _dies_in_leg(ctl, faults, 2)
        with pytest.raises(_Killed):
            ctl.run()
        runs.append(rd.read_summary())
        assert [x["index"] for x in runs[0]["legs"]] == [0, 1] and rd.read_leg(2)["status"] == "flying"
        # 2. resumed: a 45 s drop in leg 3 flown again, a 300 s drop in leg 4, SIGTERM in leg 5
        if link.lost:
            link.reconnect(wait_s=30)
        with StopSignals(echo=lambda s: None) as stop:
            ctl = _chaos_controller(box, cfg, field, link, rd, echo=None, resume=True, signals=stop)
            faults.at("drop 45 s", _flying(box, 2), lambda: faults.drop(45.0))
            faults.at("drop 300 s", _flying(box, 3), lambda: faults.drop(300.0))

            def sigterm():
                os.kill(os.getpid(), signal.SIGTERM)
                faults.hold_until(lambda: stop.received is not None, "SIGTERM")

            faults.at("SIGTERM", _flying(box, 4), sigterm)
            runs.append(ctl.run())
        assert runs[1]["status"] == "stopped" and runs[1]["stopped_by"] == "SIGTERM"
        assert [x["index"] for x in runs[1]["legs"]] == [0, 1, 2, 3]
        # 3. resumed to the end
        if link.lost:
            link.reconnect(wait_s=30)
        runs.append(_chaos_controller(box, cfg, field, link, rd, echo=None, resume=True).run())
    assert not faults.pending and list(faults.fired) == [
        "drop 10 s",
        "restart",
        "kill",
        "drop 45 s",
        "drop 300 s",
        "SIGTERM",
    ]
    final = runs[-1]
    assert final["status"] == "complete" and [x["index"] for x in final["legs"]] == list(range(6))
    ev = " | ".join(final["events"])
    assert "leg 2: vehicle rebooted" in ev and "resumed after leg 2" in ev and "stopped by SIGTERM" in ev
    # every drop was noticed where it fell, mid-leg, and ridden out
    outages = [o for r in runs for o in r["outages"]]
    assert [(o["leg"], o["during"]) for o in outages] == [(0, "leg"), (2, "leg"), (3, "leg")], outages
    assert all(o.get("back_utc") for o in outages), outages
    for o, d in zip(outages, (10.0, 45.0, 300.0), strict=True):
        assert d <= o["vehicle_s"] < d + 120.0, (d, o)  # the drop, plus noticing it and reconnecting
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
    # the drops cost readings, and they were counted: each drop's vehicle seconds in its leg's record (the 45 s and
    # 300 s drops may outlast their legs' last waypoint), and the 10 s drop's readings inside leg 1's span counted
    # missing (on the wall clock a loaded machine can push that drop to the leg's last waypoint, where the readings
    # after it belong to no leg: 9 of 10 inside the span were seen so in CI)
    by_leg = {int(x["index"]): x for x in final["legs"]}
    r0 = by_leg[0]["readings"]
    assert r0["lost_in_outages_vehicle_s"] >= 10.0 and r0["missing"] >= 1, r0
    for o in outages:
        assert by_leg[o["leg"]]["readings"]["lost_in_outages_vehicle_s"] == pytest.approx(o["vehicle_s"])
    res = replay(rd.root, out=False)
    # every attempt: the 6 legs and the 2 interrupted attempts (legs 3 and 5), each path as recorded
    why = (res.first_divergence, res.notes, [(x.index, x.path_identical, x.rmse_identical) for x in res.legs])
    assert res.reproduced is True and [x.index for x in res.legs] == [0, 1, 2, 2, 3, 4, 4, 5], why
    assert all(x.path_identical for x in res.legs) and all(x.rmse_identical for x in res.legs if x.n_gp_points)


def test_replay_of_a_run_resumed_then_rebooted_reproduces_every_leg(tmp_path):
    """The controller dies mid-leg 2 and is resumed; the autopilot restarts mid-leg 3, after the resume. The
    resumed controller numbers its boots after the stored ones (its first is boot 1, the restart boot 2) where
    the log shows one reboot: the replay reads the controller's numbering from its clock STATUSTEXT and maps
    leg 3's samples to the restart's clock anchor (it absorbed them at boot 1's, and differed in RMSE)."""
    from passt_mav.analysis.replay import replay

    field = wave_field()
    cfg = mission(tmp_path, field, legs=3, vehicle={"speed_mps": 5.0, "wp_radius_m": 3.0})
    rd = RunDir(tmp_path / "run").create()
    # a kill: on the wall clock (module docstring)
    with flight(field, tlog=rd.tlog, link_kw={"timeout_s": 1.0}, wall_clock=SPEEDUP) as (sim, link, box):
        faults = Faults(sim, box)
        ctl = _chaos_controller(box, cfg, field, link, rd, echo=None)
        _dies_in_leg(ctl, faults, 1)
        with pytest.raises(_Killed):
            ctl.run()
        if link.lost:
            link.reconnect(wait_s=30)
        ctl = _chaos_controller(box, cfg, field, link, rd, echo=None, resume=True)
        faults.at("restart", _flying(box, 2, 2), lambda: sim.reboot(downtime_s=2.0))
        summary = ctl.run()
    assert list(faults.fired) == ["kill", "restart"] and summary["status"] == "complete"
    assert "leg 3: vehicle rebooted" in " | ".join(summary["events"])
    assert sorted({r.boot for r in stored(rd) if r.leg == 2}) == [1, 2]  # the resumed session's boots
    assert len(summary["clock"]["later_boots"]) == 2
    res = replay(rd.root, out=False)
    assert res.reproduced is True and [x.index for x in res.legs] == [0, 1, 1, 2]
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
    with flight(field, tlog=rd.tlog) as (_sim, link, _):
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
    why = {k: res.get(k) for k in ("first_divergence", "notes")} | {
        "legs": [
            {k: lg.get(k) for k in ("index", "n_samples", "path_identical", "rmse_identical", "notes")}
            for lg in res["legs"]
        ]
    }
    assert rc == 0 and res["reproduced"] is True, why  # the log alone holds every leg
    assert any("damaged run: samples.sqlite unreadable" in n for n in res["notes"])
    assert main(["export", str(run), "--format", "csv", "--out", str(tmp_path / "s.csv")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("damaged run: samples.sqlite unreadable") and "telemetry log" in lines[0]
    assert len((tmp_path / "s.csv").read_text().splitlines()) > 10


# -- a real SIGKILL ---------------------------------------------------------------------------------------
def _store_count(db, leg: int) -> int:
    """Samples of ``leg`` in a run's store written by another process (0 before the store exists)."""
    import sqlite3

    if not db.exists():
        return 0
    with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)) as con:
        try:
            return int(con.execute("select count(*) from samples where leg = ?", (leg,)).fetchone()[0])
        except sqlite3.OperationalError:  # the table not created yet
            return 0


@pytest.mark.slow(
    reason="three CLI processes (demo, run --resume, replay) and a demo paced at 10x: ~100 s on a loaded 2-core machine"
)
def test_sigkill_mid_leg_then_resume_keeps_the_record_and_replays(tmp_path):
    """``passt-mav demo`` (one boat, vehicle-sim in lockstep: its clock holds while no controller steps it) killed
    with SIGKILL mid-leg 2, then ``passt-mav run --resume`` on the same simulator: nothing the store committed is
    lost, the interrupted attempt is kept, the run completes, and its replay reproduces all 4 attempts. (The
    killed controller neither holds the boat nor closes its leg in the log, nor writes its summary after leg 1:
    the log's reader ends the leg at the next controller's clock reading, the resume completes the session's
    record, and the telemetry log is written unbuffered.)"""
    import json as _json
    import re
    import subprocess
    import sys

    out = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    cli = [sys.executable, "-m", "passt_mav.cli"]
    # 10x: a leg of ~36 vehicle s lasts >= 3.6 s of wall time, the kill lands in it on a loaded machine too
    argv = ["demo", "--legs", "3", "--moves", "4", "--model", "persistence", "--speedup", "10"]
    demo = subprocess.Popen(
        [*cli, *argv, "--no-view", "--no-report", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,  # the simulator it starts shares its process group: cleaned up below
    )
    try:
        port, said = None, []
        for line in demo.stdout:
            said.append(line)
            if m := re.search(r"starting vehicle-sim on tcp:127\.0\.0\.1:(\d+) in lockstep", line):
                port = int(m.group(1))
            if line.startswith("leg 1/3:"):
                break
        assert port is not None, "".join(said)
        end = time.monotonic() + 300
        while _store_count(out / "samples.sqlite", 1) < 2:
            assert time.monotonic() < end and demo.poll() is None, "".join(said)
            time.sleep(0.01)
        os.kill(demo.pid, signal.SIGKILL)
        demo.wait(30)
        assert RunDir(out).read_leg(1)["status"] == "flying"
        before = _store_count(out / "samples.sqlite", 1)
        resume = [*cli, "run", str(out / "mission.yaml"), "--out", str(out), "--resume", "--no-report"]
        resume += ["--connect", f"tcp:127.0.0.1:{port}", "--lockstep", "0.5", "--speedup-hint", "50"]
        r = subprocess.run(resume, capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(demo.pid, signal.SIGKILL)  # the simulator (the demo itself is gone)
    rd = RunDir(out)
    s = rd.read_summary()
    assert s["status"] == "complete" and [x["index"] for x in s["legs"]] == [0, 1, 2]
    (attempt,) = rd.read_leg(1)["attempts"]
    assert attempt["status"] == "interrupted" and attempt["n_samples_stored"] == before >= 2
    assert (rd.leg_dir(1) / "attempt_1" / "leg.json").exists()
    assert [x["planned"] for x in s["sessions"]] == [[0, 1], [1, 2]]
    assert _store_count(rd.samples_db, 1) == s["legs"][1]["n_samples"] > before  # the attempt's kept, and more
    p = subprocess.run([*cli, "replay", str(out), "--json"], capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    res = _json.loads(p.stdout)
    assert res["reproduced"] is True and [x["index"] for x in res["legs"]] == [0, 1, 1, 2]
    assert all(x["path_identical"] for x in res["legs"]) and not res["notes"]
    assert all(x["rmse_identical"] for x in res["legs"] if x["n_gp_points"])
