"""One MAVLink link of the simulator: framing, signing, impairment, tlog.

A :class:`Link` owns a pymavlink ``MAVLink`` object (MAVLink 2, ardupilotmega
dialect) whose file-like writer is the link's outgoing queue; framing, parsing,
CRCs and signing are pymavlink's. On top of that it emulates a radio, in
*simulated* time:

* ``loss``: each frame is lost with probability P, each way, from a seeded
  generator (incoming frames are dropped after parsing: a lost frame never
  reaches the autopilot, so its state cannot be corrupted by a partial frame);
* ``latency_s``: added one-way delay;
* ``baud``: frames are serialised at ``baud / 10`` bytes per simulated second,
  each way; a backlog longer than ``max_queue_s`` or a frame that does not fit in
  ``buffer_bytes`` overflows (frame dropped; :func:`vehicle_sim.radio.queue_frame`,
  the rule the wall-time :class:`vehicle_sim.radio.RadioProxy` uses too);
* ``drops``: scheduled outages.

The transport (a socket, or the in-process endpoint) moves bytes in and out:
``feed(bytes, t)`` on receipt, ``pop_outgoing(t)`` for bytes due by time t.
"""

from __future__ import annotations

import collections
import random
import struct
import threading
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from vehicle_sim.config import LinkConfig
from vehicle_sim.radio import queue_frame

__all__ = ["Link", "TlogWriter", "secret_from_key", "parse_link_spec"]

#: messages ArduPilot accepts unsigned even when signing is on
UNSIGNED_OK = frozenset({mavlink2.MAVLINK_MSG_ID_RADIO_STATUS})


def secret_from_key(key: str | bytes) -> bytes:
    """32-byte signing secret: sha256 of a passphrase, or 64 hex digits taken as is.

    This matches MAVProxy's ``signing setup PASSPHRASE`` (sha256 of the UTF-8
    passphrase), so the same passphrase works on both ends.
    """
    import hashlib

    if isinstance(key, bytes):
        return key if len(key) == 32 else hashlib.sha256(key).digest()
    s = key.strip()
    if len(s) == 64:
        try:
            return bytes.fromhex(s)
        except ValueError:
            pass
    return hashlib.sha256(s.encode("utf-8")).digest()


class TlogWriter:
    """Telemetry log: each frame prefixed by its 8-byte big-endian µs UTC timestamp.

    The format of MAVProxy/pymavlink ``.tlog`` files, readable with
    ``mavutil.mavlink_connection(path)``. Timestamps are ``epoch0 + simulated
    time`` so a replay sees the simulated clock.
    """

    def __init__(self, path: str | Path, epoch0: float):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "ab")  # noqa: SIM115 - the telemetry log stays open for the link's life
        self._epoch0 = float(epoch0)
        self._lock = threading.Lock()

    def write(self, t_sim: float, frame: bytes) -> None:
        usec = int((self._epoch0 + t_sim) * 1e6)
        with self._lock:
            if not self._f.closed:
                self._f.write(struct.pack(">Q", usec) + bytes(frame))

    def close(self) -> None:
        with self._lock:
            if not self._f.closed:
                self._f.close()


class _Writer:
    """File-like sink pymavlink's MAVLink writes packed frames into."""

    def __init__(self, link: Link):
        self._link = link

    def write(self, buf: bytes) -> None:
        self._link._outgoing(bytes(buf))


class Link:
    """A simulated MAVLink channel (see module docstring).

    Args:
        index: channel number (0-based; MAV{index+1}_* parameters apply to it).
        config: impairment.
        sysid, compid: the vehicle's identity on outgoing frames.
        tlog: shared :class:`TlogWriter` or None.
        signing_secret: 32-byte key: sign outgoing, reject unsigned input.
        name: for logs ("tcp:127.0.0.1:5760 #2", "inprocess").
    """

    def __init__(
        self,
        index: int,
        config: LinkConfig,
        *,
        sysid: int = 1,
        compid: int = 1,
        tlog: TlogWriter | None = None,
        signing_secret: bytes | None = None,
        name: str = "",
    ):
        self.index = int(index)
        self.config = config
        self.armed_at: float | None = None  # the vehicle's first arming, simulated s (set by its autopilot)
        self.opened_at: float | None = None  # the simulator's clock when the link opened (set by the simulator)
        self.name = name or f"link{index}"
        self.tlog = tlog
        self.mav = mavlink2.MAVLink(_Writer(self), srcSystem=sysid, srcComponent=compid, use_native=False)
        self.mav.robust_parsing = True
        if signing_secret is not None:
            self.mav.signing.secret_key = bytes(signing_secret)
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = self.index & 0xFF
            # 10 µs units since 2015-01-01, like pymavlink's setup_signing
            import time as _time

            self.mav.signing.timestamp = int(max(_time.time() - 1420070400, 0) * 1e5)
            self.mav.signing.allow_unsigned_callback = lambda _mav, msgid: msgid in UNSIGNED_OK
        # one generator per direction: each direction's losses are a fixed sequence over its own frames,
        # whatever the interleaving of the two directions in wall time (a shared generator made "which
        # frame is lost" depend on thread timing)
        base = (config.seed * 1_000_003 + self.index) & 0xFFFFFFFF
        self._rng_tx = random.Random(base)
        self._rng_rx = random.Random(base ^ 0x5A5A5A5A)
        self._now = 0.0
        self._out: collections.deque[tuple[float, bytes]] = collections.deque()
        self._in: collections.deque[tuple[float, object]] = collections.deque()
        self._tx_free = 0.0
        self._rx_free = 0.0
        self._lock = threading.Lock()
        self.closed = False
        # counters (for tests, benchmarks and the console)
        self.stats = collections.Counter()

    # -- impairment ------------------------------------------------------------
    def is_down(self, t: float) -> bool:
        """True during a scheduled outage (``drops`` on the clock, ``arm_drops`` after ``armed_at``), and with
        ``drops_break_link`` after any outage that began while this link was open (since ``opened_at``)."""
        if not (self.config.drops or self.config.arm_drops):
            return False
        windows = list(self.config.drops)
        if self.armed_at is not None:
            windows += [(self.armed_at + start, dur) for start, dur in self.config.arm_drops]
        broken = self.config.drops_break_link and self.opened_at is not None
        return any(start <= t < start + dur or (broken and self.opened_at <= start <= t) for start, dur in windows)

    def _serialise(self, t: float, nbytes: int, free_at: float) -> float | None:
        """Delivery time of a frame given the serial budget, or None if the buffer overflows."""
        c = self.config
        return queue_frame(t, nbytes, free_at, c.baud, c.buffer_bytes, c.max_queue_s)

    # -- outgoing ----------------------------------------------------------------
    def send(self, msg, t: float) -> None:
        """Pack and queue ``msg`` (a pymavlink message object) at simulated time ``t``."""
        if self.closed:
            return
        with self._lock:
            self._now = t
            try:
                self.mav.send(msg)
            except Exception:  # noqa: BLE001 - a message that cannot be packed is a bug, not a crash
                self.stats["pack_errors"] += 1

    def _outgoing(self, frame: bytes) -> None:
        t = self._now
        if self.tlog is not None:
            self.tlog.write(t, frame)
        self.stats["tx_frames"] += 1
        if self.is_down(t) or (self.config.loss > 0 and self._rng_tx.random() < self.config.loss):
            self.stats["tx_lost"] += 1
            return
        done = self._serialise(t, len(frame), self._tx_free)
        if done is None:
            self.stats["tx_overflow"] += 1
            return
        self._tx_free = done
        self.stats["tx_bytes"] += len(frame)  # bytes the radio will deliver (after loss and overflow)
        self._out.append((done + self.config.latency_s, frame))

    def pop_outgoing(self, t: float) -> bytes:
        """All outgoing bytes due by simulated time ``t`` (frames stay whole)."""
        with self._lock:
            chunks = []
            while self._out and self._out[0][0] <= t:
                chunks.append(self._out.popleft()[1])
            out = b"".join(chunks)
            self.stats["tx_delivered_bytes"] += len(out)
            return out

    # -- incoming ----------------------------------------------------------------
    def feed(self, data: bytes, t: float) -> None:
        """Bytes received from the transport at simulated time ``t``."""
        if self.closed or not data:
            return
        with self._lock:
            self.stats["rx_bytes"] += len(data)
            try:
                msgs = self.mav.parse_buffer(bytes(data)) or []
            except Exception:  # noqa: BLE001 - hostile input must never take the vehicle down
                # pymavlink raised on garbage it could not classify: drop the buffer and resync
                self.stats["parse_errors"] += 1
                self.mav.buf = bytearray()
                self.mav.buf_index = 0
                self.mav.expected_length = mavlink2.HEADER_LEN_V1 + 2
                self.mav.have_prefix_error = False
                msgs = []
            for m in msgs:
                if m.get_type() == "BAD_DATA":
                    self.stats["rx_bad"] += 1
                    continue
                if self.is_down(t) or (self.config.loss > 0 and self._rng_rx.random() < self.config.loss):
                    self.stats["rx_lost"] += 1
                    continue
                if self.tlog is not None:  # what the vehicle really received (after the radio's losses)
                    self.tlog.write(t, m.get_msgbuf())
                done = self._serialise(t, len(m.get_msgbuf()), self._rx_free)
                if done is None:
                    self.stats["rx_overflow"] += 1
                    continue
                self._rx_free = done
                self.stats["rx_frames"] += 1
                self._in.append((done + self.config.latency_s, m))

    def pop_incoming(self, t: float) -> list:
        """Parsed messages that have arrived by simulated time ``t``."""
        with self._lock:
            out = []
            while self._in and self._in[0][0] <= t:
                out.append(self._in.popleft()[1])
            return out

    def close(self) -> None:
        self.closed = True


def parse_link_spec(spec: str) -> tuple[str, str, int]:
    """``tcp:HOST:PORT`` | ``udpin:HOST:PORT`` | ``udpout:HOST:PORT`` -> (kind, host, port).

    Raises ValueError naming the problem.
    """
    parts = spec.split(":")
    if len(parts) != 3 or parts[0] not in ("tcp", "udpin", "udpout", "udp"):
        raise ValueError(f"bad link {spec!r}; expected tcp:HOST:PORT, udpin:HOST:PORT or udpout:HOST:PORT")
    kind = "udpin" if parts[0] == "udp" else parts[0]
    try:
        port = int(parts[2])
    except ValueError:
        raise ValueError(f"bad port in {spec!r}") from None
    if not (0 <= port < 65536) or (port == 0 and kind == "udpout"):
        raise ValueError(f"port out of range in {spec!r}")
    return kind, parts[1] or "127.0.0.1", port
