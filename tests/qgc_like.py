"""A second ground-station client that behaves like QGroundControl on a shared link (tests).

System 255, component 190 (QGC's and Mission Planner's ids), a GCS HEARTBEAT every second,
and a full mission download (MISSION_REQUEST_LIST -> MISSION_COUNT -> MISSION_REQUEST_INT ->
MISSION_ITEM_INT ..., MISSION_ACK) every ``period_s`` wall seconds, as QGC re-reads the
vehicle's mission. Like QGC it takes only the replies addressed to itself (target 255/190)
and retries a request after ``item_timeout_s`` up to ``retries`` times; a whole download that
failed (another client replaced the mission under it) is tried again after ``retry_after_s``.
Framing is pymavlink's.

``downloads``: one :class:`Download` per attempt (``ok``, ``items`` as (seq, command, lat, lon),
``error``, wall seconds taken). ``foreign``: mission-protocol messages addressed to this client
that it never asked for (MISSION_REQUEST / MISSION_REQUEST_INT: it never uploads; a MISSION_ACK
outside its own downloads): another client on the link speaks with the same ids.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil


@dataclass
class Download:
    ok: bool
    items: list[tuple[int, int, float, float]] = field(default_factory=list)
    error: str = ""
    seconds: float = 0.0


class QgcLike:
    def __init__(
        self,
        connect: str,
        *,
        period_s: float = 40.0,
        target_system: int = 1,
        target_component: int = 1,
        sysid: int = 255,
        compid: int = 190,
        item_timeout_s: float = 1.5,
        retries: int = 5,
        retry_after_s: float = 2.0,
    ):
        self.connect, self.period_s = connect, period_s
        self.target = (target_system, target_component)
        self.sysid, self.compid = sysid, compid
        self.item_timeout_s, self.retries, self.retry_after_s = item_timeout_s, retries, retry_after_s
        self.downloads: list[Download] = []
        self.foreign: list[str] = []
        self._downloading = False
        self._stop = threading.Event()
        self._th: threading.Thread | None = None
        self._next_hb = 0.0
        self.conn = None

    def start(self) -> QgcLike:
        self.conn = mavutil.mavlink_connection(
            self.connect, source_system=self.sysid, source_component=self.compid, dialect="ardupilotmega"
        )
        self._th = threading.Thread(target=self._run, name="qgc-like", daemon=True)
        self._th.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._th is not None:
            self._th.join(timeout=30.0)
        if self.conn is not None:
            self.conn.close()

    # -- internals ---------------------------------------------------------------------------
    def _heartbeat(self) -> None:
        if time.monotonic() >= self._next_hb:
            self._next_hb = time.monotonic() + 1.0
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 4)  # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, active

    def _recv(self, types: tuple[str, ...], cond, timeout: float):
        """The next message of ``types`` addressed to us that satisfies ``cond``, or None (heartbeats go on)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and not self._stop.is_set():
            self._heartbeat()
            m = self._next(0.05)
            if m is None or m.get_type() not in types:
                continue
            if getattr(m, "mission_type", 0) == 0 and cond(m):
                return m
        return None

    def _next(self, timeout: float):
        """The next mission message from the vehicle addressed to us (others are a reply to another client)."""
        m = self.conn.recv_match(blocking=True, timeout=timeout)
        if m is None or m.get_srcSystem() != self.target[0] or not m.get_type().startswith("MISSION_"):
            return None
        if (getattr(m, "target_system", None), getattr(m, "target_component", None)) != (self.sysid, self.compid):
            return None
        if m.get_type() in ("MISSION_REQUEST", "MISSION_REQUEST_INT") or (
            m.get_type() == "MISSION_ACK" and not self._downloading
        ):
            self.foreign.append(f"{m.get_type()} {getattr(m, 'seq', getattr(m, 'type', ''))}")
        return m

    def _ask(self, send, types, cond):
        for _ in range(self.retries + 1):
            send()
            m = self._recv(types, cond, self.item_timeout_s)
            if m is not None:
                return m
        return None

    def download(self) -> Download:
        self._downloading = True
        try:
            return self._download()
        finally:
            self._downloading = False

    def _download(self) -> Download:
        t0 = time.monotonic()
        mav, (ts, tc) = self.conn.mav, self.target
        m = self._ask(lambda: mav.mission_request_list_send(ts, tc, 0), ("MISSION_COUNT",), lambda m: True)
        if m is None:
            return Download(False, error="no MISSION_COUNT", seconds=time.monotonic() - t0)
        items = []
        for seq in range(int(m.count)):
            it = self._ask(
                lambda seq=seq: mav.mission_request_int_send(ts, tc, seq, 0),
                ("MISSION_ITEM_INT",),
                lambda x, seq=seq: x.seq == seq,
            )
            if it is None:
                return Download(
                    False, items, error=f"no MISSION_ITEM_INT {seq} of {m.count}", seconds=time.monotonic() - t0
                )
            items.append((int(it.seq), int(it.command), it.x * 1e-7, it.y * 1e-7))
        mav.mission_ack_send(ts, tc, 0, 0)
        return Download(True, items, seconds=time.monotonic() - t0)

    def _run(self) -> None:
        next_dl = time.monotonic()  # QGC reads the mission when it connects, then again every period
        while not self._stop.is_set():
            self._heartbeat()
            if time.monotonic() >= next_dl:
                d = self.download()
                if not d.ok and self._stop.is_set():
                    break  # cut short by stop(), not by the vehicle
                self.downloads.append(d)
                # a download that collided with another client's upload (the vehicle replaced the
                # mission under it) is tried again soon, as a ground station's "refresh" would be
                next_dl = time.monotonic() + (self.period_s if self.downloads[-1].ok else self.retry_after_s)
            self._next(0.05)
