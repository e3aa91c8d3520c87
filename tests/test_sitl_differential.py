"""Differential test: one scripted MAVLink conversation against vehicle_sim and against ArduPilot
Rover 4.7 SITL, requiring the same observable answers field by field.

The conversation (plain pymavlink, independent of both passt_mav.mavlink and vehicle_sim): wait
until the vehicle is ready (EKF absolute position, GPS fix), upload ARDUPILOT_ROVER.md's table of
items (DO_CHANGE_SPEED in frame 2, NAV_WAYPOINT with p1..p4 and alt, NAV_WAYPOINT in frame 6,
NAV_LOITER_TIME with p3 = 10, DO_SET_SERVO, DO_JUMP back once, RTL in frame 3), read it back, arm,
AUTO, wait for "Mission Complete", HOLD. Waypoints are ~17 m apart so the mission takes about a
minute of simulated time.

Each vehicle's answers must equal :data:`FIRMWARE_ANSWERS` — what Rover 4.7 SITL answered
(recorded from ../shared/sitl with this script; the ``sitl`` case re-checks them on every run
where the build is present). A vehicle_sim whose mission normalisation is switched off answers
differently, and :func:`differences` says where (a test shows it).

Timeouts are in the vehicle's own time (``time_boot_ms`` of its messages), not wall time, so the
conversation does not depend on the machine's load; vehicle_sim is served in the controller-driven lockstep
(its clock runs only for the steps the script asks for when it has nothing to read: :meth:`Peer.recv`).
"""

from __future__ import annotations

import collections
import contextlib
import math
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as M

from vehicle_sim import SimConfig, Simulator
from vehicle_sim.sim import STEP_COMMAND

HOME = (40.0, -63.0)
D = 1.5e-4  # degrees of latitude between waypoints (~17 m)
LAT0, LON0 = int(HOME[0] * 1e7), int(HOME[1] * 1e7)
SPEEDUP = 20
STEP_S = 0.05  # vehicle seconds per lockstep step of vehicle_sim

# (frame, command, autocontinue, p1, p2, p3, p4, x degE7, y degE7, z m) for seq 1..; seq 0 is home
MISSION = [
    (2, 178, 1, 1, 3.0, -1, 0, 0, 0, 0),  # 1 DO_CHANGE_SPEED frame 2
    (3, 16, 1, 2, 25, 3, 7, LAT0 + int(D * 1e7), LON0, 12.34),  # 2 NAV_WAYPOINT p1..p4 + alt
    (6, 16, 1, 0, 25, 0, 0, LAT0 + int(2 * D * 1e7), LON0, 0),  # 3 NAV_WAYPOINT frame 6
    (3, 19, 1, 2, 0, 10, 0, LAT0 + int(2 * D * 1e7), LON0 + int(1.3 * D * 1e7), 0),  # 4 LOITER_TIME 2 s, p3 10
    (0, 183, 1, 5, 1500, 0, 0, 0, 0, 0),  # 5 DO_SET_SERVO
    (0, 177, 1, 3, 1, 0, 0, 0, 0, 0),  # 6 DO_JUMP to 3, once
    (3, 20, 1, 0, 0, 0, 0, 0, 0, 0),  # 7 RTL frame 3
]

#: what Rover 4.7 SITL answered to the conversation (see module docstring)
FIRMWARE_ANSWERS = {
    "mission_ack": [M.MAV_MISSION_ACCEPTED],
    "readback": [
        (0, 178, 1, 1.0, 3.0, -1.0, 0.0, 0, 0, 0.0),
        (3, 16, 1, 2.0, 0.0, 0.0, 0.0, LAT0 + int(D * 1e7), LON0, 12.34),
        (3, 16, 1, 0.0, 0.0, 0.0, 0.0, LAT0 + int(2 * D * 1e7), LON0, 0.0),
        (3, 19, 1, 2.0, 0.0, 1.0, 0.0, LAT0 + int(2 * D * 1e7), LON0 + int(1.3 * D * 1e7), 0.0),
        (0, 183, 1, 5.0, 1500.0, 0.0, 0.0, 0, 0, 0.0),
        (0, 177, 1, 3.0, 1.0, 0.0, 0.0, 0, 0, 0.0),
        (0, 20, 1, 0.0, 0.0, 0.0, 0.0, 0, 0, 0.0),
    ],
    "home_readback": (0, 16),  # frame, command of seq 0 (its lat/lon: home, checked to 1e-5 deg)
    "command_acks": [(400, 0), (176, 0), (176, 0)],  # arm, AUTO, HOLD
    "modes": [(0, False), (0, True), (10, True), (4, True)],  # (custom_mode, armed) as the HEARTBEAT went
    "mission_current_end": (7, 5),  # MISSION_CURRENT (total, mission_state) after "Mission Complete"
    # STATUSTEXT "Reached waypoint ..." in order: the DO_JUMP loop flies 3 and 4 twice; RTL (7) has no text
    "reached_texts": [
        "Reached waypoint #2. Loiter for 2 seconds",
        "Reached waypoint #3",
        "Reached waypoint #4. Loiter for 2 seconds",
        "Reached waypoint #3",
        "Reached waypoint #4. Loiter for 2 seconds",
    ],
    # MISSION_ITEM_REACHED seqs: DO_CHANGE_SPEED (1) counts (Rover verifies it), DO_SET_SERVO (5) does not
    "items_reached": [1, 2, 3, 4, 3, 4, 7],
    "mission_complete_texts": 1,
}


class Peer:
    """A pymavlink connection plus the vehicle's clock (seconds from its messages' time_boot_ms).

    ``step_s`` > 0: the vehicle is a simulator served in lockstep, and a read that finds nothing steps its
    clock (:meth:`step`); else the vehicle keeps its own clock and an idle read sleeps ``idle_sleep_s``."""

    def __init__(self, conn, wall_limit_s: float, idle_sleep_s: float, step_s: float = 0.0):
        self.conn = conn
        self.t = 0.0
        self.wall_limit_s = wall_limit_s
        self.idle_sleep_s = idle_sleep_s
        self.step_s = step_s
        self.log: list = []
        self._read: collections.deque = collections.deque()  # read during a step, not handed out yet
        self._sent = False  # something sent since the last step

    def send(self, msg) -> None:
        self.conn.mav.send(msg)
        self._sent = True

    def step(self) -> None:
        """Run the vehicle's clock one step (0 s after we sent something: only its answers, at the held time)
        and read until it acknowledges the step, which comes after everything it sent during the step."""
        h, self._sent = (0.0 if self._sent else self.step_s), False
        self.conn.mav.send(M.MAVLink_command_long_message(1, 1, STEP_COMMAND, 0, h, 0, 0, 0, 0, 0, 0))
        wall_end = time.monotonic() + 30.0
        while time.monotonic() < wall_end:
            m = self.conn.recv_match(blocking=True, timeout=1.0)
            if m is not None and m.get_type() == "COMMAND_ACK" and m.command == STEP_COMMAND:
                return
            if m is not None:
                self._read.append(m)
        raise AssertionError("the simulator did not acknowledge a lockstep step")

    def recv(self):
        m = self._read.popleft() if self._read else self.conn.recv_match(blocking=False)
        if m is None:
            if self.step_s:
                self.step()
            elif self.idle_sleep_s:
                time.sleep(self.idle_sleep_s)
            return None
        if m.get_type() == "BAD_DATA" or m.get_srcSystem() != 1 or m.get_srcComponent() != 1:
            return None
        tb = getattr(m, "time_boot_ms", None)
        if tb is not None:
            self.t = max(self.t, tb / 1000.0)
        self._seen(m)
        return m

    def _seen(self, m) -> None:
        """Each message from the vehicle, once (kept in :attr:`log`)."""
        self.log.append(m)

    def wait(self, types, cond=None, timeout: float = 5.0, what: str = ""):
        """First message of ``types`` satisfying ``cond`` within ``timeout`` vehicle seconds."""
        types = (types,) if isinstance(types, str) else tuple(types)
        end, wall_end = self.t + timeout, time.monotonic() + self.wall_limit_s
        while self.t < end:
            if time.monotonic() > wall_end:
                break
            m = self.recv()
            if m is not None and m.get_type() in types and (cond is None or cond(m)):
                return m
        raise AssertionError(f"no {what or types} within {timeout} s of vehicle time")


def _ready(p: Peer) -> bool:
    ekf = gpi = None
    for m in reversed(p.log):
        if ekf is None and m.get_type() == "EKF_STATUS_REPORT":
            ekf = m
        if gpi is None and m.get_type() == "GLOBAL_POSITION_INT":
            gpi = m
        if ekf is not None and gpi is not None:
            break
    return bool(ekf and ekf.flags & 16 and not ekf.flags & 128 and gpi and (gpi.lat or gpi.lon))


def _upload(p: Peer, items) -> int:
    p.send(M.MAVLink_mission_count_message(1, 1, len(items), 0))
    while True:
        m = p.wait(("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"), timeout=10, what="upload reply")
        if m.get_type() == "MISSION_ACK":
            return int(m.type)
        p.send(items[m.seq])


def _download(p: Peer) -> list:
    p.send(M.MAVLink_mission_request_list_message(1, 1, 0))
    n = p.wait("MISSION_COUNT", timeout=5).count
    out = []
    for s in range(n):
        p.send(M.MAVLink_mission_request_int_message(1, 1, s, 0))
        out.append(p.wait("MISSION_ITEM_INT", lambda m, s=s: m.seq == s, timeout=5, what=f"item {s}"))
    p.send(M.MAVLink_mission_ack_message(1, 1, 0, 0))
    return out


def _command(p: Peer, cmd: int, *params) -> tuple[int, int]:
    ps = list(params) + [0.0] * (7 - len(params))
    p.send(M.MAVLink_command_long_message(1, 1, cmd, 0, *ps))
    a = p.wait("COMMAND_ACK", lambda m: m.command == cmd, timeout=5, what=f"COMMAND_ACK {cmd}")
    return (cmd, int(a.result))


def conversation(p: Peer) -> dict:
    """Run the script; returns the observable answers (keys of :data:`FIRMWARE_ANSWERS`)."""
    p.wait("HEARTBEAT", timeout=10)
    ready_by = p.t + 120
    while not _ready(p):
        p.wait(("EKF_STATUS_REPORT", "GLOBAL_POSITION_INT"), timeout=max(ready_by - p.t, 0.1), what="readiness")
    hb0 = len(p.log)
    items = [M.MAVLink_mission_item_int_message(1, 1, 0, 0, 16, 0, 1, 0, 0, 0, 0, LAT0, LON0, 0, 0)]
    items += [
        M.MAVLink_mission_item_int_message(1, 1, i + 1, f, c, 0, a, p1, p2, p3, p4, x, y, z, 0)
        for i, (f, c, a, p1, p2, p3, p4, x, y, z) in enumerate(MISSION)
    ]
    out: dict = {"mission_ack": [_upload(p, items)]}
    got = _download(p)
    out["readback"] = [
        (g.frame, g.command, g.autocontinue, g.param1, g.param2, g.param3, g.param4, g.x, g.y, round(g.z, 4))
        for g in got[1:]
    ]
    out["home_readback"] = (got[0].frame, got[0].command)
    out["home_latlon"] = (got[0].x / 1e7, got[0].y / 1e7)
    acks = [_command(p, M.MAV_CMD_COMPONENT_ARM_DISARM, 1)]
    p.wait("HEARTBEAT", lambda m: m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout=5, what="armed")
    acks.append(_command(p, M.MAV_CMD_DO_SET_MODE, 1, 10))
    p.wait("STATUSTEXT", lambda m: m.text.startswith("Mission Complete"), timeout=240, what="Mission Complete")
    mc = p.wait("MISSION_CURRENT", lambda m: m.mission_state == 5, timeout=5, what="MISSION_CURRENT complete")
    out["mission_current_end"] = (mc.total, mc.mission_state)
    acks.append(_command(p, M.MAV_CMD_DO_SET_MODE, 1, 4))
    p.wait("HEARTBEAT", lambda m: m.custom_mode == 4, timeout=5, what="HOLD")
    out["command_acks"] = acks
    modes = []
    for m in p.log[hb0:]:
        if m.get_type() == "HEARTBEAT":
            k = (int(m.custom_mode), bool(m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED))
            if not modes or modes[-1] != k:
                modes.append(k)
    out["modes"] = modes
    texts = [m.text for m in p.log if m.get_type() == "STATUSTEXT"]
    out["reached_texts"] = [t for t in texts if t.startswith("Reached waypoint")]
    out["items_reached"] = [int(m.seq) for m in p.log if m.get_type() == "MISSION_ITEM_REACHED"]
    out["mission_complete_texts"] = sum(t.startswith("Mission Complete") for t in texts)
    return out


def differences(got: dict, want: dict = FIRMWARE_ANSWERS) -> list[str]:
    """Field-by-field differences between two vehicles' answers ([] = the same)."""
    bad = []
    for key, w in want.items():
        g = got.get(key)
        if key == "readback":
            if len(g) != len(w):
                bad.append(f"readback: {len(g)} items, want {len(w)}")
            for i, (a, b) in enumerate(zip(g, w)):
                names = ("frame", "command", "autocontinue", "param1", "param2", "param3", "param4", "x", "y", "z")
                for name, u, v in zip(names, a, b):
                    if not math.isclose(u, v, rel_tol=0, abs_tol=1e-4):
                        bad.append(f"readback seq {i + 1} {name}: {u!r}, firmware {v!r}")
        elif g != w:
            bad.append(f"{key}: {g!r}, firmware {w!r}")
    if "home_latlon" in got:
        la, lo = got["home_latlon"]
        if abs(la - HOME[0]) > 1e-5 or abs(lo - HOME[1]) > 1e-5:
            bad.append(f"home read back at {la:.7f},{lo:.7f}, not {HOME}")
    return bad


@contextlib.contextmanager
def _sim_peer(normalise: bool = True):
    """A :class:`Peer` on vehicle_sim served in lockstep (stopped on exit)."""
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.autopilot.missions.normalise = normalise
    sim.serve([], lockstep=True)
    conn = sim.connect_inprocess().mavlink_connection(source_system=255, source_component=190)
    try:
        yield Peer(conn, wall_limit_s=120.0, idle_sleep_s=0.0, step_s=STEP_S)
    finally:
        conn.close()
        sim.stop()


@pytest.fixture(params=["vehicle_sim", pytest.param("sitl", marks=pytest.mark.sitl)])
def peer(request):
    if request.param == "vehicle_sim":
        with _sim_peer() as p:
            yield p
        return
    sitl = request.getfixturevalue("sitl_factory")(speedup=SPEEDUP)
    conn = sitl.mavlink()
    try:
        yield Peer(conn, wall_limit_s=60.0, idle_sleep_s=0.001)
    finally:
        conn.close()


def test_same_answers_as_the_firmware(peer):
    got = conversation(peer)
    assert differences(got) == []


def test_the_comparison_catches_a_sim_that_stores_items_verbatim():
    """With its normalisation off vehicle_sim answers the read-back differently from the firmware
    (the acceptance radius kept, DO_CHANGE_SPEED's frame 2 kept, ...), and the comparison says so."""
    with _sim_peer(normalise=False) as p:
        bad = differences(conversation(p))
    assert "readback seq 1 frame: 2, firmware 0" in bad
    assert "readback seq 2 param2: 25.0, firmware 0.0" in bad
    assert "readback seq 4 param3: 10.0, firmware 1.0" in bad
    assert "readback seq 7 frame: 3, firmware 0" in bad
    assert all(b.startswith("readback") for b in bad)  # the rest of the conversation is the same
