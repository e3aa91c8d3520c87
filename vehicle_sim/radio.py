"""A telemetry radio between a vehicle and a ground station: baud rate, latency, loss, a small buffer.

A SiK-style radio pair at ``baud`` moves ``baud / 10`` bytes per second each way (8N1 on the
UART), delays every frame by ``latency_s``, loses a fraction ``loss`` of the frames and holds
only ``buffer_bytes`` waiting to be sent: a frame that does not fit in what is left of the
transmit buffer is dropped (a SiK radio's buffer is about 2 kB). The model is one rule,
:func:`queue_frame`, applied per direction with whatever clock the caller keeps:

* **simulated time** - ``vehicle-sim``'s own links (:class:`vehicle_sim.link.Link`) use it
  with the lockstep clock: ``LinkConfig.radio(57600)`` is this radio (on the command line
  ``vehicle-sim --baud 57600 --latency 0.1 --loss 0.03 --radio-buffer 2048``). Results then
  do not depend on the machine's load.
* **wall time** - :class:`RadioProxy` is a TCP proxy on 127.0.0.1 between a MAVLink TCP
  server (ArduPilot SITL's ``tcp:127.0.0.1:5760``) and one client (a controller, MAVProxy),
  each frame cut out of the byte stream by pymavlink's parser and passed through a
  :class:`RadioChannel` per direction in ``time.monotonic()`` seconds.

What it leaves out: a real SiK pair shares its air time between the two directions
(TDM; this model gives each direction the whole ``baud``), retransmits nothing (nor does
this), and its own RADIO_STATUS reports are not sent.
"""

from __future__ import annotations

import collections
import random
import socket
import threading
import time
from dataclasses import dataclass
from typing import Self

__all__ = ["RadioConfig", "RadioChannel", "RadioProxy", "queue_frame"]


@dataclass(frozen=True)
class RadioConfig:
    """One radio link (both directions alike).

    Attributes:
        baud: UART rate (bit/s); ``baud / 10`` bytes/s each way. 0 = unlimited.
        latency_s: one-way delay added to every frame (s).
        loss: probability that a frame is lost, each direction independently.
        buffer_bytes: transmit buffer of each radio (bytes); a frame that does not fit is dropped.
            0 = unbounded.
        seed: seed of the loss draws.
    """

    baud: int = 57600
    latency_s: float = 0.1
    loss: float = 0.03
    buffer_bytes: int = 2048
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {self.loss}")
        if self.baud < 0 or self.latency_s < 0 or self.buffer_bytes < 0:
            raise ValueError("baud, latency_s and buffer_bytes must be >= 0")

    @property
    def bytes_per_s(self) -> float:
        """Capacity of each direction (bytes/s), ``baud / 10``; inf when unlimited."""
        return self.baud / 10.0 if self.baud else float("inf")


def queue_frame(
    t: float, nbytes: int, free_at: float, baud: int, buffer_bytes: int = 0, max_queue_s: float = float("inf")
) -> float | None:
    """When a frame of ``nbytes`` offered at time ``t`` has left the radio, or None when it is dropped.

    ``free_at``: when the radio finishes what it already holds (same clock as ``t``, s). The
    backlog at ``t`` is ``(free_at - t) * baud / 10`` bytes; the frame is dropped when the backlog
    plus the frame exceeds ``buffer_bytes`` (> 0), or when it would wait more than ``max_queue_s``.
    """
    if baud <= 0:
        return t
    start = max(t, free_at)
    rate = baud / 10.0
    if buffer_bytes > 0 and (start - t) * rate + nbytes > buffer_bytes:
        return None
    if start - t > max_queue_s:
        return None
    return start + nbytes / rate


class RadioChannel:
    """One direction of a radio: frames in at time t, out at their delivery time (caller's clock).

    ``stats``: ``frames``, ``bytes`` offered; ``lost`` (radio loss), ``overflow`` (did not fit in the
    buffer); ``delivered``, ``delivered_bytes``.
    """

    def __init__(self, config: RadioConfig, *, seed_offset: int = 0):
        self.config = config
        self._rng = random.Random((config.seed * 1_000_003 + seed_offset) & 0xFFFFFFFF)
        self._free = float("-inf")
        self._q: collections.deque[tuple[float, bytes]] = collections.deque()
        self._lock = threading.Lock()
        self.stats: collections.Counter = collections.Counter()

    def offer(self, frame: bytes, t: float) -> bool:
        """Queue a whole frame at time ``t``; False when lost or dropped for lack of buffer."""
        c = self.config
        with self._lock:
            self.stats["frames"] += 1
            self.stats["bytes"] += len(frame)
            if c.loss > 0 and self._rng.random() < c.loss:
                self.stats["lost"] += 1
                return False
            done = queue_frame(t, len(frame), self._free, c.baud, c.buffer_bytes)
            if done is None:
                self.stats["overflow"] += 1
                return False
            self._free = done
            self._q.append((done + c.latency_s, bytes(frame)))
            return True

    def due(self, t: float) -> bytes:
        """The bytes of every frame delivered by time ``t``, in order (frames stay whole)."""
        out = []
        with self._lock:
            while self._q and self._q[0][0] <= t:
                out.append(self._q.popleft()[1])
            self.stats["delivered"] += len(out)
            self.stats["delivered_bytes"] += sum(len(f) for f in out)
        return b"".join(out)

    def next_due(self) -> float | None:
        with self._lock:
            return self._q[0][0] if self._q else None


class _Framer:
    """Cuts whole MAVLink frames (v1 or v2) out of a byte stream with pymavlink's parser."""

    def __init__(self):
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2

        self._mav = mavlink2.MAVLink(None)
        self._mav.robust_parsing = True

    def frames(self, data: bytes) -> list[bytes]:
        msgs = self._mav.parse_buffer(data) or []
        return [bytes(m.get_msgbuf()) for m in msgs if m.get_type() != "BAD_DATA"]


class RadioProxy:
    """A wall-time radio between a MAVLink TCP server and the clients that connect to this proxy.

    Listens on ``127.0.0.1:port`` (``port`` 0: a free one, see :attr:`port`). Each accepted client
    gets its own connection to ``upstream`` (host, port) and its own pair of
    :class:`RadioChannel` s (up: client -> server, down: server -> client), seeded apart. Use as a
    context manager, or :meth:`start` / :meth:`stop`. ``channels`` lists ``(up, down)`` per client.

    ArduPilot SITL serves one client on its SERIAL0 port and waits for it: the proxy connects to it
    only when its own client arrives, and never probes it.
    """

    def __init__(self, upstream: tuple[str, int], config: RadioConfig, *, port: int = 0):
        self.upstream = upstream
        self.config = config
        self._srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._srv.bind(("127.0.0.1", int(port)))
        self._srv.listen(4)
        self.port: int = self._srv.getsockname()[1]
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._socks: list[socket.socket] = []
        self.channels: list[tuple[RadioChannel, RadioChannel]] = []
        self.t0 = time.monotonic()
        self._down_until = 0.0  # monotonic s: every frame offered before then is lost (:meth:`outage`)

    @property
    def connect(self) -> str:
        """The pymavlink connection string of this proxy (``tcp:127.0.0.1:PORT``)."""
        return f"tcp:127.0.0.1:{self.port}"

    def start(self) -> Self:
        self._spawn(self._accept_loop, "radio-accept")
        return self

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        self._stop.set()
        for s in [self._srv] + self._socks:
            try:
                s.close()
            except OSError:
                pass
        for th in self._threads:
            th.join(timeout=2.0)

    def outage(self, seconds: float) -> None:
        """The radio goes out of range for ``seconds`` of wall time from now: every frame, both ways, is lost
        (the TCP connections on either side stay open, as a telemetry radio's serial port does)."""
        self._down_until = time.monotonic() + float(seconds)

    def stats(self) -> dict[str, collections.Counter]:
        """Counters summed over the clients: ``{"up": ..., "down": ...}``."""
        up, down = collections.Counter(), collections.Counter()
        for a, b in self.channels:
            up.update(a.stats), down.update(b.stats)
        return {"up": up, "down": down}

    def _spawn(self, fn, name: str, *args) -> None:
        th = threading.Thread(target=fn, args=args, name=name, daemon=True)
        th.start()
        self._threads.append(th)

    def _accept_loop(self) -> None:
        self._srv.settimeout(0.2)
        while not self._stop.is_set():
            try:
                cli, _ = self._srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                up_sock = socket.create_connection(self.upstream, timeout=10.0)
            except OSError:
                cli.close()
                continue
            for s in (cli, up_sock):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(0.2)
                self._socks.append(s)
            n = len(self.channels)
            up, down = RadioChannel(self.config, seed_offset=2 * n), RadioChannel(self.config, seed_offset=2 * n + 1)
            self.channels.append((up, down))
            self._spawn(self._pump_in, f"radio-up{n}", cli, up, up_sock)
            self._spawn(self._pump_in, f"radio-down{n}", up_sock, down, cli)
            self._spawn(self._pump_out, f"radio-out{n}", [(up, up_sock), (down, cli)])

    def _pump_in(self, src: socket.socket, ch: RadioChannel, other: socket.socket) -> None:
        """Read a socket, offer each whole frame to the radio at the time it arrived. When ``src`` closes, the
        other side is closed too (a client that hangs up frees the server's port for the next one)."""
        framer = _Framer()
        while not self._stop.is_set():
            try:
                data = src.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                data = b""
            if not data:
                try:
                    other.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                return
            now = time.monotonic()
            for f in framer.frames(data):
                if now < self._down_until:
                    ch.stats["outage"] += 1
                    continue
                ch.offer(f, now)

    def _pump_out(self, pairs: list[tuple[RadioChannel, socket.socket]]) -> None:
        """Write each frame to its destination at its delivery time."""
        while not self._stop.is_set():
            now = time.monotonic()
            for ch, dst in pairs:
                data = ch.due(now)
                if data:
                    try:
                        dst.sendall(data)
                    except OSError:
                        return
            nxt = [t for ch, _ in pairs if (t := ch.next_due()) is not None]
            time.sleep(min(0.005, max(0.0, min(nxt) - time.monotonic())) if nxt else 0.005)
