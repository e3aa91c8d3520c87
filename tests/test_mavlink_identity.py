"""Our own MAVLink identity beside a ground station (issue 28, item 3).

Known answers: the ids on the wire; which heartbeats the vehicle's GCS failsafe counts (vehicle_sim
models ArduPilot: only MAV_GCS_SYSID's); replies addressed to another system/component never
answer our requests (a router hands us QGroundControl's replies too); and a ground station that
uploads its own mission during our leg swap is caught by the read-back, our mission is flown (or,
when it keeps replacing it, the controller stops in HOLD). The simulator is served in the controller-driven
lockstep (its clock runs only while our link waits for the vehicle, :class:`passt_mav.mavlink.link.Lockstep`),
or a ground station on the controller's own thread steps it: timeouts are the simulator's, not the machine's.
"""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
import pytest
from mavlink_helpers import HOME, SPEEDUP, Router, Wire, link_config, waypoints
from pymavlink.dialects.v20 import ardupilotmega as M
from simclient import SimClient

from passt_mav.mavlink import Link, LinkConfig, MissionClient, with_home
from passt_mav.mavlink import link as link_mod
from passt_mav.mavlink.mission_client import MissionWatch, rover_stored
from passt_mav.runs.rundir import RunDir
from vehicle_sim import SimConfig, Simulator
from vehicle_sim.inprocess import InProcessMavfile

QGC = (255, 190)
STEP_S = 0.05  # vehicle seconds per lockstep step of our link
BOOT_S = 2.0  # vehicle seconds run after connecting (the boot timeline of SimConfig.fast)
_SERVED: list = []  # simulators served by _link, stopped after each test
OURS = (link_mod.DEFAULT_SOURCE_SYSTEM, link_mod.DEFAULT_SOURCE_COMPONENT)


class _Stopped(Exception):
    """The test is over: a client following another's clock stops waiting."""


class QgcClient(SimClient):
    """A ground station like QGroundControl (255/190) on its own endpoint: it ignores replies addressed to
    another system/component (so it can share a router with us)."""

    def __init__(self, sim, ep=None):
        super().__init__(sim, sysid=QGC[0], compid=QGC[1])
        if ep is not None:  # a router port instead of a link of its own
            self.ep.close()
            self.ep = ep
            self.mav.file = ep

    def follow_clock(self, stop: threading.Event) -> None:
        """Let another client drive the simulated clock: :meth:`wait` polls without stepping the
        simulator (:meth:`advance`), and raises :class:`_Stopped` once ``stop`` is set (the clock
        stands still then). Two clients stepping one clock race
        each other: QGC's thread could run the vehicle's 8 s transfer timeout out while ours had no CPU."""
        self._stop = stop

    def advance(self, dt: float) -> None:
        if getattr(self, "_stop", None) is None:
            return super().advance(dt)
        if self._stop.is_set():
            raise _Stopped
        time.sleep(0.001)  # our link steps the simulator

    def pump(self) -> None:
        super().pump()
        for m in list(self.queue):
            ts, tc = getattr(m, "target_system", 0), getattr(m, "target_component", 0)
            if ts not in (0, QGC[0]) or tc not in (0, QGC[1]):
                self.queue.remove(m)


@pytest.fixture(autouse=True)
def _stop_served():
    yield
    while _SERVED:
        _SERVED.pop().stop()


def _link(sim, ep=None, pace: float = SPEEDUP, **kw) -> tuple[Link, Wire]:
    """Our link to ``sim`` (on ``ep``: a router port), which serves it in lockstep: our waits step its clock, at
    most ``pace`` x the wall clock (a QGC thread following the clock needs wall time to answer in)."""
    if not sim.running:
        sim.serve([], lockstep=True)
        _SERVED.append(sim)
    wire = Wire()
    ep = wire.wrap(ep if ep is not None else sim.connect_inprocess())
    cfg = link_config(heartbeat_period_s=0.02, lockstep_s=STEP_S, lockstep_pace=pace, **kw)
    link = Link(cfg, connection_factory=lambda: InProcessMavfile(ep)).connect()
    # the clock held while nobody waited: let the vehicle finish booting (SimConfig.fast: ~2 s) as it does
    # while a ground station connects to a running one (a mission sent sooner is refused with NO_SPACE)
    assert link.lockstep is not None and link.lockstep.step(BOOT_S)
    return link, wire


def test_default_identity_is_ours_neither_qgcs_nor_the_vehicles():
    c = LinkConfig()
    assert (c.source_system, c.source_component) == OURS == (245, M.MAV_COMP_ID_PATHPLANNER)
    assert OURS != QGC and link_mod.GCS_IDENTITY == QGC and OURS[0] not in (1, 200, 255)


@pytest.mark.parametrize("source_system, counted", [(None, False), (255, True)])
def test_only_mav_gcs_sysid_heartbeats_feed_the_gcs_failsafe(source_system, counted):
    """ArduPilot's GCS failsafe counts heartbeats from MAV_GCS_SYSID (255) only: ours (245) leave it to the
    real ground station; a controller speaking as 255 would keep it fed after QGC is gone."""
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    kw = {} if source_system is None else {"source_system": source_system}
    link, wire = _link(sim, **kw)
    try:
        t0 = sim.t
        while sim.t - t0 < 3.0:  # our heartbeat thread sends every 0.02 wall s; our link steps the sim
            link.idle(0.02)
        assert wire.ids == {OURS if source_system is None else (255, OURS[1])}
        assert (sim.autopilot.last_gcs_hb is not None) == counted
    finally:
        link.close()


def _mission(offset: float) -> list:
    return with_home(waypoints([(offset, 0.0), (offset + 2e-4, 2e-4), (offset, 4e-4)]))


def test_through_a_router_replies_to_qgc_are_not_ours_and_ours_not_qgcs():
    """One vehicle link shared (MAVProxy --out): QGC re-downloads the mission all the time while we upload and
    read back five missions. Every one of ours is verified (read-back = what we sent; with both sides
    speaking as 255/190 our upload is DENIED at once, as the issue's QGC downloads timed out), and every
    item QGC downloads is the item of that seq of one of our missions. (A download may mix two of them: the
    vehicle keeps no download state, so our upload can land between QGC's item requests, as on ArduPilot;
    and after the vehicle cancelled one of our uploads it may hold only the items stored before.)
    One clock: our link steps the simulator and QGC follows it (QGC stepping it too raced our
    thread: the vehicle's transfer timeout could run out in QGC's steps while ours had no CPU)."""
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    router = Router(sim)
    link, wire = _link(sim, router.port())
    qgc = QgcClient(sim, router.port())
    stop = threading.Event()
    qgc.follow_clock(stop)  # one clock, driven by our link only
    got: list = []

    def qgc_loop():
        with contextlib.suppress(_Stopped):
            while not stop.is_set():
                qgc.heartbeat()
                got.append(qgc.download(timeout=5.0, item_timeout=0.5))

    th = threading.Thread(target=qgc_loop, daemon=True)
    th.start()
    sent = []
    try:
        mc = MissionClient(link, no_space_delay_s=0.05)
        for k in range(5):
            items = _mission(1e-3 * (k + 1))
            back = mc.upload_verified(items)
            assert [rover_stored(a).same_as(b) for a, b in zip(items[1:], back[1:])] == [True] * 3
            sent.append(items)
            # ArduPilot DENIES a download while an upload runs, and ours come back to back: leave QGC 2
            # simulated seconds (our link steps the clock) to read whole lists between them too
            t, wall = sim.t, time.monotonic() + 60
            while sim.t - t < 2.0 and time.monotonic() < wall:
                link.idle(0.005)
    finally:
        stop.set()
        th.join(timeout=30)
        link.close()
    assert wire.ids == {OURS}
    whole = [g for g in got if isinstance(g, list)]
    assert len(whole) >= 3, [type(g).__name__ if not isinstance(g, list) else len(g) for g in got]
    # the vehicle cancelled one of our uploads half-way (its 8 s transfer timeout, on the simulated clock
    # that our link steps while it waits for the next item request); ArduPilot keeps the partial list, and
    # our client restarts the transfer
    cancelled = any("Mission upload timeout" in t for _, _, t in list(link.texts))
    for g in whole:
        # home only (before our first upload), or home + our 3 items; after a cancel, home + the items
        # stored before it
        assert len(g) in (1, 4) or (cancelled and 1 < len(g) < 4), (len(g), cancelled)
        for m in g[1:]:
            assert any(rover_stored(_item(m)).same_as(rover_stored(items[m.seq])) for items in sent), m


def test_the_watch_sees_foreign_uploads_through_a_router():
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    router = Router(sim)
    link, _ = _link(sim, router.port())
    qgc = QgcClient(sim, router.port())
    try:
        watch = MissionWatch(link)
        mark = watch.mark()
        MissionClient(link, no_space_delay_s=0.05).upload(_mission(1e-3))
        assert watch.changed(mark) == ""  # our own upload is not foreign
        ack = qgc.upload([SimClient.waypoint(s, HOME[0] + 1e-4 * s, HOME[1]) for s in range(3)])
        assert ack is not None and ack.type == M.MAV_MISSION_ACCEPTED
        deadline = time.monotonic() + 10
        while watch.foreign_uploads == mark[0] and time.monotonic() < deadline:  # our reader may lag QGC's
            time.sleep(0.01)
        assert watch.foreign_requests >= 3  # the vehicle's MISSION_REQUESTs to QGC, seen through the router
        assert watch.changed(mark) == "another ground station (system 255 component 190) uploaded a mission"
    finally:
        link.close()


# -- a ground station uploads its own mission while the controller swaps legs --------------------------


def _replacing(ctl, sim, qgc, times: int):
    """Make QGC download and then upload a mission of the same length (different items) right after our
    read-back, inside the swap (just before set-current), ``times`` times. Returns the record list."""
    orig = ctl.vehicle.mission.set_current
    done: list[tuple] = []

    def set_current(seq, **kw):
        if len(done) < times:
            qgc.heartbeat()
            before = qgc.download(timeout=10.0, item_timeout=0.5)
            ours = sim.autopilot.store.items[0]
            theirs = [SimClient.waypoint(it.seq, it.x / 1e7 + 3e-4, it.y / 1e7 - 3e-4) for it in ours]
            done.append((before, qgc.upload(theirs, timeout=20.0, item_timeout=0.5), len(ours)))
        return orig(seq, **kw)

    ctl.vehicle.mission.set_current = set_current
    return done


def _flight(tmp_path, shared: bool, times: int, legs: int = 2):
    from test_controller import controller, mission, sim_config, wave_field

    from passt_mav.commands.run import LEAN_STREAMS

    field = wave_field()
    cfg = mission(tmp_path, field, legs=legs)
    sim = Simulator(field, home=HOME, config=sim_config(), start_time=0.0)
    router = Router(sim) if shared else None
    # QGC's transfers run on the controller's thread and step the simulator there (SimClient.advance): our
    # steps need not wait for it; in lockstep our link counts as lost only when its transport closes
    link, wire = _link(sim, router.port() if shared else None, pace=1e4, stream_rates_hz=LEAN_STREAMS)
    qgc = QgcClient(sim, router.port() if shared else None)
    rd = RunDir(tmp_path / "run").create()
    ctl = controller(cfg, field, link, rd, echo=print)
    done = _replacing(ctl, sim, qgc, times)
    try:
        try:
            summary = ctl.run()
        finally:
            mode = ctl.vehicle.mode
    finally:
        link.close()
    return summary, sim, wire, done, field, mode


@pytest.mark.parametrize("shared", [False, True], ids=["own-link", "router"])
def test_a_gcs_upload_during_the_swap_is_caught_by_the_read_back_and_ours_flown(tmp_path, shared):
    from passt_mav.mission.waypoints import WaypointMission

    summary, sim, wire, done, field, mode = _flight(tmp_path, shared, times=1)
    assert summary["status"] == "complete" and len(summary["legs"]) == 2, summary["events"]
    ((before, ack, n_ours),) = done
    # QGC's download during the swap got our fresh leg-0 mission, whole; its upload really replaced it
    leg0 = WaypointMission.from_path(
        field.grid, np.array(summary["legs"][0]["path"]), speed=5.0, wp_radius_m=3.0, fence_margin_m=30.0
    ).items()
    assert isinstance(before, list) and len(before) == len(leg0) == n_ours
    assert all(rover_stored(a).same_as(rover_stored(_item(m))) for a, m in zip(leg0[1:], before[1:]))
    assert ack is not None and ack.type == M.MAV_MISSION_ACCEPTED
    replaced = [e for e in summary["events"] if "mission replaced" in e]
    assert len(replaced) == 1 and replaced[0].startswith("leg 1:")
    if shared:  # through a router the vehicle's ACK to QGC reached us too: the message names it
        assert "system 255 component 190" in replaced[0]
    # the vehicle ends holding the last leg's mission, ours; every frame we sent carried our identity
    last = WaypointMission.from_path(
        field.grid, np.array(summary["legs"][-1]["path"]), speed=5.0, wp_radius_m=3.0, fence_margin_m=30.0
    ).items()
    stored = sim.autopilot.store.items[0]
    assert len(stored) == len(last) and all(
        rover_stored(a).same_as(rover_stored(_item(b))) for a, b in zip(last[1:], stored[1:])
    )
    assert wire.ids == {OURS} and mode == 5  # LOITER at the end (vehicle.on_end: loiter)


def test_a_gcs_upload_mid_leg_through_a_router_is_seen_and_ours_resumed(tmp_path):
    """Through a router the vehicle's MISSION_ACK to QGC reaches us: the watch sees QGC's upload mid-leg (a
    mission of the same length: MISSION_CURRENT.total cannot tell), the read-back confirms it, ours goes back
    up and the leg resumes at the item it was flying."""
    from test_controller import controller, mission, sim_config, wave_field

    from passt_mav.commands.run import LEAN_STREAMS

    field = wave_field()
    cfg = mission(tmp_path, field, legs=1, planner={"name": "greedy", "path_length": 5})
    sim = Simulator(field, home=HOME, config=sim_config(), start_time=0.0)
    router = Router(sim)
    link, _wire = _link(sim, router.port(), stream_rates_hz=LEAN_STREAMS)
    qgc = QgcClient(sim, router.port())
    stop = threading.Event()
    qgc.follow_clock(stop)  # one clock: the controller's waits step it, QGC's thread only follows
    ctl = controller(cfg, field, link, RunDir(tmp_path / "run").create(), echo=print)
    acks = []

    def qgc_mid_leg():
        end = time.monotonic() + 60
        while time.monotonic() < end and not (
            ctl.vehicle.mode == 10 and ctl.vehicle.progress.reached and not ctl.session.verify_pending
        ):
            time.sleep(0.005)  # AUTO, our read-back done, the first waypoint reached
        ours = sim.autopilot.store.items[0]
        theirs = [SimClient.waypoint(it.seq, it.x / 1e7 + 3e-4, it.y / 1e7) for it in ours]
        with contextlib.suppress(_Stopped):
            acks.append(qgc.upload(theirs, timeout=20.0, item_timeout=0.5))

    th = threading.Thread(target=qgc_mid_leg, daemon=True)
    th.start()
    try:
        summary = ctl.run()
    finally:
        stop.set()
        th.join(30)
        link.close()
    assert acks and acks[0] is not None and acks[0].type == M.MAV_MISSION_ACCEPTED
    assert summary["status"] == "complete", summary["events"]
    replaced = [e for e in summary["events"] if "mission replaced" in e]
    assert len(replaced) == 1 and "another ground station (system 255 component 190) uploaded a mission" in replaced[0]
    stored = sim.autopilot.store.items[0]  # ours again, as flown to the end
    assert [round(it.x / 1e7, 7) for it in stored[2:]] == [round(w[0], 7) for w in summary["legs"][0]["waypoints"]]


def test_a_gcs_that_keeps_replacing_the_mission_stops_the_run_in_hold(tmp_path):
    summary, _sim, _wire, done, _field, mode = _flight(tmp_path, shared=False, times=10, legs=1)
    assert summary["status"] == "paused"
    assert len(done) == 3 and all(a is not None and a.type == M.MAV_MISSION_ACCEPTED for _, a, _ in done)
    assert any("replaced our mission 3 times" in e for e in summary["events"]), summary["events"]
    assert mode == 5  # LOITER (its wait_mode): not flying someone else's mission


def test_an_upload_denied_while_qgc_holds_a_transfer_is_waited_out(tmp_path):
    """QGC opens an upload and goes quiet (a ground station stalled mid-transfer) right before our leg's
    upload: the vehicle DENIES ours until its own 8 s transfer timeout cancels QGC's; the controller says
    so once, waits, and the leg flies with our mission."""
    from test_controller import controller, mission, sim_config, wave_field

    from passt_mav.commands.run import LEAN_STREAMS

    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    sim = Simulator(field, home=HOME, config=sim_config(), start_time=0.0)
    link, wire = _link(sim, pace=1e4, stream_rates_hz=LEAN_STREAMS)  # QGC waits on the controller's thread
    qgc = QgcClient(sim)
    ctl = controller(cfg, field, link, RunDir(tmp_path / "run").create(), echo=print)
    orig = ctl.vehicle.mission.upload
    opened = []

    def upload(items, *a, **kw):
        if not opened:
            qgc.mav.mission_count_send(1, 1, 5, 0)
            opened.append(qgc.wait("MISSION_REQUEST", timeout=5.0))  # the vehicle now serves QGC's transfer
        return orig(items, *a, **kw)

    ctl.vehicle.mission.upload = upload
    try:
        summary = ctl.run()
    finally:
        link.close()
    assert opened[0] is not None and opened[0].seq == 0
    assert summary["status"] == "complete", summary["events"]
    assert sum("upload denied" in e for e in summary["events"]) == 1
    qgc.pump()  # the vehicle's own 8 s timeout ended QGC's stalled transfer: CANCELLED, to QGC
    assert [m.type for _, m in qgc.log if m.get_type() == "MISSION_ACK"] == [M.MAV_MISSION_OPERATION_CANCELLED]
    assert wire.ids == {OURS}


def _item(m):
    """A MissionItem from a simulator's stored Item or a MISSION_ITEM_INT message."""
    from passt_mav.mission.items import MissionItem

    return MissionItem(
        int(m.seq),
        int(m.frame),
        int(m.command),
        0,
        int(m.autocontinue),
        float(m.param1),
        float(m.param2),
        float(m.param3),
        float(m.param4),
        m.x / 1e7,
        m.y / 1e7,
        float(m.z),
        0,
    )
