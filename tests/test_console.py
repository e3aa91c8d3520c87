"""Issue 44, "act from the page": the operator's commands carried out by the controller on vehicle-sim.

The simulator is served in lockstep (its clock runs only while the controller waits for it), so what the
vehicle does between two commands depends on the controller's steps, not on the machine's load. The
operator is a thread that appends to the run's command channel (as the view server does) when the run
reaches a state, and waits for the controller's answer (an event of kind ``command`` with the id).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import shutil
import threading
import time

import pytest
from mavlink_helpers import HOME, inprocess_factory, link_config, served
from test_controller import SPEEDUP, controller, mission, sim_config, wave_field

from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.mavlink import Link
from passt_mav.mavlink.vehicle import ROVER_MODES
from passt_mav.runs.commands import append_command
from passt_mav.runs.live import read_events
from passt_mav.runs.rundir import RunDir
from vehicle_sim import Simulator
from vehicle_sim.telemetry import battery

HOLD, AUTO, RTL = ROVER_MODES["HOLD"], ROVER_MODES["AUTO"], ROVER_MODES["RTL"]
LOITER = ROVER_MODES["LOITER"]  # how the boat waits (vehicle.wait_mode: loiter, the default; HOLD drifts)
WALL_S = 60.0  # a generous bound on each wait of the operator thread (the run takes a few seconds)


def _answer(root, cid: str) -> dict | None:
    return next((e for e in read_events(root)[0] if e.get("command_id") == cid), None)


class Operator(threading.Thread):
    """Sends ``script`` [(condition(ctl) -> bool, command dict, after(answer))] one by one: each command once
    its condition holds, the next once the controller answered."""

    def __init__(self, ctl, root, script):
        super().__init__(daemon=True)
        self.ctl, self.root, self.script = ctl, root, script
        self.answers: list[dict] = []
        self.error: str | None = None

    def _wait(self, cond, what: str) -> bool:
        end = time.monotonic() + WALL_S
        while time.monotonic() < end:
            if cond():
                return True
            time.sleep(0.002)
        self.error = f"timed out waiting for {what}"
        return False

    def run(self):
        for cond, cmd, after in self.script:
            if not self._wait(lambda c=cond: c(self.ctl), f"the moment for {cmd}"):
                return
            rec = append_command(self.root, cmd, source="test")
            if not self._wait(lambda r=rec: _answer(self.root, r["id"]) is not None, f"the answer to {cmd}"):
                return
            ans = _answer(self.root, rec["id"])
            self.answers.append(ans)
            if after is not None:
                after(ans)


def fly_with(ctl, root, script) -> tuple[dict, Operator]:
    """Run ``ctl`` with an :class:`Operator` sending ``script``; (the run's summary, the operator)."""
    op = Operator(ctl, root, script)
    op.start()
    summary = ctl.run()
    op.join(10)
    assert op.error is None, op.error
    return summary, op


def _flying(ctl, leg: int = 0) -> bool:
    """Leg ``leg`` flies in AUTO with its first waypoint behind it."""
    return (
        ctl.collector is not None
        and ctl.collector.leg == leg
        and ctl.vehicle.mode == AUTO
        and len(ctl.vehicle.progress.reached) >= 2
    )


@contextlib.contextmanager
def lockstep_session(tmp_path, tlog: bool = False, **sim_kw):
    """(sim, controller factory, run dir): the simulator in lockstep (``sim_kw`` to its config), the controller's
    link stepping it (``tlog``: writing the run's telemetry log); ``make(legs, budget=None, approve=None,
    **controller_kw)`` makes a controller for a mission of 5-move legs."""
    field = wave_field()
    sim = Simulator(field, home=HOME, config=sim_config(**sim_kw))
    sim.serve([], lockstep=True)
    rd = RunDir(tmp_path / "run").create()
    link = Link(
        link_config(
            lockstep_s=0.5, lockstep_pace=SPEEDUP, stream_rates_hz=LEAN_STREAMS, tlog=str(rd.tlog) if tlog else None
        ),
        connection_factory=inprocess_factory(sim),
    )

    def make(legs: int = 2, budget: dict | None = None, approve: dict | None = None, **kw):
        over = {k: v for k, v in (("budget", budget), ("approve", approve)) if v}
        cfg = mission(tmp_path, field, legs=legs, planner={"name": "greedy", "path_length": 5}, **over)
        return controller(cfg, field, link, rd, echo=None, **kw)

    link.connect()
    try:
        yield sim, make, rd
    finally:
        link.close()
        sim.stop()


@pytest.fixture()
def lockstep_run(tmp_path):
    with lockstep_session(tmp_path) as parts:
        yield parts


def test_pause_holds_resume_goes_on_at_the_same_item_end_returns(lockstep_run):
    sim, make, rd = lockstep_run
    ctl = make(legs=2, pause_timeout_s=WALL_S)
    ap = sim.autopilot
    seen: dict = {}

    def paused(_ans):
        seen["paused"] = (ap.mode, ap.mission_index, sim.t, ap.boat.x, ap.boat.y)

    def resumed(_ans):
        seen["resumed"] = (ap.mode, ap.mission_index)
        seen["held_at"] = (sim.t, ap.boat.x, ap.boat.y)

    def held_a_while(c):  # the vehicle's clock ran 20 s in HOLD (the controller steps it while it waits)
        return "paused" in seen and sim.t > seen["paused"][2] + 20.0

    def held(_ans=None):
        return held_a_while(ctl)

    script = [
        (_flying, {"boat": 0, "action": "pause"}, paused),
        (held, {"boat": 0, "action": "resume"}, resumed),
        (
            lambda c: _flying(c) and ap.mission_index > seen["resumed"][1],
            {"boat": 0, "action": "end", "end_mode": "RTL"},
            None,
        ),
    ]
    op = Operator(ctl, rd.root, script)
    op.start()
    summary = ctl.run()
    op.join(10)
    assert op.error is None, op.error
    # Pause: the vehicle reports LOITER (its wait_mode); it stayed at its item while its clock ran on
    mode, seq, t_p, x, y = seen["paused"]
    assert mode == LOITER and seq >= 2
    t_r, x_r, y_r = seen["held_at"]
    held_m = ((x_r - x) ** 2 + (y_r - y) ** 2) ** 0.5
    assert t_r - t_p >= 20.0 and held_m < 15.0, (t_r - t_p, held_m)  # 5 m/s boat: 100 m in 20 s had it gone on
    # Resume: AUTO at the same item it was paused at
    assert seen["resumed"] == (AUTO, seq)
    # End with RTL: the vehicle returns, the run ends cleanly (state saved for --resume)
    assert ap.mode == RTL and summary["status"] == "ended"
    assert [a["level"] for a in op.answers] == ["ok", "ok", "ok"]
    texts = [a["text"] for a in op.answers]
    assert "LOITER at item" in texts[0] and f"AUTO at item {seq}/" in texts[1] and "RTL" in texts[2]
    assert all("operator (test)" in t for t in texts)  # its source
    assert any("operator (test): end RTL" in e for e in summary["events"])
    legs = rd.read_legs()
    assert [lg["status"] for lg in legs] == ["flying"]  # the leg in flight is re-planned by --resume
    # --resume continues the ended run: the interrupted leg flown again from where the boat is, then the next
    again = make(legs=2, resume=True).run()
    assert again["status"] == "complete" and [lg["index"] for lg in again["legs"]] == [0, 1]
    assert again["legs"][0]["attempts"][0]["status"] == "interrupted"


def test_skip_ends_the_leg_and_plans_the_next(lockstep_run):
    _sim, make, rd = lockstep_run
    summary, op = fly_with(make(legs=2), rd.root, [(_flying, {"boat": 0, "action": "skip"}, None)])
    assert summary["status"] == "complete" and len(summary["legs"]) == 2
    first = summary["legs"][0]
    n_items = len(first["waypoints"]) + 1  # + DO_CHANGE_SPEED
    assert first["operator"]["action"] == "skip" and first["operator"]["at_item"] < n_items
    assert "the leg ends here" in op.answers[0]["text"] and first["n_samples"] > 0


def test_replan_plans_the_leg_again_keeping_the_attempt(lockstep_run):
    _sim, make, rd = lockstep_run
    summary, op = fly_with(make(legs=1), rd.root, [(_flying, {"boat": 0, "action": "replan"}, None)])
    assert summary["status"] == "complete" and len(summary["legs"]) == 1
    (leg,) = summary["legs"]
    (att,) = leg["attempts"]
    assert att["status"] == "replanned by the operator" and att["n_samples_stored"] > 0
    assert (rd.leg_dir(0) / "attempt_1" / "leg.json").exists()
    assert leg["n_samples"] >= att["n_samples_stored"]  # the attempt's samples are the leg's too
    assert "planned again from here" in op.answers[0]["text"]


def test_replay_reproduces_a_run_with_the_operators_skip_and_replan(tmp_path, capsys):
    """A run whose first leg the operator skipped and whose second he re-planned in flight: ``passt-mav replay RUN
    --json`` reproduces it (every leg's path identical, the re-planned attempt's path too, the RMSE the same)."""
    from passt_mav.cli import main

    with lockstep_session(tmp_path, tlog=True) as (_sim, make, rd):
        script = [
            (_flying, {"boat": 0, "action": "skip"}, None),
            (lambda c: _flying(c, leg=1), {"boat": 0, "action": "replan"}, None),
        ]
        summary, _op = fly_with(make(legs=3), rd.root, script)
    assert summary["status"] == "complete"
    legs = summary["legs"]
    assert legs[0]["operator"]["action"] == "skip" and legs[1]["attempts"][0]["status"] == "replanned by the operator"
    rc = main(["replay", str(rd.root), "--json"])
    res = json.loads(capsys.readouterr().out)
    assert rc == 0 and res["reproduced"] is True and res["first_divergence"] is None, res["notes"]
    replayed = [x for x in res["legs"] if not any("interrupted attempt" in n for n in x["notes"])]
    attempts = [x for x in res["legs"] if any("interrupted attempt" in n for n in x["notes"])]
    assert [x["path"] for x in replayed] == [lg["path"] for lg in legs]
    assert [x["path"] for x in attempts] == [legs[1]["attempts"][0]["path"]]
    assert all(x["path_identical"] and x["rmse_identical"] is not False for x in res["legs"])


def test_replay_reproduces_a_run_with_the_operators_pause_and_resume(tmp_path):
    """A run whose first leg the operator paused (the boat waited 20 s of vehicle time in its wait mode) and resumed:
    the pause's wait is not the leg's end, so ``replay`` rebuilds every leg's samples from the log exactly as the
    store holds them (the readings of the wait and of the rest of the leg included) and reproduces every path."""
    from passt_mav.analysis.replay import replay
    from passt_mav.runs.legs import rebuild_from_tlog
    from passt_mav.runs.store import SampleStore

    with lockstep_session(tmp_path, tlog=True) as (sim, make, rd):
        ctl = make(legs=3, pause_timeout_s=WALL_S)
        seen: dict = {}
        script = [
            (_flying, {"boat": 0, "action": "pause"}, lambda _a: seen.setdefault("t", sim.t)),
            (lambda c: "t" in seen and sim.t > seen["t"] + 20.0, {"boat": 0, "action": "resume"}, None),
        ]
        summary, op = fly_with(ctl, rd.root, script)
    assert summary["status"] == "complete" and len(summary["legs"]) == 3, summary["events"]
    assert [a["level"] for a in op.answers] == ["ok", "ok"]
    (wait,) = [w for w in summary["legs"][0]["waits"] if w["kind"] == "pause"]
    t0, t1 = wait["uptime_s"]  # the pause on the vehicle's clock (s since boot)
    assert t1 - t0 >= 20.0 and wait["vehicle_s"] == pytest.approx(t1 - t0, abs=0.1)
    # the log marks the pause, its resume and the leg's end, each once, in that order, at the vehicle's times
    legs = rebuild_from_tlog(rd.tlog).legs
    assert [[m for m, _ in lg.marks] for lg in legs] == [["pause", "resume", "end"], ["end"], ["end"]]
    (_, tb_p), (_, tb_r), _ = legs[0].marks
    assert tb_p <= 1000 * t0 + 500 and tb_r >= 1000 * t1 - 500
    res = replay(rd.root, out=False)
    assert not res.notes, res.notes  # the log holds every reading of the store, those outside the legs too
    assert res.reproduced and res.first_divergence is None, [(x.index, x.notes) for x in res.legs] + res.notes
    assert [x.path for x in res.legs] == [lg["path"] for lg in summary["legs"]]
    assert all(x.path_identical and x.rmse_identical is not False for x in res.legs)
    st = SampleStore(rd.samples_db, readonly=True)
    try:
        stored = [sum(1 for x in st.all() if int(x.leg) == i) for i in range(3)]
    finally:
        st.close()
    assert [x.n_samples for x in res.legs] == stored == [lg["n_samples"] for lg in summary["legs"]]
    assert not [n for x in res.legs for n in x.notes if "samples" in n]
    assert any("paused by the operator 1 time(s)" in n for n in res.legs[0].notes), res.legs[0].notes
    # the same run with a log without the marks (an older controller's): its leg ends at the pause, as it did, and
    # the replay says why the leg's samples differ from the store's
    old = RunDir(tmp_path / "old")
    shutil.copytree(rd.root, old.root)
    old.tlog.write_bytes(_without_leg_marks(rd.tlog.read_bytes()))
    assert all(not lg.marks for lg in rebuild_from_tlog(old.tlog).legs)
    res_old = replay(old.root, out=False)
    assert res_old.legs[0].n_samples < stored[0]
    assert any("1 operator pause(s) recorded, 0 marked in the log" in n for n in res_old.legs[0].notes)


def _without_leg_marks(data: bytes) -> bytes:
    """A telemetry log's bytes without the controller's leg marks (``PASST leg I end|pause|resume``)."""
    from passt_mav.runs.legs import parse_leg_statustext
    from passt_mav.runs.tlog import TlogScanner

    keep, pos = bytearray(), 0
    for _, m in TlogScanner(data):
        buf = m.get_msgbuf()
        at = data.index(buf, pos)
        pos = at + len(buf)
        if m.get_type() != "STATUSTEXT" or parse_leg_statustext(str(m.text)) is None:
            keep += data[at - 8 : pos]  # 8-byte timestamp + frame
    return bytes(keep)


def test_commands_that_do_not_apply_are_answered_with_the_reason(lockstep_run):
    sim, make, rd = lockstep_run
    ctl = make(legs=1)
    script = [
        (_flying, {"boat": 0, "action": "resume"}, None),
        (_flying, {"boat": 0, "action": "end", "end_mode": "HOLD"}, None),
    ]
    summary, op = fly_with(ctl, rd.root, script)
    assert op.answers[0]["level"] == "warn" and "not paused" in op.answers[0]["text"]
    assert summary["status"] == "ended" and sim.autopilot.mode == HOLD


# -- the safety budget (mission key budget; passt_mav.vehicle.budget) ------------------------------------------
@pytest.fixture()
def drained_run(tmp_path):
    """As :func:`lockstep_run`, with a small simulated battery (6 Wh: ~255 W at 5 m/s drains 70 % in ~60 s, a leg
    of 5 moves takes ~40 s)."""
    with lockstep_session(tmp_path, battery_wh=6.0) as parts:
        yield parts


def test_battery_reserve_returns_the_boat_ends_cleanly_and_resume_continues(drained_run):
    sim, make, rd = drained_run
    ap = sim.autopilot
    summary = make(3, {"battery_reserve_pct": 30}).run()
    # the boat returns (RTL) once the battery reached the reserve; the run ends cleanly with the leg cut there
    assert summary["status"] == "ended" and ap.mode == RTL
    pct = battery(ap)[2]
    assert 20 <= pct <= 30, pct  # at the reserve, not long past it (1 Hz BATTERY_STATUS, 0.5 s steps)
    legs = summary["legs"]
    assert legs and all(lg["status"] == "complete" for lg in legs) and len(legs) < 3
    cut = legs[-1]["budget_cut"]
    assert "battery" in cut["reason"] and "<= budget.battery_reserve_pct 30" in cut["reason"]
    assert summary["budget"]["spent"] == cut["reason"] and summary["budget"]["battery_pct"] <= 30
    kinds = [e["kind"] for e in read_events(rd.root)[0]]
    assert kinds.count("budget") == 2 and kinds[-1] == "run_end"  # the cut, then the return
    # a fresh battery (a swap at the dock): --resume continues from the next leg to the end
    ap.energy_wh = 0.0
    again = make(3, {"battery_reserve_pct": 30}, resume=True).run()
    print(f"battery: ended after {len(legs)} leg(s) at {pct} %; resumed: {again['status']}, {again['budget']}")
    assert again["status"] == "complete" and len(again["legs"]) == 3
    assert again["budget"]["spent"] is None and again["budget"]["battery_pct"] > 30


def test_battery_status_is_asked_for_again_after_an_autopilot_reboot(tmp_path):
    """The autopilot reboots early in leg 1 (lockstep, :class:`test_resilience.Faults`): a reboot forgets the rates
    set by SET_MESSAGE_INTERVAL, and the controller's lean streams turn BATTERY_STATUS (and SYS_STATUS) off; the
    controller asks for BATTERY_STATUS again, so the drained battery still reaches the reserve: RTL, ``ended``."""
    from test_resilience import Faults, _chaos_controller, _flying, flight

    field = wave_field()
    budget = {"battery_reserve_pct": 30}
    cfg = mission(tmp_path, field, legs=3, planner={"name": "greedy", "path_length": 5}, budget=budget)
    rd = RunDir(tmp_path / "run").create()
    with flight(field, sim_cfg=sim_config(battery_wh=6.0), link_kw={"timeout_s": 1.0}) as (sim, link, box):
        faults = Faults(sim, box)
        ctl = _chaos_controller(box, cfg, field, link, rd, echo=None)
        heard: list[float] = []  # the simulator's clock at each BATTERY_STATUS the controller got
        link.add_listener(lambda m: heard.append(sim.t), "BATTERY_STATUS")
        faults.at("reboot", _flying(box, 0, 1), lambda: sim.reboot(downtime_s=2.0))
        summary = ctl.run()
        ap = sim.autopilot
        pct = battery(ap)[2]
    assert "reboot" in faults.fired
    t_reboot = faults.fired["reboot"]
    assert any("vehicle rebooted" in e for e in summary["events"])
    assert sum(t > t_reboot + 5.0 for t in heard) >= 10  # ~1 Hz after the reboot (and the EKF wait)
    b = summary["budget"]
    assert summary["status"] == "ended" and ap.mode == RTL and "battery" in b["spent"]
    at_cut = float(b["spent"].split("battery: ")[1].split(" %")[0])  # the charge the cut was made at
    assert 25 <= at_cut <= 30 and pct <= 30, (b, pct)


def test_a_distance_budget_cuts_the_leg_and_holds(drained_run):
    sim, make, _rd = drained_run  # (the battery is not watched here: no reserve set)
    summary = make(3, {"max_distance_m": 150, "on_spent": "hold"}).run()
    assert summary["status"] == "ended" and sim.autopilot.mode == LOITER  # "hold": stopped in its wait_mode
    b = summary["budget"]
    # cut within a fix or two of the limit (1 Hz fixes of a 5 m/s boat: ~5 m apart)
    assert 150 <= b["distance_m"] < 170 and "distance" in b["spent"], b
    assert "budget_cut" in summary["legs"][-1]


def test_battery_remaining_takes_the_lower_known_value():
    from types import SimpleNamespace

    from passt_mav.vehicle.budget import battery_remaining

    class FakeLink:
        def __init__(self, **msgs):
            self.msgs = msgs

        def latest(self, typ):
            return self.msgs.get(typ)

    assert battery_remaining(FakeLink()) is None
    assert battery_remaining(FakeLink(SYS_STATUS=SimpleNamespace(battery_remaining=-1))) is None
    link = FakeLink(
        SYS_STATUS=SimpleNamespace(battery_remaining=55), BATTERY_STATUS=SimpleNamespace(battery_remaining=48)
    )
    assert battery_remaining(link) == 48.0


def test_the_cut_is_judged_at_the_first_report_below_the_reserve():
    """Reports reach the budget as they arrive (the reader thread); the controller may ask only later, when the
    charge has fallen further: the cut is said at the first charge at or below the reserve (29 %), not at the
    latest (20 %). A new session (``request_battery``) forgets it, and -1 (unknown) is not a charge."""
    from types import SimpleNamespace

    from passt_mav.mission.config import BudgetConfig
    from passt_mav.vehicle.budget import SafetyBudget

    class FakeLink:
        def __init__(self):
            self.msgs, self.listeners = {}, []

        def latest(self, typ):
            return self.msgs.get(typ)

        def forget(self, *types):
            for t in types:
                self.msgs.pop(t, None)

        def add_listener(self, cb, types):
            self.listeners.append((cb, tuple(types)))

        def remove_listener(self, cb):
            self.listeners = [(c, t) for c, t in self.listeners if c != cb]

        def keep_stream(self, name, hz):
            return True

        def vehicle_uptime_s(self):
            return 100.0

        def report(self, typ, pct):
            m = SimpleNamespace(battery_remaining=pct)
            self.msgs[typ] = m
            for cb, types in self.listeners:
                if typ in types:
                    cb(m)

    link = FakeLink()
    budget = SafetyBudget(link, BudgetConfig(battery_reserve_pct=30))
    budget.request_battery()
    for pct in (45, -1, 31, 29, 24, 20):
        link.report("BATTERY_STATUS", pct)
    assert budget.spent() == "battery: 29 % remaining <= budget.battery_reserve_pct 30 %"
    budget.reason = None
    budget.request_battery()  # a new session: a swapped battery
    link.report("SYS_STATUS", 80)
    assert budget.spent() is None
    budget.close()
    assert link.listeners == []


FLEET_STARTS = [(1, 1), (6, 6)]  # two boats' start cells


def two_boat_mission(tmp_path, field, **over):
    """A mission of two boats (5 m/s, starting at :data:`FLEET_STARTS`), 2 legs each; ``over``: more keys."""
    from test_fleet_controller import fleet_mission

    vehicles = [
        {"connect": f"tcp:127.0.0.1:{5760 + 10 * k}", "speed_mps": 5.0, "wp_radius_m": 3.0, "start_cell": list(s)}
        for k, s in enumerate(FLEET_STARTS)
    ]
    return fleet_mission(tmp_path, field, legs=2, vehicles=vehicles, **over)


@contextlib.contextmanager
def fleet_lockstep(field, starts, tlogs=None):
    """(fleet, links): boats of one :class:`vehicle_sim.fleet.Fleet` served in lockstep (one clock, advanced by
    whichever controller waits), one in-process link per boat stepping it (writing ``tlogs[k]``)."""
    from vehicle_sim.fleet import Fleet

    homes = [tuple(float(x) for x in field.grid.cell_to_latlon(r, c)) for r, c in starts]
    fleet = Fleet(field, starts=homes, config=sim_config())
    fleet.serve([], lockstep=True)
    links = [
        Link(
            link_config(
                lockstep_s=0.5,
                lockstep_pace=SPEEDUP,
                stream_rates_hz=LEAN_STREAMS,
                tlog=None if tlogs is None else str(tlogs[k]),
            ),
            connection_factory=inprocess_factory(fleet[k]),
        )
        for k in range(len(starts))
    ]
    try:
        for link in links:
            link.connect()
        yield fleet, links
    finally:
        for link in links:
            link.close()
        fleet.stop()


class FleetOperator(threading.Thread):
    """Approves every leg awaiting approval (``leg`` named), rejecting each leg in ``reject`` once; sends ``replan``
    to boat ``replan_boat`` once ``when(fleet)`` holds. Waits for each answer."""

    def __init__(self, fleet, root, reject=(), replan_boat=None, when=None):
        super().__init__(daemon=True)
        self.fleet, self.root, self.reject, self.replan_boat, self.when = fleet, root, set(reject), replan_boat, when
        self.answers: list[dict] = []
        self.error: str | None = None
        self.done = threading.Event()

    def _send(self, cmd: dict) -> None:
        rec = append_command(self.root, cmd, source="test")
        end = time.monotonic() + WALL_S
        while (ans := _answer(self.root, rec["id"])) is None:
            if time.monotonic() > end:
                self.error = f"no answer to {cmd}"
                raise TimeoutError(self.error)
            time.sleep(0.005)
        self.answers.append(ans)

    def run(self):
        rd, answered = RunDir(self.root), set()
        try:
            while not self.done.is_set():
                if self.replan_boat is not None and self.when(self.fleet):
                    self._send({"boat": self.replan_boat, "action": "replan"})
                    self.replan_boat = None
                for i in rd.leg_indices():
                    try:
                        rec = rd.read_leg(i)
                    except Exception:  # noqa: BLE001, S112 - being written: read again next turn
                        continue
                    key = (i, len(rec.get("attempts") or []))
                    if rec.get("status") != "awaiting_approval" or key in answered:
                        continue
                    act = "reject" if i in self.reject and key[1] == 0 else "approve"
                    self._send({"boat": int(rec["boat"]), "action": act, "leg": i})
                    answered.add(key)
                time.sleep(0.005)
        except TimeoutError:
            return


def test_a_fleet_replans_a_boats_leg_and_approves_each_leg_and_the_replay_reproduces_it(tmp_path):
    """Two boats of one lockstep fleet in approve mode: every leg is approved on the page, fleet leg 1 (boat 0's or
    boat 1's first, whichever planned first) is rejected once and planned again, and boat 1 is re-planned in flight.
    The fleet completes; the rejected and the re-planned attempts are kept with the fleet step they were planned at;
    ``passt-mav replay`` reproduces every leg's path."""
    from test_fleet_controller import run_fleet

    from passt_mav.analysis.replay import replay

    field = wave_field()
    starts = FLEET_STARTS
    cfg = two_boat_mission(
        tmp_path, field, planner={"name": "greedy", "path_length": 5}, approve={"enabled": True, "timeout_s": WALL_S}
    )
    tlogs = [RunDir(tmp_path / "run").create().boat_tlog(k) for k in range(len(starts))]
    with fleet_lockstep(field, starts, tlogs) as (_sims, links):
        fleet, rd = run_fleet(tmp_path, field, cfg, links)

        def boat1_flying(f):
            b = f.boats[1]
            return b.collector is not None and b.collector.leg is not None and len(b.vehicle.progress.reached) >= 2

        op = FleetOperator(fleet, rd.root, reject={0}, replan_boat=1, when=boat1_flying)
        op.start()
        summary = fleet.run()
        op.done.set()
        op.join(10)
    assert op.error is None, op.error
    assert summary["status"] == "complete", summary["events"]
    legs = {lg["index"]: lg for lg in summary["legs"]}
    assert sorted(legs) == [0, 1, 2, 3] and all(lg["approval"]["answer"] == "approve" for lg in legs.values())
    rejected = legs[0]["attempts"][0]
    assert rejected["status"] == "rejected by the operator" and rejected["n_samples_stored"] == 0
    replanned = [a for lg in legs.values() for a in lg.get("attempts") or [] if a["status"].startswith("replanned")]
    (att,) = replanned
    assert att["n_samples_stored"] > 0 and att["fleet_seq"]["plan"] > 0
    assert any("planned again from here" in a["text"] and a["boat"] == 1 for a in op.answers)
    result = replay(rd.root, out=False)
    assert result.reproduced, [(x.index, x.differing_cells, x.notes) for x in result.legs]
    assert [x.path for x in result.legs] == [legs[i]["path"] for i in sorted(legs)]


def test_a_fleet_takes_a_command_for_all(tmp_path):
    """Two boats of one lockstep fleet: End (HOLD) for "all" ends both boats; the fleet ends."""
    from test_fleet_controller import run_fleet

    field = wave_field()
    starts = FLEET_STARTS
    cfg = two_boat_mission(tmp_path, field)
    with fleet_lockstep(field, starts) as (sims, links):
        fleet, rd = run_fleet(tmp_path, field, cfg, links)

        def both_flying(_f):
            return all(
                b.collector is not None and b.collector.leg is not None and b.vehicle.mode == AUTO for b in fleet.boats
            )

        script = [(both_flying, {"boat": "all", "action": "end", "end_mode": "HOLD"}, None)]
        op = Operator(fleet, rd.root, script)
        op.start()
        summary = fleet.run()
        op.join(10)
        modes = [sims[k].autopilot.mode for k in range(len(starts))]
    assert op.error is None, op.error
    ended = [e for e in read_events(rd.root)[0] if e.get("command_id") and "mission ended" in e["text"]]
    assert sorted(e["boat"] for e in ended) == [0, 1]  # one answer per boat to the one command
    assert summary["status"] == "ended" and [b["status"] for b in summary["boats"]] == ["ended", "ended"]
    assert modes == [HOLD, HOLD]


# -- the vehicle's own alarms (passt_mav.vehicle.alerts) ---------------------------------------------------------
class _Journal:
    def __init__(self):
        self.notes: list[tuple[str, str]] = []

    def note(self, kind, text):
        self.notes.append((kind, text))


def _from_vehicle(name: str, *args, sysid: int = 1):
    """A MAVLink message ``name`` as the reader gets it from system ``sysid`` (packed, then parsed)."""
    from pymavlink.dialects.v20 import ardupilotmega as M

    enc = M.MAVLink(None, srcSystem=sysid, srcComponent=1)
    return M.MAVLink(None).parse_char(getattr(enc, f"{name}_encode")(*args).pack(enc))


def test_a_fence_breach_is_one_alert_until_it_clears():
    from types import SimpleNamespace

    from passt_mav.vehicle.alerts import VehicleAlerts

    j = _Journal()
    va = VehicleAlerts(SimpleNamespace(target_system=1), j)
    for breach, count in ((1, 2), (1, 2), (1, 2), (0, 2), (0, 2), (1, 3), (1, 4)):  # (the last: its clear missed)
        va.on_message(_from_vehicle("fence_status", breach, count, 3, 0))
    va.on_message(_from_vehicle("fence_status", 0, 0, 0, 0, sysid=7))  # not our vehicle's
    assert [k for k, _ in j.notes] == ["fence_breach", "fence_clear", "fence_breach", "fence_breach"]
    assert "boundary" in j.notes[0][1] and "breach 2" in j.notes[0][1]


def test_vehicle_sim_reports_its_fence_as_rover_does():
    """vehicle-sim's fence (vehicle_sim.fence): no FENCE_STATUS while FENCE_ENABLE is 0; enabled, FENCE_STATUS at the
    extended status stream's 1 Hz; leaving the uploaded inclusion polygon is a boundary breach (count 1, its time
    since boot), sent at once, and FENCE_ACTION 2 holds the armed boat; back inside, the breach clears."""
    from pymavlink.dialects.v20 import ardupilotmega as M

    from vehicle_sim.mission_server import Item

    sim = Simulator(wave_field(), home=HOME, config=sim_config())
    ap = sim.autopilot
    got: list[tuple[float, object]] = []
    sim.connect_inprocess()  # one link to the vehicle: what it sends there is kept here (FENCE_STATUS)
    ap._send_raw = lambda _link, m: got.append((ap.t, m)) if m.get_type() == "FENCE_STATUS" else None
    sim.step(50.0)  # booted, GPS, home set
    assert ap.home_set and got == []  # the fence disabled: no FENCE_STATUS
    # a 40 m square about the boat (fence list, mission type 1), the circle off; the boat armed in MANUAL
    x0, y0 = ap.boat.x, ap.boat.y
    corners = [ap.frame.to_latlon(x0 + dx, y0 + dy) for dx, dy in ((-20, -20), (20, -20), (20, 20), (-20, 20))]
    for k, (a, b) in enumerate(corners):  # (through the store, as an upload: its version marks the change)
        ap.store.put(
            Item(
                k,
                0,
                M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                0,
                1,
                4,
                0,
                0,
                0,
                round(a * 1e7),
                round(b * 1e7),
                0,
                1,
            )
        )
    ap.params.update(FENCE_ENABLE=1, FENCE_TYPE=4, FENCE_ACTION=2)
    assert ap.arm(force=True) == M.MAV_RESULT_ACCEPTED
    t0 = ap.t
    sim.step(5.0)
    inside = [m for _, m in got]
    assert 4 <= len(inside) <= 6 and all(m.breach_status == 0 and m.breach_count == 0 for m in inside)
    # outside the square (30 m east): a boundary breach, sent at once, and the boat held
    ap.boat.x = x0 + 30.0
    n = len(got)
    sim.step(ap.cfg.physics_dt)
    (t_b, m) = got[n]
    assert (m.breach_status, m.breach_count, m.breach_type) == (1, 1, M.FENCE_BREACH_BOUNDARY)
    assert m.breach_time == ap.time_boot_ms and t_b > t0 + 5.0
    assert ap.mode == ROVER_MODES["HOLD"]
    ap.boat.x = x0  # back inside: cleared, the count kept
    sim.step(2.0)
    last = got[-1][1]
    assert (last.breach_status, last.breach_count, last.breach_type) == (0, 1, M.FENCE_BREACH_NONE)


def test_a_fence_breach_on_vehicle_sim_becomes_the_pages_alert(lockstep_run):
    """End to end: vehicle-sim's circular fence (60 m about home, report only) is left by the first leg; the
    controller's alert reaches events.jsonl and the live page's state as an alert, once, with its type and count."""
    from passt_mav.view.state import RunState

    sim, make, rd = lockstep_run
    sim.autopilot.params.update(FENCE_ENABLE=1, FENCE_TYPE=2, FENCE_RADIUS=60.0, FENCE_ACTION=0)
    ctl = make(legs=1)
    heard: list[float] = []  # the simulator's clock at each FENCE_STATUS the controller got
    ctl.link.add_listener(lambda m: heard.append(sim.t), "FENCE_STATUS")
    summary = ctl.run()
    assert summary["status"] == "complete"
    # kept at ~1 Hz although the controller's lean streams stop the others (FENCE_STATUS is asked for)
    span = summary["legs"][0]["duration_vehicle_s"]
    assert len(heard) >= 0.8 * span and max(b - a for a, b in itertools.pairwise(heard)) < 3.0, (len(heard), span)
    events = RunState(rd.root).snapshot()["events"]
    fence = [e for e in events if e["kind"] in ("fence_breach", "fence_clear")]
    assert fence and fence[0]["kind"] == "fence_breach" and fence[0]["level"] == "alert"
    assert "fence breach (boundary, breach 1)" in fence[0]["text"]
    assert sum(e["kind"] == "fence_breach" for e in fence) == sim.autopilot.fence.breach_count


def test_a_failsafe_statustext_from_the_vehicle_becomes_an_alert_once():
    from pymavlink.dialects.v20 import ardupilotmega as M

    from passt_mav.vehicle.alerts import VehicleAlerts

    with served(sim_config()) as (sim, link):
        j = _Journal()
        clock = [0.0]
        va = VehicleAlerts(link, j, clock=lambda: clock[0])
        va.attach()
        ap = sim.autopilot
        ap.text(None, M.MAV_SEVERITY_WARNING, "GCS Failsafe")
        ap.text(None, M.MAV_SEVERITY_WARNING, "GCS Failsafe")  # again at once: not repeated
        ap.text(None, M.MAV_SEVERITY_CRITICAL, "Arm: System not initialised")  # a pre-arm refusal: not an alert
        ap.text(None, M.MAV_SEVERITY_INFO, "Fence breach cleared?")  # INFO: not an alert
        ap.text(None, M.MAV_SEVERITY_ALERT, "Potential thrust loss")
        end = time.monotonic() + WALL_S
        while len(j.notes) < 2 and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(0.3)  # (anything more would have come by now)
        clock[0] += 31.0
        ap.text(None, M.MAV_SEVERITY_WARNING, "GCS Failsafe")  # 31 s later: said again
        while len(j.notes) < 3 and time.monotonic() < end:
            time.sleep(0.01)
        va.detach()
    assert j.notes == [
        ("vehicle_alert", "the vehicle says: GCS Failsafe (severity 4)"),
        ("vehicle_alert", "the vehicle says: Potential thrust loss (severity 1)"),
        ("vehicle_alert", "the vehicle says: GCS Failsafe (severity 4)"),
    ]


# -- approve mode (mission key approve; run --approve) -------------------------------------------------------------
def _awaiting(rd, leg: int, attempts: int = 0):
    """A condition: leg ``leg`` awaits approval (after ``attempts`` earlier attempts)."""

    def cond(_ctl) -> bool:
        try:
            rec = rd.read_leg(leg)
        except Exception:  # noqa: BLE001 - not written yet, or being written
            return False
        return rec.get("status") == "awaiting_approval" and len(rec.get("attempts") or []) == attempts

    return cond


def test_approve_mode_approved_leg_flies_rejected_leg_is_planned_again(lockstep_run):
    sim, make, rd = lockstep_run
    stored: list[int] = []

    def note_store(_ans):
        stored.append(sim.autopilot.store.count(0))

    script = [
        (_awaiting(rd, 0), {"boat": 0, "action": "approve", "leg": 0}, None),
        (_awaiting(rd, 1), {"boat": 0, "action": "approve", "leg": 0}, None),  # a stale approval: not this leg
        (_awaiting(rd, 1), {"boat": 0, "action": "reject", "leg": 1}, note_store),
        (_awaiting(rd, 1, attempts=1), {"boat": 0, "action": "approve"}, None),
    ]
    summary, op = fly_with(make(legs=2, approve={"enabled": True, "timeout_s": WALL_S}), rd.root, script)
    assert summary["status"] == "complete" and [lg["index"] for lg in summary["legs"]] == [0, 1]
    assert [a["level"] for a in op.answers] == ["ok", "warn", "ok", "ok"]
    assert "leg 1 does not await approval" in op.answers[1]["text"]
    assert "rejected: planned again" in op.answers[2]["text"]
    leg0, leg1 = summary["legs"]
    assert leg0["approval"]["answer"] == "approve" and leg0["approval"]["distance_m"] > 0
    assert leg0["approval"]["expected_s"] > 0
    (att,) = leg1["attempts"]
    assert att["status"] == "rejected by the operator" and att["n_samples_stored"] == 0
    # the rejected leg was never uploaded: the vehicle held leg 0's mission (home, speed, its waypoints)
    assert stored == [len(leg0["waypoints"]) + 2]


def test_approve_mode_timeout_approves_or_holds(tmp_path):
    with lockstep_session(tmp_path / "a") as (_sim, make, rd):
        s = make(legs=1, approve={"enabled": True, "timeout_s": 0.3, "on_timeout": "approve"}).run()
        assert s["status"] == "complete" and s["legs"][0]["approval"]["answer"] == "timeout"
        assert any("approved by the timeout" in e["text"] for e in read_events(rd.root)[0])
    with lockstep_session(tmp_path / "h") as (sim, make, rd):
        s = make(legs=1, approve={"enabled": True, "timeout_s": 0.3, "on_timeout": "hold"}).run()
        assert s["status"] == "paused" and "no approval within" in s["events"][-1]
        assert sim.autopilot.store.count(0) <= 1 and sim.autopilot.mode == LOITER  # nothing uploaded, waiting


def test_console_keys_send_approve_and_reject(tmp_path):
    import io

    from passt_mav.runs.commands import console_keys, read_commands

    assert console_keys(tmp_path, io.StringIO("x\na\n R \napprove\n\n")) == 3
    cmds = read_commands(tmp_path)[0]
    assert [(c["action"], c["boat"], c["source"]) for c in cmds] == [
        ("approve", "all", "console"),
        ("reject", "all", "console"),
        ("approve", "all", "console"),
    ]


def test_a_leg_that_would_overrun_the_budget_is_shortened_before_upload(tmp_path):
    """A 250 m distance budget (RTL when spent) against 5-move legs of ~40 m cells: leg 1 is uploaded with only the
    waypoints that fit with the way home kept in reserve, and the vehicle holds that shorter mission; a later leg
    does not fit at all and the run ends cleanly (RTL); ``--resume`` with a larger budget flies to the end, and the
    replay of the two sessions reproduces every leg."""
    from passt_mav.analysis.replay import replay

    with lockstep_session(tmp_path, tlog=True) as parts:
        _budget_shortens_and_resumes(*parts)
    res = replay(RunDir(tmp_path / "run").root, out=False)
    assert res.reproduced and all(x.path_identical and x.rmse_identical is not False for x in res.legs), res.notes


def _budget_shortens_and_resumes(sim, make, rd) -> None:
    """The run and its resumption of :func:`test_a_leg_that_would_overrun_the_budget_is_shortened_before_upload`."""
    import geo

    ap = sim.autopilot
    ctl = make(3, {"max_distance_m": 250})
    summary = ctl.run()
    assert summary["status"] == "ended" and ap.mode == RTL
    legs = summary["legs"]
    short = legs[0]["budget_shortened"]
    k, n = short["kept"], short["of"]
    assert 1 <= k < n and len(legs[0]["waypoints"]) == k and short["budget_left_m"] == 250
    # the way home (to the vehicle's HOME_POSITION) from the last waypoint kept is in reserve
    last = legs[0]["waypoints"][-1]
    home_m = float(geo.geodesic_distance_m(last[0], last[1], *ap.home_latlon))
    assert short["return_m"] == pytest.approx(home_m, abs=0.1)
    assert short["distance_m"] + short["return_m"] <= 250 < short["planned_distance_m"] + short["return_m"]
    # the mission read back from the vehicle (the last one uploaded): home, DO_CHANGE_SPEED and the waypoints kept
    items = ctl.vehicle.mission.download()
    assert len(items) == len(legs[-1]["waypoints"]) + 2 == legs[-1]["budget_shortened"]["kept"] + 2
    got = [x for it in items[2:] for x in (it.lat, it.lon)]
    assert got == pytest.approx([x for w in legs[-1]["waypoints"] for x in w], abs=1e-7)
    texts = [e["text"] for e in read_events(rd.root)[0] if e["kind"] == "budget"]
    assert texts[0].startswith(f"leg 1 shortened: {k} of {n} waypoints") and "budget left 250 m" in texts[0]
    assert f"leg {len(legs) + 1} does not fit" in summary["budget"]["spent"] and "RTL" in texts[-1]
    assert len(legs) < 3 and rd.read_legs()[-1]["index"] == len(legs) - 1  # the leg that did not fit: not written
    # --resume (a larger budget) plans the leg that did not fit and flies on to the end
    again = make(3, {"max_distance_m": 5000}, resume=True).run()
    assert again["status"] == "complete" and [lg["index"] for lg in again["legs"]] == [0, 1, 2]
    assert "budget_shortened" not in again["legs"][-1]


def test_waypoints_that_fit_the_budget():
    from passt_mav.vehicle.budget import waypoints_that_fit

    to_wp, back = [10.0, 60.0, 110.0, 160.0], [50.0, 20.0, 30.0, 80.0]
    assert waypoints_that_fit(to_wp, [0.0] * 4, None, None, 2.0) == 4
    assert waypoints_that_fit(to_wp, [0.0] * 4, 110.0, None, 2.0) == 3  # 110 m fits exactly
    assert waypoints_that_fit(to_wp, back, 110.0, None, 2.0) == 2  # 60 + 20 m home; 110 + 30 does not
    assert waypoints_that_fit(to_wp, back, None, 40.0, 2.0) == 2  # 80 m = 40 s at 2 m/s
    assert waypoints_that_fit(to_wp, back, 500.0, 39.0, 2.0) == 1
    assert waypoints_that_fit(to_wp, back, 59.0, None, 2.0) == 0
