"""The :class:`Simulator`: clock, links, transports (in-process and sockets).

Two ways to run it:

* **Lockstep** (tests): nothing happens until you call :meth:`Simulator.step` /
  :meth:`Simulator.run_until`; messages written by an in-process GCS endpoint are
  taken in at the next step, replies are readable once their (simulated)
  delivery time has passed.
* **Served** (:meth:`Simulator.serve`): a background thread advances simulated
  time at ``speedup`` x wall-clock time and moves bytes between the links and
  TCP/UDP sockets (and in-process endpoints). :meth:`Simulator.stop` ends it.

All stream rates, timeouts and link impairments are in simulated time, so a
speedup of 100 behaves like real time, only faster.
"""

from __future__ import annotations

import collections
import select
import socket
import threading
import time
from collections.abc import Iterable

from vehicle_sim.autopilot import Autopilot
from vehicle_sim.boat import CurrentModel
from vehicle_sim.config import LinkConfig, SimConfig
from vehicle_sim.link import Link, TlogWriter, parse_link_spec

__all__ = ["Simulator", "InProcessEndpoint", "STEP_COMMAND"]

#: COMMAND_LONG id a GCS sends to advance a lockstep-served simulator (MAV_CMD_USER_1)
STEP_COMMAND = 31010


class InProcessEndpoint:
    """GCS side of an in-memory link: ``write(bytes)`` to the vehicle, ``read() -> bytes`` from it.

    Thread-safe. ``read`` returns at once (``b""`` when nothing has arrived); in
    lockstep nothing arrives until the simulator steps. ``wait_readable`` blocks until
    something has arrived, and ``write`` wakes a serving thread, so a GCS and a served
    simulator hand a lockstep step back and forth without polling delays. A pymavlink
    ``MAVLink`` object can use the endpoint as its file (it calls ``write``).
    """

    def __init__(self, sim: Simulator, link: Link):
        self.sim = sim
        self.link = link
        self._lock = threading.Lock()
        self._inbox: collections.deque[bytes] = collections.deque()  # GCS -> vehicle, not yet taken
        self._outbox = bytearray()  # vehicle -> GCS, delivered
        self._readable = threading.Event()  # set while the outbox holds bytes
        self.closed = False

    def write(self, buf: bytes) -> int:
        if self.closed:
            return 0
        with self._lock:
            self._inbox.append(bytes(buf))
        self.sim._wake.set()
        return len(buf)

    def read(self, n: int | None = None) -> bytes:
        with self._lock:
            if n is None or n >= len(self._outbox):
                out = bytes(self._outbox)
                self._outbox.clear()
                self._readable.clear()
            else:
                out = bytes(self._outbox[:n])
                del self._outbox[:n]
            return out

    def wait_readable(self, timeout: float) -> bool:
        """Wait at most ``timeout`` wall seconds for delivered bytes; True when some are there."""
        return self._readable.wait(timeout)

    def pending(self) -> int:
        """Bytes delivered and not read yet."""
        with self._lock:
            return len(self._outbox)

    # simulator side
    def _take_inbox(self) -> bytes:
        with self._lock:
            data = b"".join(self._inbox)
            self._inbox.clear()
            return data

    def _deliver(self, data: bytes) -> None:
        if data:
            with self._lock:
                self._outbox += data
                self._readable.set()

    def close(self) -> None:
        self.closed = True
        self.sim._remove_link(self.link)

    def mavlink_connection(self, **kw):
        """A pymavlink ``mavutil``-compatible connection on this endpoint (see :mod:`vehicle_sim.inprocess`)."""
        from vehicle_sim.inprocess import InProcessMavfile

        return InProcessMavfile(self, **kw)


def serve_paced(owner, speedup: float, wait_for_client: bool, poll_s: float, max_dt: float) -> None:
    """The serving loop of a :class:`Simulator` or a :class:`~vehicle_sim.fleet.Fleet` (``owner``),
    until ``owner._stop`` is set: poll the sockets, then either advance in lockstep (the steps
    clients asked for) or keep simulated time at ``speedup`` x wall time.

    ``owner`` provides ``t`` and ``step(dt)`` (simulated s), ``_stop``, ``_lockstep``,
    ``_serve_sockets()`` (socket entries), ``_serve_budget()`` (lockstep seconds asked for),
    ``_serve_tick()`` (per-round chores), ``_poll_sockets(timeout)``, ``_flush_sockets()`` and
    ``_lockstep_round(max_dt)``. With ``wait_for_client`` the clock holds at its start until a
    first TCP client connects.
    """
    have_tcp = any(e["kind"] == "tcp-listen" for e in owner._serve_sockets())
    waiting = wait_for_client and have_tcp
    wall0 = time.monotonic()
    sim0 = owner.t
    while not owner._stop.is_set():
        owner._serve_tick()
        owner._poll_sockets(poll_s if not (owner._lockstep and owner._serve_budget() > 0) else 0.0)
        if owner._lockstep:
            owner._lockstep_round(max_dt)
            continue
        if waiting:
            if any(e["kind"] == "tcp-client" for e in owner._serve_sockets()):
                waiting = False
                wall0, sim0 = time.monotonic(), owner.t
            continue
        target = sim0 + (time.monotonic() - wall0) * speedup
        behind = target - owner.t
        if behind > 5.0 + 50 * max_dt:
            # too slow to keep up: let the clock slip rather than spiral: the target falls back to
            # 5 s ahead (moving sim0 the other way pushed it further ahead on every slip, and a
            # served simulator once behind ran flat out at any --speedup)
            sim0 -= behind - 5.0
            target = sim0 + (time.monotonic() - wall0) * speedup
        steps = 0
        while owner.t + 1e-9 < target and steps < 200 and not owner._stop.is_set():
            owner.step(min(max_dt, target - owner.t))
            steps += 1
            if steps % 20 == 0:
                owner._flush_sockets()
                # read the GCS too while catching up: 200 steps are 10 s of simulated time, longer
                # than the vehicle's 8 s mission-transfer timeout (uploads were cancelled at >100x)
                owner._poll_sockets(0.0)
        owner._flush_sockets()


class Clocked:
    """``run_until`` / ``run_until_condition`` for anything with ``t`` and ``step(dt)`` (a simulator, a fleet)."""

    def run_until(self, t: float) -> None:
        """Advance until simulated time ``t``."""
        if t > self.t:
            self.step(t - self.t)

    def run_until_condition(self, cond, timeout: float, dt: float | None = None) -> bool:
        """Step until ``cond()`` is true or ``timeout`` simulated seconds pass; returns cond()."""
        end = self.t + timeout
        while not cond():
            if self.t >= end:
                return bool(cond())
            self.step(dt)
        return True


class Simulator(Clocked):
    """A simulated ArduPilot Rover boat in a current field.

    Args:
        field: a :class:`passt_mav.fields.FlowField`, or None for still water.
        home: ``(lat, lon)`` degrees where the boat starts (and home).
        config: :class:`SimConfig`.
        velocity_scale, time_scale, start_time, uniform_current: see
            :class:`vehicle_sim.boat.CurrentModel`.
        link_config: default impairment for new links.
        epoch0: UTC epoch seconds at boot (default: now).
    """

    def __init__(
        self,
        field=None,
        *,
        home: tuple[float, float],
        config: SimConfig | None = None,
        velocity_scale: float = 1.0,
        time_scale: float = 1.0,
        start_time: float | None = None,
        uniform_current: tuple[float, float] = (0.0, 0.0),
        link_config: LinkConfig | None = None,
        epoch0: float | None = None,
        current: CurrentModel | None = None,
    ):
        self.config = config or SimConfig()
        self.field = field
        # ``current``: a CurrentModel shared with other boats (a Fleet); it replaces the one
        # built from field/start_time/velocity_scale/time_scale/uniform_current
        self.current = (
            current
            if current is not None
            else CurrentModel(
                field,
                start_time=start_time,
                velocity_scale=velocity_scale,
                time_scale=time_scale,
                uniform=uniform_current,
            )
        )
        self.link_config = link_config or LinkConfig()
        self.epoch0 = time.time() if epoch0 is None else float(epoch0)
        self.links: list[Link] = []
        self._endpoints: dict[int, InProcessEndpoint] = {}
        self.tlog = TlogWriter(self.config.tlog, self.epoch0) if self.config.tlog else None
        self.autopilot = Autopilot(home, self.current, self.config, self._send, lambda: self.links, epoch0=self.epoch0)
        self._lock = threading.RLock()
        self._next_index = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        #: set by an in-process endpoint's write: a serving thread without sockets waits on it, not a sleep
        self._wake = threading.Event()
        self._sockets: list = []
        self.running = False
        self.error: BaseException | None = None
        self._lockstep = False
        self._step_budget = 0.0
        self._step_waiters: list = []
        self._fleet = None  # set by vehicle_sim.fleet.Fleet: step() then advances every boat of the fleet

    # -- clock -------------------------------------------------------------------------
    @property
    def t(self) -> float:
        """Simulated seconds since the simulator started (= since boot until a :meth:`reboot`)."""
        return self.autopilot.clock

    def reboot(self, downtime_s: float = 2.0, drop_tcp: bool = True) -> None:
        """Reboot the autopilot now (a brown-out or watchdog reset; see :meth:`Autopilot.reboot`).

        ``drop_tcp``: close every TCP client connection, as SITL does when it restarts (its
        clients see EOF and must reconnect); in-process and UDP links stay (a radio link does).
        """
        with self._lock:
            self.autopilot.reboot_requested = False
            if drop_tcp:
                for e in [e for e in self._sockets if e["kind"] == "tcp-client"]:
                    self._close_entry(e)
            self.autopilot.reboot(downtime_s)

    def step(self, dt: float | None = None) -> None:
        """Advance simulated time by ``dt`` (default one physics step), in physics sub-steps.

        A boat of a :class:`vehicle_sim.fleet.Fleet` has no clock of its own: this advances
        the whole fleet (every boat, the same ``dt``), so a client stepping "its" boat keeps
        the others in time.
        """
        if self._fleet is not None:
            self._fleet.step(dt)
            return
        dt = self.config.physics_dt if dt is None else float(dt)
        with self._lock:
            remaining = dt
            while remaining > 1e-12:
                h = min(self.config.physics_dt, remaining)
                self._tick(h)
                remaining -= h

    def _tick(self, h: float) -> None:
        self._process_incoming()
        self.autopilot.update(h)
        self._deliver_inprocess()
        if self.autopilot.reboot_requested:  # MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, acknowledged above
            self._flush_sockets()  # the ACK goes out before the links drop, as on ArduPilot
            self.reboot()

    def _process_incoming(self) -> None:
        ap = self.autopilot
        for link in list(self.links):
            ep = self._endpoints.get(id(link))
            if ep is not None:
                data = ep._take_inbox()
                if data:
                    link.feed(data, ap.clock)
            for msg in link.pop_incoming(ap.clock):
                if (
                    self._lockstep
                    and msg.get_type() == "COMMAND_LONG"
                    and msg.command == STEP_COMMAND
                    and msg.target_system in (0, self.config.sysid)
                ):
                    self._step_budget += max(0.0, float(msg.param1)) if msg.param1 == msg.param1 else 0.0
                    self._step_waiters.append((link, msg))
                    continue
                ap.handle(link, msg)

    def _deliver_inprocess(self) -> None:
        t = self.autopilot.clock
        for link in list(self.links):
            ep = self._endpoints.get(id(link))
            if ep is not None:
                ep._deliver(link.pop_outgoing(t))

    # -- links --------------------------------------------------------------------------
    def _send(self, link: Link, msg) -> None:
        link.send(msg, self.autopilot.clock)

    def add_link(self, name: str = "", config: LinkConfig | None = None) -> Link:
        """A new link (channel); its index picks its MAVn_* stream parameters."""
        with self._lock:
            cfg = config or self.link_config
            link = Link(
                self._next_index,
                cfg,
                sysid=self.config.sysid,
                compid=self.config.compid,
                tlog=self.tlog,
                signing_secret=self.config.signing_key,
                name=name,
            )
            link.armed_at = self.autopilot.first_armed_clock  # a link opened after the first arming
            link.opened_at = self.autopilot.clock
            self._next_index += 1
            self.links.append(link)
            return link

    def _remove_link(self, link: Link) -> None:
        with self._lock:
            link.close()
            if link in self.links:
                self.links.remove(link)
            self._endpoints.pop(id(link), None)
            self.autopilot.forget_link(link)

    def connect_inprocess(self, config: LinkConfig | None = None) -> InProcessEndpoint:
        """A new in-memory link; returns its GCS-side endpoint (``write``/``read`` bytes)."""
        with self._lock:
            link = self.add_link("inprocess", config)
            ep = InProcessEndpoint(self, link)
            self._endpoints[id(link)] = ep
            return ep

    # -- serving over sockets -------------------------------------------------------------
    def serve(
        self,
        listen: Iterable[str] = (),
        speedup: float = 1.0,
        wait_for_client: bool = False,
        link_configs: dict[str, LinkConfig] | None = None,
        poll_s: float = 0.002,
        lockstep: bool = False,
    ) -> None:
        """Run in a background thread: simulated time = ``speedup`` x wall time.

        ``lockstep``: the clock stands still (messages are still answered at the
        frozen time) until a GCS sends COMMAND_LONG ``MAV_CMD_USER_1`` (31010) with
        ``param1`` = seconds to advance; the simulator then runs those seconds as
        fast as it can and acknowledges the command (COMMAND_ACK ACCEPTED) when
        done. ``speedup`` is ignored.

        ``listen``: ``tcp:HOST:PORT`` (server; every client is its own link),
        ``udpin:HOST:PORT`` (bind; reply to the last sender), ``udpout:HOST:PORT``
        (send to it, like SITL's GCS output). ``wait_for_client``: hold the clock at
        0 until a first TCP client connects (like SITL).
        Sockets are opened before this returns (bind errors raise here).
        """
        if self._thread is not None:
            raise RuntimeError("simulator already serving")
        if speedup <= 0:
            raise ValueError("speedup must be positive")
        self._open_listeners(listen, link_configs)
        self._stop.clear()
        self.running = True
        self._lockstep = bool(lockstep)
        self._thread = threading.Thread(
            target=self._serve_loop, args=(speedup, wait_for_client, poll_s), name="vehicle-sim", daemon=True
        )
        self._thread.start()

    def _open_listeners(self, listen: Iterable[str], link_configs: dict[str, LinkConfig] | None) -> None:
        """Open the sockets of ``listen`` (see :meth:`serve`); bind errors raise here (nothing stays open)."""
        link_configs = link_configs or {}
        self._sockets = []
        try:
            self._open_each(listen, link_configs)
        except BaseException:
            for e in self._sockets:
                e["sock"].close()
            self._sockets = []
            raise

    def _open_each(self, listen: Iterable[str], link_configs: dict[str, LinkConfig]) -> None:
        for spec in listen:
            kind, host, port = parse_link_spec(spec)
            cfg = link_configs.get(spec)
            if kind == "tcp":
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((host, port))
                s.listen(8)
                s.setblocking(False)
                self._sockets.append({"kind": "tcp-listen", "sock": s, "spec": spec, "cfg": cfg})
            else:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.setblocking(False)
                if kind == "udpin":
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                    s.bind((host, port))
                    peer = None
                else:
                    s.bind(("127.0.0.1" if host in ("127.0.0.1", "localhost") else "", 0))
                    peer = (host, port)
                link = self.add_link(spec, cfg)
                self._sockets.append({"kind": kind, "sock": s, "spec": spec, "peer": peer, "link": link})

    def ports(self) -> list[tuple[str, int]]:
        """(spec, bound port) of each socket (useful with port 0)."""
        return [(e["spec"], e["sock"].getsockname()[1]) for e in self._sockets if e["kind"] in ("tcp-listen", "udpin")]

    def _serve_loop(self, speedup: float, wait_for_client: bool, poll_s: float) -> None:
        try:
            serve_paced(self, speedup, wait_for_client, poll_s, max(self.config.physics_dt, 0.0))
        except BaseException as exc:  # noqa: BLE001 - recorded and re-raised by stop()
            self.error = exc
        finally:
            for e in self._sockets:
                try:
                    e["sock"].close()
                except OSError:
                    pass
            self.running = False

    # what serve_paced asks of a served simulator (a Fleet answers for all its boats)
    def _serve_sockets(self):
        return self._sockets

    def _serve_budget(self) -> float:
        return self._step_budget

    def _serve_tick(self) -> None:
        pass

    def _lockstep_round(self, max_dt: float) -> None:
        with self._lock:
            self._process_incoming()
            steps = 0
            while self._step_budget > 1e-9 and steps < 200:
                h = min(max_dt, self._step_budget)
                self._tick(h)
                self._step_budget -= h
                steps += 1
            if self._step_budget <= 1e-9 and self._step_waiters:
                self._step_budget = 0.0
                for link, msg in self._step_waiters:
                    link.send(
                        self.autopilot.MAVLINK.MAVLink_command_ack_message(
                            STEP_COMMAND, 0, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                        ),
                        self.autopilot.clock,
                    )
                self._step_waiters.clear()
            self._deliver_inprocess()
        self._flush_sockets()

    def _poll_sockets(self, timeout: float) -> None:
        socks = [e["sock"] for e in self._sockets]
        if not socks:
            self._wake.wait(timeout)
            self._wake.clear()  # what was written before this is taken in by the round that follows
            return
        try:
            ready, _, _ = select.select(socks, [], [], timeout)
        except (OSError, ValueError):
            ready = []
        self._handle_ready(ready)

    def _handle_ready(self, ready) -> None:
        """Accept, read and receive on the sockets in ``ready`` (from a select over ours, or a fleet's)."""
        for e in list(self._sockets):
            if e["sock"] not in ready:
                continue
            kind = e["kind"]
            if kind == "tcp-listen":
                try:
                    c, addr = e["sock"].accept()
                except OSError:
                    continue
                c.setblocking(False)
                c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                link = self.add_link(f"{e['spec']} {addr[0]}:{addr[1]}", e.get("cfg"))
                self._sockets.append({"kind": "tcp-client", "sock": c, "spec": e["spec"], "link": link, "pending": b""})
            elif kind == "tcp-client":
                try:
                    data = e["sock"].recv(65536)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    data = b""
                if not data:
                    self._close_entry(e)
                    continue
                with self._lock:
                    e["link"].feed(data, self.t)
            else:
                while True:
                    try:
                        data, addr = e["sock"].recvfrom(65536)
                    except (BlockingIOError, InterruptedError, ConnectionRefusedError):
                        break
                    except OSError:
                        break
                    if kind == "udpin":
                        e["peer"] = addr
                    with self._lock:
                        e["link"].feed(data, self.t)

    def _close_entry(self, e) -> None:
        try:
            e["sock"].close()
        except OSError:
            pass
        if e in self._sockets:
            self._sockets.remove(e)
        self._remove_link(e["link"])

    def _flush_sockets(self) -> None:
        t = self.t
        for e in list(self._sockets):
            kind = e["kind"]
            if kind == "tcp-client":
                data = e["pending"] + e["link"].pop_outgoing(t)
                if data:
                    try:
                        n = e["sock"].send(data)
                    except (BlockingIOError, InterruptedError):
                        n = 0
                    except OSError:
                        self._close_entry(e)
                        continue
                    # a client that does not read: keep at most 1 MB, then drop (a radio would too)
                    e["pending"] = data[n:][-1_000_000:]
            elif kind in ("udpin", "udpout"):
                data = e["link"].pop_outgoing(t)
                if data and e["peer"] is not None:
                    # one datagram per frame, as MAVLink UDP peers expect
                    for frame in _split_frames(data):
                        try:
                            e["sock"].sendto(frame, e["peer"])
                        except OSError:
                            break
        for link in list(self.links):
            ep = self._endpoints.get(id(link))
            if ep is not None:
                ep._deliver(link.pop_outgoing(t))
                data = ep._take_inbox()
                if data:
                    with self._lock:
                        link.feed(data, t)

    def stop(self) -> None:
        """Stop serving (joins the thread); closes sockets and the tlog."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None
        if self.tlog is not None:
            self.tlog.close()
        if self.error is not None:
            err, self.error = self.error, None
            raise err

    def close(self) -> None:
        self.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def _split_frames(data: bytes) -> list[bytes]:
    """Split a run of whole MAVLink frames (v1/v2, signed or not) into frames."""
    out, i, n = [], 0, len(data)
    while i < n:
        magic = data[i]
        if magic == 0xFD and i + 10 <= n:
            ln = 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
        elif magic == 0xFE and i + 6 <= n:
            ln = 8 + data[i + 1]
        else:
            out.append(data[i:])
            break
        out.append(data[i : i + ln])
        i += ln
    return out
