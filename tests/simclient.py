"""A small test-only pymavlink client for the simulator (independent of passt_mav.mavlink).

It sits on an in-process endpoint and drives the simulator in lockstep: every
wait advances simulated time in small steps until the expected message arrives
or a simulated timeout passes. Nothing here is clever on purpose: it is the
reference the simulator is checked against, written straight from the MAVLink
mission protocol.
"""

from __future__ import annotations

import collections
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

M = mavlink2


class SimClient:
    def __init__(self, sim, sysid: int = 255, compid: int = 190, link_config=None, signing_secret: bytes | None = None):
        self.sim = sim
        self.ep = sim.connect_inprocess(link_config)
        self.mav = mavlink2.MAVLink(self.ep, srcSystem=sysid, srcComponent=compid, use_native=False)
        self.mav.robust_parsing = True
        if signing_secret is not None:
            self.mav.signing.secret_key = signing_secret
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 1
            # 10 µs units since 2015-01-01: a stale timestamp would be rejected as a replay
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
        self.dt = 0.01  # simulated seconds per lockstep step while waiting
        self.queue: collections.deque = collections.deque()
        self.log: list = []

    # -- plumbing --------------------------------------------------------------------
    def pump(self) -> None:
        data = self.ep.read()
        if data:
            for m in self.mav.parse_buffer(data) or []:
                if m.get_type() != "BAD_DATA":
                    self.queue.append(m)
                    self.log.append((self.sim.t, m))

    def drain(self) -> None:
        self.pump()
        self.queue.clear()

    def wait(self, types, cond=None, timeout: float = 5.0, dt: float | None = None):
        """First message of ``types`` (str or tuple) satisfying ``cond`` within ``timeout`` sim seconds."""
        if isinstance(types, str):
            types = (types,)
        dt = self.dt if dt is None else dt
        end = self.sim.t + timeout
        while True:
            self.pump()
            while self.queue:
                m = self.queue.popleft()
                if m.get_type() in types and (cond is None or cond(m)):
                    return m
            if self.sim.t >= end:
                return None
            self.advance(dt)

    def advance(self, dt: float) -> None:
        """Let ``dt`` simulated seconds pass while waiting: this client steps the simulator."""
        self.sim.step(dt)

    def collect(self, duration: float, dt: float = 0.05) -> list:
        """All messages received during the next ``duration`` sim seconds."""
        out = []
        end = self.sim.t + duration
        while self.sim.t < end - 1e-9:
            self.sim.step(min(dt, end - self.sim.t))
            self.pump()
            out.extend(self.queue)
            self.queue.clear()
        return out

    def texts(self) -> list[str]:
        return [m.text for _, m in self.log if m.get_type() == "STATUSTEXT"]

    # -- commands ----------------------------------------------------------------------
    def command(self, cmd: int, *params, target_component: int = 1, timeout: float = 3.0):
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(1, target_component, cmd, 0, *p)
        return self.wait("COMMAND_ACK", lambda m: m.command == cmd, timeout=timeout)

    def set_mode(self, mode: int):
        return self.command(M.MAV_CMD_DO_SET_MODE, 1, mode)

    def arm(self, force: bool = False):
        return self.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 2989 if force else 0)

    def heartbeat(self):
        self.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    # -- missions ------------------------------------------------------------------------
    @staticmethod
    def waypoint(seq: int, lat: float, lon: float, mission_type: int = 0, command: int = 16, frame: int = 6):
        return M.MAVLink_mission_item_int_message(
            1, 1, seq, frame, command, 0, 1, 0, 0, 0, 0, int(round(lat * 1e7)), int(round(lon * 1e7)), 0.0, mission_type
        )

    def upload(
        self, items, mission_type: int = 0, timeout: float = 60.0, item_timeout: float = 1.5, max_count_tries: int = 20
    ):
        """Upload ``items`` (MISSION_ITEM_INT messages, seq 0..n-1); returns the final MISSION_ACK.

        Retries like a careful GCS: resends MISSION_COUNT until the first request
        arrives, answers every MISSION_REQUEST for seq k with item k (so a lost item
        or request is recovered by the vehicle's re-request), and if the final ACK
        is lost re-sends the last item and accepts an ERROR reply to it as "the
        vehicle had already finished" only after verifying by download.
        """
        n = len(items)
        end = self.sim.t + timeout
        tries = 0
        sent_last = False
        while self.sim.t < end:
            self.mav.mission_count_send(1, 1, n, mission_type)
            tries += 1
            m = self.wait(
                ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"),
                lambda m: m.mission_type == mission_type,
                timeout=item_timeout,
            )
            if m is None:
                if tries >= max_count_tries:
                    return None
                continue
            while m is not None:
                if m.get_type() == "MISSION_ACK":
                    if m.type == M.MAV_MISSION_ERROR and sent_last:
                        return m if self.download(mission_type) is not None else None
                    return m
                seq = m.seq
                if 0 <= seq < n:
                    self.mav.send(items[seq])
                    sent_last = seq == n - 1
                m = self.wait(
                    ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"),
                    lambda m: m.mission_type == mission_type,
                    timeout=item_timeout,
                )
                if m is None and sent_last:
                    # the final ACK may be lost: resend the last item; the vehicle answers ERROR (not receiving)
                    self.mav.send(items[n - 1])
                    m = self.wait(
                        ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"),
                        lambda m: m.mission_type == mission_type,
                        timeout=item_timeout,
                    )
                if m is None and self.sim.t >= end:
                    return None
                if m is None:
                    # silence: the vehicle re-requests after ~1 s; wait a bit longer before giving up
                    m = self.wait(
                        ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"),
                        lambda m: m.mission_type == mission_type,
                        timeout=8.0,
                    )
                    if m is None:
                        break
        return None

    def download(self, mission_type: int = 0, timeout: float = 60.0, item_timeout: float = 1.0, legacy: bool = False):
        """Read back the list; returns the items (MISSION_ITEM_INT, or MISSION_ITEM if legacy) or None."""
        end = self.sim.t + timeout
        count = None
        while count is None and self.sim.t < end:
            self.mav.mission_request_list_send(1, 1, mission_type)
            m = self.wait(
                ("MISSION_COUNT", "MISSION_ACK"), lambda m: m.mission_type == mission_type, timeout=item_timeout
            )
            if m is not None:
                if m.get_type() == "MISSION_ACK":
                    return m
                count = m.count
        if count is None:
            return None
        items = []
        want = "MISSION_ITEM" if legacy else "MISSION_ITEM_INT"
        while len(items) < count and self.sim.t < end:
            seq = len(items)
            if legacy:
                self.mav.mission_request_send(1, 1, seq, mission_type)
            else:
                self.mav.mission_request_int_send(1, 1, seq, mission_type)
            m = self.wait(
                (want, "MISSION_ACK"),
                lambda m, seq=seq: m.get_type() == "MISSION_ACK" or m.seq == seq,
                timeout=item_timeout,
            )
            if m is None:
                continue
            if m.get_type() == "MISSION_ACK":
                return m
            items.append(m)
        if len(items) < count:
            return None
        self.mav.mission_ack_send(1, 1, M.MAV_MISSION_ACCEPTED, mission_type)
        return items


def free_port() -> int:
    """A loopback TCP port nobody listens on right now (the OS picks it)."""
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p
