"""The MAVLink link to one vehicle: connection, reader thread, heartbeats, commands.

A :class:`Link` wraps one pymavlink ``mavutil`` connection (MAVLink 2,
ardupilotmega dialect). One background thread reads every message and
dispatches it (subscriber queues, listener callbacks, latest message per type,
statistics, tlog); a second thread sends the GCS HEARTBEAT at 1 Hz. Sending is
thread-safe. All times here are wall-clock seconds on the link's :attr:`Link.clock`
(:mod:`passt_mav.mavlink.clock`), which every user of the link asks too.

Written to shared/ARDUPILOT_ROVER.md, independently of ``vehicle_sim``::

    link = Link(LinkConfig("tcp:127.0.0.1:5760")).connect()
    ack = link.command_long(mavlink2.MAV_CMD_DO_SET_MODE, 1, 4)   # HOLD
    link.close()

Tests hand the link any ``mavutil.mavfile`` (e.g. an in-process simulator
endpoint) through ``connection_factory``.
"""

from __future__ import annotations

import collections
import hashlib
import logging
import os
import socket
import struct
import threading
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Self

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is imported: talk MAVLink 2
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from passt_mav.errors import CommandRejected, LinkTimeout, LinkUnavailable, MavlinkError, UserError  # noqa: E402
from passt_mav.mavlink.clock import SYSTEM_CLOCK, Clock, StepBudget, Timeout  # noqa: E402
from passt_mav.mavlink.link_stats import LinkAccounting, LinkStats  # noqa: E402
from passt_mav.mavlink.routing import Message, MessageRouter, Subscription  # noqa: E402
from passt_mav.mavlink.streams import request_streams  # noqa: E402

__all__ = [
    "LinkConfig",
    "Link",
    "Subscription",
    "LinkStats",
    "secret_from_key",
    "result_name",
    "mavlink2",
    "DEFAULT_SOURCE_SYSTEM",
    "DEFAULT_SOURCE_COMPONENT",
    "GCS_IDENTITY",
]

log = logging.getLogger(__name__)

#: Our MAVLink identity by default (docs/real-boat.md, "Identity on a shared link"): system 245, component 195.
#: Not 255: QGroundControl, Mission Planner and MAVProxy speak as system 255 and ArduPilot's GCS failsafe
#: (FS_GCS_ENABLE) counts only heartbeats from MAV_GCS_SYSID (255 by default): a controller with 255 would
#: keep that failsafe fed after the real ground station is gone, and take the vehicle's replies meant for
#: QGC. Not the vehicle's own (1, or 1..N in a fleet) and not 200 (Blue Robotics' BlueOS companion).
#: Component 195 is MAV_COMP_ID_PATHPLANNER: what this program is. On the boat's companion computer
#: use the vehicle's system id and keep component 195 (``--source-system``).
DEFAULT_SOURCE_SYSTEM = 245
DEFAULT_SOURCE_COMPONENT = mavlink2.MAV_COMP_ID_PATHPLANNER  # 195
#: QGroundControl's and Mission Planner's identity (system, component): never ours by default
GCS_IDENTITY = (255, mavlink2.MAV_COMP_ID_MISSIONPLANNER)  # (255, 190)
#: how long one TCP connect may take before the address counts as unreachable (wall s)
_TCP_CONNECT_TIMEOUT_S = 5.0

_CONNECT_PREFIXES = ("tcp:", "tcpin:", "udp:", "udpin:", "udpout:", "udpbcast:")
#: messages a signing GCS still accepts unsigned (as ArduPilot does: the radio's own reports)
_UNSIGNED_OK = frozenset({mavlink2.MAVLINK_MSG_ID_RADIO_STATUS})
_DEFAULT_STREAMS = (
    ("GLOBAL_POSITION_INT", 1.0),
    ("MISSION_CURRENT", 1.0),
    ("EKF_STATUS_REPORT", 1.0),
    ("SYSTEM_TIME", 1.0),
)
_SIGNING_HINT = "the vehicle may require MAVLink 2 signing (signing key, --signing-key)"


class _BoundedTcp(mavutil.mavtcp):
    """pymavlink's TCP client with one connect attempt bounded by :data:`_TCP_CONNECT_TIMEOUT_S`."""

    def __init__(self, device: str, **kw):
        super().__init__(device, autoreconnect=False, retries=0, **kw)

    def do_connect(self) -> None:
        self.port = None
        self.port = socket.create_connection(self.destination_addr, timeout=_TCP_CONNECT_TIMEOUT_S)
        self.port.setblocking(False)
        mavutil.set_close_on_exec(self.port.fileno())
        self.port.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)


def _why_not_open(exc: BaseException) -> str:
    """One short phrase for a transport that did not open (what the user can check)."""
    import errno

    if isinstance(exc, ConnectionRefusedError):
        return (
            "connection refused (nothing listens there: is the vehicle, SITL or the router running, is the port right?)"
        )
    if isinstance(exc, socket.gaierror):
        return f"unknown host ({exc.strerror or exc})"
    if isinstance(exc, (socket.timeout, TimeoutError)):
        return f"no answer within {_TCP_CONNECT_TIMEOUT_S:g} s (host unreachable or filtered)"
    if isinstance(exc, FileNotFoundError):
        return exc.strerror or "no such device"
    if isinstance(exc, PermissionError):
        return "permission denied (serial devices: add the user to the dialout group)"
    code = getattr(exc, "errno", None)
    if code in (errno.ENETUNREACH, errno.EHOSTUNREACH):
        return "network or host unreachable"
    if code == errno.EADDRINUSE:
        return "address already in use (another program listens there: MAVProxy, a ground station?)"
    if code == errno.EADDRNOTAVAIL:
        return "cannot bind that address (not one of this machine's)"
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if "No such file or directory" in text or "could not open port" in text:
        return f"no such serial device ({text})"
    return text


class _TransportClosed(ConnectionError):
    """The transport reached EOF or was reset: raised from pymavlink's hooks instead of its print-and-retry."""


def secret_from_key(key: str | bytes) -> bytes:
    """32-byte MAVLink 2 signing secret: 64 hex digits taken as is, else sha256 of the passphrase.

    Same rule as MAVProxy's ``signing setup PASSPHRASE``, so one passphrase works on both ends.
    (vehicle_sim has its own copy on purpose: DESIGN.md keeps the two sides of the protocol
    independent, so neither imports the other.)
    """
    if isinstance(key, bytes):
        return key if len(key) == 32 else hashlib.sha256(key).digest()
    s = key.strip()
    if len(s) == 64:
        try:
            return bytes.fromhex(s)
        except ValueError:
            pass
    return hashlib.sha256(s.encode("utf-8")).digest()


def result_name(enum: str, value: int) -> str:
    """Name of a MAVLink enum value from pymavlink (``MAV_MISSION_RESULT``, 4 -> ``MAV_MISSION_NO_SPACE``)."""
    entry = mavlink2.enums.get(enum, {}).get(int(value))
    return entry.name if entry is not None else f"{enum} {value}"


@dataclass(frozen=True)
class LinkConfig:
    """How to reach the vehicle and how patient to be (seconds are wall-clock).

    Attributes:
        connect: pymavlink connection string as MAVProxy users write it:
            ``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``udp:HOST:PORT``
            or a serial device ``/dev/ttyUSB0,57600`` (``DEVICE,BAUD``; default ``baud``).
        source_system, source_component: our identity on the link (default
            :data:`DEFAULT_SOURCE_SYSTEM`/:data:`DEFAULT_SOURCE_COMPONENT`, 245/195; see there why
            not QGroundControl's 255/190). Mission-protocol and command replies addressed to another
            system/component are not ours and are ignored (0 = broadcast, accepted).
        target_system: the vehicle's sysid, or None for the first vehicle heartbeat.
        heartbeat_period_s: GCS heartbeat period.
        link_lost_s: no vehicle heartbeat for this long = link lost.
        signing_key: MAVLink 2 signing passphrase or 64 hex digits (None = unsigned).
        timeout_s: smallest reply timeout; the link raises it to 4 x measured RTT + 0.1 s.
        retries: resends of a command / protocol step before :class:`LinkTimeout`.
        connect_timeout_s: how long :meth:`Link.connect` waits for a vehicle heartbeat.
        reconnect_backoff_s: ``(first, max)`` delays between reconnect attempts (doubling).
        reconnect_attempts: attempts of :meth:`Link.reconnect`.
        tlog: path of a telemetry log (MAVProxy ``.tlog`` format, in and out), or None.
        stream_rates_hz: ``((MESSAGE_NAME, hz), ...)`` requested with SET_MESSAGE_INTERVAL. TIMESYNC is
            skipped (not a stream on ArduPilot: refused); see ``timesync_period_s``. A message the vehicle
            refuses it for is asked for by its REQUEST_DATA_STREAM group instead (``streams.STREAM_GROUPS``).
        quiet_other_streams: when ``stream_rates_hz`` is not empty, first stop every data stream on this
            link (REQUEST_DATA_STREAM, all streams, rate 0), so that the vehicle sends only
            ``stream_rates_hz`` (plus what is never a stream: HEARTBEAT, STATUSTEXT, replies,
            NAMED_VALUE_FLOAT): the link budget of a telemetry radio. Stream rates belong to the vehicle's port: a ground station sharing it through a router
            loses those streams too, and streams it requests come back for everyone (MAVProxy: start it
            with ``--streamrate=-1``). False leaves them as they are.
        timesync_period_s: wall seconds between TIMESYNC requests (``tc1 = 0``) that keep the RTT
            estimate current (0 = only at connect).
        baud: serial baud when ``connect`` names a device without one.
        lockstep_s: the vehicle's clock in lockstep (a simulator served with ``vehicle-sim --lockstep``:
            its time stands still until a ground station sends COMMAND_LONG 31010 with param1 = seconds
            to run): vehicle seconds per step, taken only while we wait for the vehicle
            (:class:`Lockstep`); 0 (default) = the vehicle keeps its own clock (a real boat, SITL).
        lockstep_pace: in lockstep, at most this many vehicle seconds per wall second (the display's pace,
            not the science's: what the vehicle does depends on the steps alone); wall timeouts become
            that many vehicle seconds.
    """

    connect: str = "tcp:127.0.0.1:5760"
    source_system: int = DEFAULT_SOURCE_SYSTEM
    source_component: int = DEFAULT_SOURCE_COMPONENT
    target_system: int | None = None
    heartbeat_period_s: float = 1.0
    link_lost_s: float = 5.0
    signing_key: str | bytes | None = field(default=None, repr=False)
    timeout_s: float = 1.5
    retries: int = 5
    connect_timeout_s: float = 30.0
    reconnect_backoff_s: tuple[float, float] = (0.5, 8.0)
    reconnect_attempts: int = 6
    tlog: str | None = None
    stream_rates_hz: tuple[tuple[str, float], ...] = _DEFAULT_STREAMS
    baud: int = 57600
    timesync_period_s: float = 10.0
    quiet_other_streams: bool = True
    lockstep_s: float = 0.0
    lockstep_pace: float = 50.0

    def __post_init__(self) -> None:
        c = self.connect.strip()
        if not c:
            raise UserError("connection string is empty; expected e.g. tcp:127.0.0.1:5760")
        if c.startswith(_CONNECT_PREFIXES):
            parts = c.split(":")
            if len(parts) != 3 or not parts[2].isdigit() or not 0 < int(parts[2]) < 65536:
                raise UserError(f"bad connection string {c!r}; expected KIND:HOST:PORT, e.g. tcp:127.0.0.1:5760")
        elif "," in c:
            dev, _, baud = c.rpartition(",")
            if not dev or not baud.isdigit():
                raise UserError(f"bad serial connection {c!r}; expected DEVICE,BAUD e.g. /dev/ttyUSB0,57600")
        elif not (c.startswith("/") or c.upper().startswith("COM")):
            raise UserError(
                f"bad connection string {c!r}; expected tcp:HOST:PORT, udpin:HOST:PORT, "
                "udpout:HOST:PORT or a serial DEVICE[,BAUD]"
            )
        for name in ("source_system", "source_component"):
            if not 1 <= getattr(self, name) <= 255:
                raise UserError(f"{name} must be in 1..255")
        if self.heartbeat_period_s <= 0 or self.link_lost_s <= 0 or self.timeout_s <= 0:
            raise UserError("heartbeat_period_s, link_lost_s and timeout_s must be positive")
        if self.retries < 0:
            raise UserError("retries must be >= 0")
        if self.lockstep_s < 0 or self.lockstep_pace <= 0:
            raise UserError("lockstep_s must be >= 0 and lockstep_pace positive")

    def open(self):
        """A new pymavlink connection for :attr:`connect` (MAVLink 2, ardupilotmega).

        Raises :class:`~passt_mav.errors.LinkUnavailable` naming the address and the cause (refused,
        unreachable, unknown host, no such serial device, permission, address in use); one attempt,
        the caller retries (:meth:`Link.connect`, :meth:`Link.reconnect`).
        """
        c = self.connect.strip()
        kw = dict(source_system=self.source_system, source_component=self.source_component, use_native=False)
        try:
            if c.startswith("tcp:"):
                # pymavlink's mavtcp connects without a timeout (an unreachable host blocks ~2 min) and
                # retries with prints: one bounded attempt here, the back-off is the caller's
                return _BoundedTcp(c[4:], **kw)
            if c.startswith(_CONNECT_PREFIXES):
                return mavutil.mavlink_connection(c, dialect="ardupilotmega", autoreconnect=False, retries=1, **kw)
            dev, _, baud = c.rpartition(",") if "," in c else (c, "", str(self.baud))
            if not os.path.exists(dev):
                raise FileNotFoundError(2, "no such serial device (radio unplugged? see ls /dev/serial/by-id)")
            return mavutil.mavlink_connection(dev, baud=int(baud), dialect="ardupilotmega", autoreconnect=False, **kw)
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise LinkUnavailable(f"{c}: {_why_not_open(exc)}") from exc


class _Tlog:
    """MAVProxy/pymavlink ``.tlog``: 8-byte big-endian µs UTC timestamp + frame, both directions.

    pymavlink's ``setup_logfile`` writes only received frames, from the reader;
    sent frames come from other threads, so one locked writer records both.

    A write the machine refuses (a full disk, a read-only or vanished file system) is the log's fault, not the
    link's: it never raises. The frame is counted lost (:meth:`lost`), a partial frame is cut off again, the
    failure is said once, and writing is tried again :attr:`RETRY_S` wall seconds later (once the disk has room,
    the log goes on; the log's gap is the lost frames).
    """

    #: wall seconds between tries once a write failed
    RETRY_S = 5.0

    def __init__(self, path: str, clock: Clock):
        self._clock = clock
        self.path = path
        # unbuffered: every frame reaches the OS as it is logged, so a controller killed with SIGKILL loses none
        self._f = open(path, "ab", buffering=0)  # noqa: SIM115 - the telemetry log stays open for the link's life
        self._lock = threading.Lock()
        self._lost_frames = self._lost_bytes = 0
        self._error: str | None = None  # the first failure, as said
        self._retry_at: float | None = None  # (the clock) the next try after a failure; None = writing

    def write(self, frame: bytes) -> None:
        usec = int(self._clock.wall() * 1e6) & ~3
        data = struct.pack(">Q", usec) + bytes(frame)
        with self._lock:
            if self._f.closed:
                return
            if self._retry_at is not None and self._clock.now() < self._retry_at:
                self._lost(len(data))
                return
            try:
                end = os.fstat(self._f.fileno()).st_size
                n = self._f.write(data)
                if n != len(data):
                    os.ftruncate(self._f.fileno(), end)  # the frame whole or not at all: the log stays readable
                    raise OSError(f"short write ({n} of {len(data)} bytes)")
            except OSError as exc:
                self._failed(exc, len(data))
                return
            if self._retry_at is not None:
                self._retry_at = None
                log.warning(
                    "telemetry log %s: writing again (%d messages lost meanwhile)", self.path, self._lost_frames
                )

    def _lost(self, nbytes: int) -> None:
        self._lost_frames += 1
        self._lost_bytes += nbytes

    def _failed(self, exc: OSError, nbytes: int) -> None:
        self._lost(nbytes)
        first = self._error is None
        self._error = self._error or (exc.strerror or str(exc))
        self._retry_at = self._clock.now() + self.RETRY_S
        if first:
            log.warning(
                "telemetry log %s: write failed (%s); the link goes on, lost messages are counted, retrying every "
                "%.0f s",
                self.path,
                self._error,
                self.RETRY_S,
            )

    def lost(self) -> dict | None:
        """The frames not logged: ``{"frames", "bytes", "error" (the first), "path"}``; None when none was lost."""
        with self._lock:
            if not self._lost_frames:
                return None
            return {"frames": self._lost_frames, "bytes": self._lost_bytes, "error": self._error, "path": self.path}

    def close(self) -> None:
        with self._lock:
            if not self._f.closed:
                self._f.close()


def _is_vehicle_heartbeat(msg) -> bool:
    return (
        msg.type
        not in (
            mavlink2.MAV_TYPE_GCS,
            mavlink2.MAV_TYPE_GIMBAL,
            mavlink2.MAV_TYPE_ADSB,
            mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
        )
        and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID
    )


#: COMMAND_LONG that advances a lockstep simulator's clock by param1 seconds (MAV_CMD_USER_1; vehicle_sim's
#: ``--lockstep``), acknowledged once that time has run
LOCKSTEP_COMMAND = 31010


class Lockstep:
    """The vehicle's clock in lockstep: it runs only while we wait for the vehicle, one step at a time.

    A simulator served with ``vehicle-sim --lockstep`` holds its time until a ground station sends
    COMMAND_LONG :data:`LOCKSTEP_COMMAND` with param1 = seconds; it answers the messages it gets at the
    held time and acknowledges the command once those seconds have run. Every wait of the link's users
    for a message goes through :meth:`Subscription.get <passt_mav.mavlink.routing.Subscription.get>`,
    which asks the vehicle first for a step of 0 s (its answers to what we sent, no time passing) and
    then for steps of ``step_s`` until the message comes; waits on the vehicle's state call
    :meth:`Link.idle`. The acknowledgement comes on the same link after everything the vehicle sent
    during the step, and the reader thread routes messages in order, so when :meth:`step` returns the
    waiter has seen all of it: what the vehicle does, and what we see of it, depends on the sequence of
    our messages and steps alone, not on the machine's load or the time our own computing takes (the
    vehicle's clock stands still meanwhile). The wall clock (the link's :attr:`Link.clock`) only paces the
    steps (``pace`` vehicle seconds per wall second at most, for whoever watches) and bounds the wait for
    one acknowledgement (:attr:`ACK_WALL_S`): the backstop of a vehicle whose clock has stopped.
    """

    #: wall seconds to wait for the acknowledgement of one step before the link counts as closed
    ACK_WALL_S = 30.0

    def __init__(self, link: Link, step_s: float, pace: float):
        self.link, self.step_s, self.pace = link, float(step_s), float(pace)
        #: vehicle seconds stepped so far
        self.t = 0.0
        self._lock = threading.Lock()
        self._ref: tuple[float, float] | None = None  # (wall, self.t) the pace counts from

    def budget(self, timeout: float | None) -> StepBudget:
        """What a wait of ``timeout`` wall seconds may step: ``timeout x pace`` vehicle seconds (None: no bound)."""
        return StepBudget(timeout, self.pace)

    def step(self, seconds: float | None = None) -> bool:
        """Run the vehicle's clock ``seconds`` (default ``step_s``; 0: only its answers to what we sent) and
        wait until it says it has; False when the link is closed or the vehicle does not answer."""
        h = self.step_s if seconds is None else max(float(seconds), 0.0)
        link = self.link
        with self._lock:
            if link.closed_reason is not None or link.conn is None:
                return False
            if h > 0:
                self._pace(h)
            sub = link._router.subscribe("COMMAND_ACK", raw=True)
            try:
                msg = mavlink2.MAVLink_command_long_message(
                    link.target_system or 0, 0, LOCKSTEP_COMMAND, 0, h, 0, 0, 0, 0, 0, 0
                )
                try:
                    link.send(msg)
                except MavlinkError:
                    return False
                ack = Timeout(link.clock, self.ACK_WALL_S)
                while True:
                    m = sub.get(ack.left())
                    if m is None:
                        if link.closed_reason is None:
                            link.closed_reason = f"no answer to a lockstep step within {self.ACK_WALL_S:g} s"
                            link._router.wake_subscribers()
                        return False
                    if m.command == LOCKSTEP_COMMAND:
                        self.t += h
                        return True
            finally:
                sub.close()

    def _pace(self, h: float) -> None:
        """Sleep so that the steps run at most :attr:`pace` x wall time; a pace fallen behind (our own
        computing held the clock, or a busy machine) starts again from now instead of catching up in a burst."""
        clock = self.link.clock
        now = clock.now()
        if self._ref is None:
            self._ref = (now, self.t)
        due = self._ref[0] + (self.t + h - self._ref[1]) / self.pace
        if due > now:
            clock.sleep(due - now)
        elif now - due > 0.25:
            self._ref = (now, self.t)


class Link:
    """A MAVLink 2 link to one vehicle (see the module docstring).

    Args:
        config: :class:`LinkConfig`.
        connection_factory: ``() -> mavutil.mavfile`` to use instead of opening
            ``config.connect`` (tests: an in-process simulator endpoint). Called again
            by :meth:`reconnect`.
        clock: the :class:`~passt_mav.mavlink.clock.Clock` every wait on this link asks (default the machine's).
    """

    def __init__(
        self,
        config: LinkConfig | None = None,
        *,
        connection_factory: Callable[[], Any] | None = None,
        clock: Clock | None = None,
    ):
        self.config = config or LinkConfig()
        #: the wall clock of every wait, timeout and backstop on this link and of its users
        self.clock: Clock = SYSTEM_CLOCK if clock is None else clock
        self._factory = connection_factory or self.config.open
        self.conn: Any = None  # the pymavlink connection (pymavlink has no type hints); None while closed
        self.target_system: int | None = self.config.target_system
        self.target_component: int = 1
        self.vehicle_type: int | None = None
        self.autopilot: int | None = None
        self._acct = LinkAccounting(self.clock)
        self._router = MessageRouter()
        #: the vehicle's clock when it runs in lockstep (``config.lockstep_s``), else None
        self.lockstep: Lockstep | None = (
            Lockstep(self, self.config.lockstep_s, self.config.lockstep_pace) if self.config.lockstep_s > 0 else None
        )
        self._router.stepper = self.lockstep
        self._send_lock = threading.Lock()
        #: held by the reader while it logs and routes one message: a caller holding it knows no message is
        #: half-handled (logged to the tlog but not yet seen by the listeners) and none starts meanwhile
        self.dispatch_lock = threading.RLock()
        self._last_hb: float | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._tlog = _Tlog(self.config.tlog, self.clock) if self.config.tlog else None
        self.texts: collections.deque[tuple[float, int, str]] = collections.deque(maxlen=200)
        self.error: BaseException | None = None
        #: why the transport is dead (EOF, reset, read error), None while it is open and alive
        self.closed_reason: str | None = None
        #: streams asked for besides ``config.stream_rates_hz`` (:meth:`keep_stream`): name -> Hz
        self._kept_streams: dict[str, float] = {}

    # -- lifecycle -------------------------------------------------------------------
    def connect(
        self, timeout: float | None = None, *, wait_s: float = 0.0, say: Callable[[str], None] | None = None
    ) -> Link:
        """Open the connection, find the vehicle by its HEARTBEAT, start the threads,
        request the telemetry streams and measure the round trip. Returns self.

        ``timeout``: wall seconds one attempt waits for a vehicle heartbeat (default
        ``config.connect_timeout_s``). ``wait_s``: keep trying for this many wall seconds while the
        transport does not open (refused, unreachable, no such device) or no vehicle heartbeat comes:
        attempts ``config.reconnect_backoff_s`` apart (doubling), one line per failed attempt naming
        the address through ``say`` (default: a log warning). 0 = one attempt.

        Raises :class:`LinkUnavailable` (a :class:`LinkTimeout`) naming the address and the last cause.
        """
        say = say or log.warning
        t0 = self.clock.now()
        deadline = t0 + max(float(wait_s), 0.0)
        per_try = self.config.connect_timeout_s if timeout is None else timeout
        delay, max_delay = self.config.reconnect_backoff_s
        attempt = 0
        while True:
            attempt += 1
            self._acct.new_stats()  # what this attempt received (_what_arrived)
            try:
                self._open()
                left = deadline - self.clock.now()
                # retrying: at least two heartbeat waits fit in the time left (a line each), none past it
                self._find_vehicle(per_try if wait_s <= 0 else max(min(per_try, max(1.0, left / 2), left), 0.5))
                break
            except LinkTimeout as exc:
                self._shutdown()
                left = deadline - self.clock.now()
                if left <= 0:
                    tries = f" after {attempt} attempts over {self.clock.now() - t0:.0f} s" if attempt > 1 else ""
                    raise LinkUnavailable(
                        f"no vehicle at {self.config.connect}{tries}: {_strip_address(exc, self.config.connect)}"
                    ) from None
                pause = min(delay, left)
                say(
                    f"{self.config.connect}: {_strip_address(exc, self.config.connect)}; retrying in {pause:.1f} s "
                    f"(attempt {attempt}, giving up in {left:.0f} s)"
                )
                self.clock.sleep(pause)
                delay = min(delay * 2.0, max_delay)
            except BaseException:
                self._shutdown()
                raise
        try:
            self.measure_rtt()
            self.request_streams()
        except BaseException:
            self._shutdown()
            raise
        return self

    def _open(self) -> None:
        try:
            conn = self._factory()
        except OSError as exc:  # a connection_factory of our own raises LinkUnavailable itself
            raise LinkUnavailable(f"{self.config.connect}: {_why_not_open(exc)}") from exc
        _speak_as_configured(conn, self.config)
        if self._tlog is not None:
            conn.mav.set_send_callback(lambda m: self._tlog.write(m.get_msgbuf()))
        _hook_transport_end(conn)
        self.conn = conn
        self.closed_reason = None
        self._acct.restart_sequences()
        self._stop.clear()
        self._last_hb = None
        self._threads = [
            threading.Thread(target=self._reader, name="mavlink-reader", daemon=True),
            threading.Thread(target=self._heartbeat_loop, name="mavlink-heartbeat", daemon=True),
        ]
        for th in self._threads:
            th.start()

    def _find_vehicle(self, timeout: float) -> None:
        with self.subscribe("HEARTBEAT") as sub:
            left = Timeout(self.clock, timeout).left
            while True:
                m = sub.get(left())
                if m is None:
                    raise LinkTimeout(
                        f"no vehicle heartbeat on {self.config.connect} within {timeout:.1f} s"
                        + self._what_arrived()
                        + self._why(lost=False)
                    )
                if not _is_vehicle_heartbeat(m):
                    continue  # another GCS
                if self.target_system is not None and m.get_srcSystem() != self.target_system:
                    continue
                break
        self.target_system, self.target_component = m.get_srcSystem(), m.get_srcComponent()
        self.vehicle_type, self.autopilot = m.type, m.autopilot
        me = (self.config.source_system, self.config.source_component)
        if me == (self.target_system, self.target_component):
            raise UserError(
                f"our MAVLink identity {me[0]}/{me[1]} is the vehicle's own autopilot's: choose another "
                f"component (default {DEFAULT_SOURCE_COMPONENT}) or system (default {DEFAULT_SOURCE_SYSTEM})"
            )
        if me == GCS_IDENTITY:
            log.warning(
                "speaking as %d/%d, QGroundControl's and Mission Planner's identity: a ground station on the "
                "same link takes our replies and we take its; the vehicle's GCS failsafe counts our heartbeats",
                *me,
            )
        self._last_hb = self.clock.now()
        if m.type != mavlink2.MAV_TYPE_SURFACE_BOAT or m.autopilot != mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA:
            warnings.warn(
                f"vehicle {self.target_system} is {result_name('MAV_TYPE', m.type)} on "
                f"{result_name('MAV_AUTOPILOT', m.autopilot)}, not a boat on ArduPilot; continuing",
                RuntimeWarning,
                stacklevel=3,
            )

    def close(self) -> None:
        """Stop the threads and close the connection and the tlog."""
        self._shutdown()
        if self._tlog is not None:
            self._tlog.close()

    def _shutdown(self) -> None:
        self._stop.set()
        for th in self._threads:
            if th is not threading.current_thread():
                th.join(timeout=2.0)
        self._threads = []
        if self.conn is not None:
            try:
                self.conn.close()
            except Exception:  # noqa: BLE001, S110 - closing a dead transport must not raise
                pass
            self.conn = None

    def reconnect(
        self, attempts: int | None = None, *, wait_s: float | None = None, say: Callable[[str], None] | None = None
    ) -> Link:
        """Close and reopen, with doubling back-off between attempts (capped at
        ``config.reconnect_backoff_s[1]``); re-finds the vehicle and re-requests the streams.
        Subscriptions and listeners carry over.

        ``wait_s``: keep trying for this many wall seconds (a link-loss window) instead of
        ``attempts`` times. ``say``: where the one line per failed attempt goes (default: a log warning).
        Raises :class:`LinkTimeout` when every attempt failed.
        """
        say = say or log.warning
        attempts = self.config.reconnect_attempts if attempts is None else max(int(attempts), 1)
        end = None if wait_s is None else self.clock.now() + max(float(wait_s), 0.0)
        t0 = self.clock.now()
        delay, max_delay = self.config.reconnect_backoff_s
        last: BaseException | None = None
        i = 0
        while True:
            i += 1
            self._shutdown()
            try:
                self._open()
                self._find_vehicle(max(self.config.link_lost_s, self.reply_timeout))
                self.request_streams()
                self.error = None
                if i > 1:
                    log.warning("reconnected to %s at attempt %d", self.config.connect, i)
                return self
            except (OSError, MavlinkError) as exc:
                last = exc
                left = (attempts - i) if end is None else end - self.clock.now()
                more = left > 0
                # one line per attempt (never per frame): the console stays readable during an outage
                of = f"{i}/{attempts}" if end is None else f"{i}"
                nxt = ""
                if more:
                    pause = delay if end is None else min(delay, left)
                    nxt = f"; next in {pause:.2g} s" + ("" if end is None else f", giving up in {left:.0f} s")
                say(
                    f"reconnect attempt {of} to {self.config.connect} failed: {_strip_address(exc, self.config.connect)}{nxt}"
                )
                if not more:
                    break
                self.clock.sleep(pause)
                delay = min(delay * 2.0, max_delay)
        self._shutdown()
        span = f"{i} attempts" if end is None else f"{i} attempts over {self.clock.now() - t0:.0f} s"
        raise LinkTimeout(f"could not reconnect to {self.config.connect} after {span}: {last}")

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- threads -----------------------------------------------------------------------
    def _reader(self) -> None:
        conn = self.conn
        while not self._stop.is_set():
            try:
                msg = conn.recv_msg()
            except (OSError, ValueError) as exc:
                # the transport is dead (EOF, reset, unplugged serial): say so once and stop reading. Reading on
                # would spin (a socket at EOF is always readable) and pymavlink would print on every pass;
                # the link is lost at once and reconnect() opens a new transport.
                self.error = exc
                self.closed_reason = str(exc) or type(exc).__name__
                log.warning("link to %s closed: %s", self.config.connect, self.closed_reason)
                self._router.wake_subscribers()
                return
            except Exception as exc:  # noqa: BLE001 - pymavlink may raise on garbage; keep reading
                self.stats.bad += 1
                log.debug("parse error: %s", exc)
                continue
            if msg is None:
                conn.select(0.01)
                continue
            self._dispatch(msg)

    def _dispatch(self, msg) -> None:
        with self.dispatch_lock:
            self._dispatch_one(msg)

    def _dispatch_one(self, msg) -> None:
        typ = msg.get_type()
        if typ == "BAD_DATA":
            self.stats.bad += 1
            return
        now = self.clock.now()
        if self._tlog is not None:
            self._tlog.write(msg.get_msgbuf())
        from_vehicle = self._acct.count(msg, typ, self.target_system)
        if typ == "HEARTBEAT" and from_vehicle and _is_vehicle_heartbeat(msg):
            self._last_hb = now
        elif typ == "TIMESYNC" and msg.tc1 != 0:
            self._acct.timesync_answered(int(msg.ts1), now)
        elif typ == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("ascii", "replace")
            self.texts.append((now, int(msg.severity), text.rstrip("\x00")))
        self._router.route(msg, typ, keep=from_vehicle or self.target_system is None)

    def _heartbeat_loop(self) -> None:
        period = self.config.timesync_period_s
        next_sync = self.clock.now() + period
        while not self._stop.is_set():
            if self.closed_reason is not None:
                return  # nothing to send on: reconnect() starts a new loop
            try:
                self.send(
                    mavlink2.MAVLink_heartbeat_message(
                        mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, mavlink2.MAV_STATE_ACTIVE, 3
                    )
                )
                if period > 0 and self.clock.now() >= next_sync and self.target_system is not None:
                    # TIMESYNC is not a stream on ArduPilot: keep the RTT current with requests (tc1 = 0)
                    next_sync = self.clock.now() + period
                    self._send_timesync()
            except (OSError, MavlinkError) as exc:
                log.debug("heartbeat send failed: %s", exc)
            self._stop.wait(self.config.heartbeat_period_s)

    def _send_timesync(self) -> int:
        """Send one TIMESYNC request; the reader turns its answer into an RTT sample. Returns its ts1."""
        ts1 = self._acct.timesync_request()
        self.send(mavlink2.MAVLink_timesync_message(0, ts1))
        return ts1

    # -- subscribers -----------------------------------------------------------------------
    def subscribe(self, types: str | Iterable[str] | None = None) -> Subscription:
        """A queue of every message of ``types`` (None = all) received from now on."""
        return self._router.subscribe(types)

    def add_listener(self, callback: Callable[[Message], None], types: str | Iterable[str] | None = None) -> None:
        """Call ``callback(msg)`` from the reader thread for each message of ``types`` (keep it quick)."""
        self._router.add_listener(callback, types)

    def remove_listener(self, callback: Callable[[Message], None]) -> None:
        self._router.remove_listener(callback)

    def latest(self, typ: str):
        """The last message of type ``typ`` from the vehicle, or None."""
        return self._router.latest(typ)

    def forget(self, *types: str) -> None:
        """Drop the last message of each of ``types`` (e.g. after a reboot made them stale)."""
        self._router.forget(*types)

    # -- state -------------------------------------------------------------------------------
    @property
    def seconds_since_heartbeat(self) -> float:
        return float("inf") if self._last_hb is None else self.clock.now() - self._last_hb

    @property
    def lost(self) -> bool:
        """No vehicle heartbeat for ``config.link_lost_s``, or the transport closed (EOF/reset: at once). In
        lockstep only the latter (and a step the vehicle never answers): its heartbeats stop whenever we hold
        its clock."""
        if self.lockstep is not None:
            return self.closed_reason is not None
        return self.closed_reason is not None or self.seconds_since_heartbeat > self.config.link_lost_s

    def _what_arrived(self) -> str:
        """Why no vehicle was found, from what did arrive: nothing, garbage, or MAVLink without a vehicle."""
        st = self.stats
        if st.received == 0 and st.bad == 0:
            return " (nothing arrived: wrong port or address? SITL instance N listens on 5760 + 10*N)"
        if st.received == 0:
            return " (bytes arrive but no MAVLink frame: wrong port, or the serial baud rate differs)"
        return " (MAVLink arrives, but no autopilot heartbeat: only ground stations or other components there?)"

    def _why(self, lost: bool = True) -> str:
        """What to add to a timeout message: a lost link, and signing as the likely cause when it fits."""
        parts = []
        if self.closed_reason is not None:
            parts.append(f"link closed: {self.closed_reason}")
        elif lost and self.lost:
            parts.append("link lost")
        mav = getattr(self.conn, "mav", None)
        signing = _signing_problem(getattr(mav, "signing", None))
        if signing is not None:
            parts.append(signing)
        return f" ({'; '.join(parts)})" if parts else ""

    @property
    def tlog_lost(self) -> dict | None:
        """Messages the telemetry log could not write (a full disk: the link goes on without them), as
        ``{"frames", "bytes", "error", "path"}``; None when none was lost or no log is written."""
        return None if self._tlog is None else self._tlog.lost()

    def signing_hint(self) -> str:
        """``_why()`` for callers outside the link (empty when nothing points at signing or link loss)."""
        return self._why()

    @property
    def stats(self) -> LinkStats:
        """Counters since the last connect attempt."""
        return self._acct.stats

    @property
    def rtt(self) -> float | None:
        """Median measured round-trip time, seconds (None before any sample)."""
        return self._acct.rtt

    @property
    def reply_timeout(self) -> float:
        """How long to wait for one reply: ``max(config.timeout_s, 4 x RTT + 0.1 s)``."""
        rtt = self.rtt
        return self.config.timeout_s if rtt is None else max(self.config.timeout_s, 4.0 * rtt + 0.1)

    def vehicle_uptime_s(self) -> float | None:
        """Vehicle time since boot, seconds: the largest ``time_boot_ms`` among the last second of messages.

        Only recent messages count: after a reboot a stream that stopped (e.g. ATTITUDE switched off)
        would otherwise keep the old boot's larger time.
        """
        msgs = [
            m
            for typ in ("SYSTEM_TIME", "GLOBAL_POSITION_INT", "ATTITUDE", "NAMED_VALUE_FLOAT")
            if (m := self._router.latest(typ)) is not None
        ]
        if not msgs:
            return None
        newest = max((getattr(m, "_timestamp", None) or 0.0) for m in msgs)
        recent = [m for m in msgs if (getattr(m, "_timestamp", None) or 0.0) >= newest - 1.0]
        return max(m.time_boot_ms for m in recent) / 1000.0

    # -- sending -------------------------------------------------------------------------------
    def send(self, msg) -> None:
        """Send one pymavlink message object (thread-safe)."""
        conn = self.conn
        if conn is None:
            raise MavlinkError("link is not open")
        if self.closed_reason is not None:
            raise LinkTimeout(f"link to {self.config.connect} is closed ({self.closed_reason}); reconnect first")
        try:
            with self._send_lock:
                conn.mav.send(msg)
                self.stats.sent += 1
        except OSError as exc:
            self.error = exc
            self.closed_reason = str(exc) or type(exc).__name__
            raise LinkTimeout(f"link to {self.config.connect} closed while sending: {self.closed_reason}") from exc

    def statustext(self, text: str, severity: int = mavlink2.MAV_SEVERITY_INFO) -> None:
        """Send a STATUSTEXT (a note for the telemetry log and the vehicle's DataFlash log; at most 50 chars)."""
        self.send(mavlink2.MAVLink_statustext_message(int(severity), text.encode()))

    def idle(self, wall_s: float) -> None:
        """Wait for news from the vehicle: in lockstep let one step of its clock pass (:class:`Lockstep`;
        nothing changes on a vehicle whose clock stands still), else sleep ``wall_s`` wall seconds."""
        if self.lockstep is not None:
            self.lockstep.step()
        else:
            self.clock.sleep(wall_s)

    def clear_error(self) -> None:
        """Forget the reader's or sender's last error (:attr:`error`) before a reconnect."""
        self.error = None

    def wait(
        self,
        types: str | Iterable[str],
        condition: Callable[[Message], bool] | None = None,
        timeout: float | None = None,
    ):
        """Next message of ``types`` satisfying ``condition`` within ``timeout`` s; raises LinkTimeout."""
        timeout = self.reply_timeout if timeout is None else timeout
        with self.subscribe(types) as sub:
            left = Timeout(self.clock, timeout).left
            while True:
                m = sub.get(left())
                if m is None:
                    raise LinkTimeout(f"no {types} within {timeout:.2f} s" + self._why())
                if condition is None or condition(m):
                    return m

    def for_us(self, msg) -> bool:
        """Whether ``msg`` is addressed to this ground station (or broadcast; a message without a target is)."""
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.config.source_system) and tc in (0, self.config.source_component)

    def command_long(
        self,
        command: int,
        *params: float,
        timeout: float | None = None,
        retries: int | None = None,
        target_component: int | None = None,
        accept: Iterable[int] = (0,),
    ):
        """Send COMMAND_LONG and wait for its COMMAND_ACK.

        Resends (``confirmation`` + 1) when no ACK arrives within the reply timeout,
        ``retries`` times, then raises :class:`LinkTimeout`. A result outside
        ``accept`` raises :class:`CommandRejected` carrying the STATUSTEXT(s) the
        vehicle sent with the refusal. Returns the ACK.
        """
        if self.target_system is None:
            raise MavlinkError("no vehicle: call connect() first")
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        retries = self.config.retries if retries is None else retries
        tc = self.target_component if target_component is None else target_component
        with self.subscribe(("COMMAND_ACK", "STATUSTEXT")) as sub:
            for attempt in range(retries + 1):
                timeout_ = self.reply_timeout if timeout is None else timeout
                texts: list[tuple[int, str]] = []
                t_sent = self.clock.now()
                self.send(
                    mavlink2.MAVLink_command_long_message(self.target_system, tc, int(command), attempt % 256, *p)
                )
                end = t_sent + timeout_
                while True:
                    m = sub.get(end - self.clock.now())
                    if m is None:
                        break
                    if m.get_type() == "STATUSTEXT":
                        texts.append((int(m.severity), _text(m)))
                        continue
                    if m.command != int(command) or not self.for_us(m):
                        continue
                    if m.result == mavlink2.MAV_RESULT_IN_PROGRESS:
                        end = self.clock.now() + timeout_
                        continue
                    self._acct.add_rtt(self.clock.now() - t_sent)
                    if m.result in tuple(accept):
                        return m
                    # the STATUSTEXT explaining a refusal may follow the ACK by a moment
                    grace_end = self.clock.now() + min(0.3, 2 * (self.rtt or 0.05) + 0.05)
                    while True:
                        t = sub.get(grace_end - self.clock.now())
                        if t is None:
                            break
                        if t.get_type() == "STATUSTEXT":
                            texts.append((int(t.severity), _text(t)))
                    important = [s for sev, s in texts if sev <= mavlink2.MAV_SEVERITY_WARNING] or [s for _, s in texts]
                    raise CommandRejected(
                        result_name("MAV_CMD", command).removeprefix("MAV_CMD_"), m.result, "; ".join(important)
                    )
        raise LinkTimeout(
            f"no COMMAND_ACK for {result_name('MAV_CMD', command)} after {retries + 1} tries" + self._why()
        )

    # -- streams and round trip ------------------------------------------------------------------
    def request_streams(self, rates: Iterable[tuple[str, float]] | None = None) -> dict[str, bool]:
        """SET_MESSAGE_INTERVAL for each ``(MESSAGE_NAME, hz)`` (default ``config.stream_rates_hz``); returns
        name -> accepted. See :func:`passt_mav.mavlink.streams.request_streams` (with ``quiet_other_streams``
        every data stream is stopped first; a refused message is requested by its stream group)."""
        if rates is None:  # (the streams kept by keep_stream too: a reboot or a reconnect forgot them)
            rates = list({**dict(self.config.stream_rates_hz), **self._kept_streams}.items())
        return request_streams(self, rates, quiet_others=self.config.quiet_other_streams)

    def keep_stream(self, name: str, hz: float) -> bool:
        """SET_MESSAGE_INTERVAL for ``name`` at ``hz`` (Hz of the vehicle's time) now, the other streams left as they
        are, and again with the others whenever :meth:`request_streams` asks for them (a reconnect; the controller
        after an autopilot reboot, which forgets the rates set). Returns whether the vehicle accepted it now."""
        self._kept_streams[name] = float(hz)
        return request_streams(self, [(name, hz)], quiet_others=False).get(name, False)

    def measure_rtt(self, samples: int = 3) -> float | None:
        """Round trip by TIMESYNC (``tc1 = 0`` request, the vehicle echoes ``ts1``); falls back to
        a COMMAND_LONG round trip (REQUEST_MESSAGE HEARTBEAT). Returns the median in seconds."""
        for _ in range(samples):
            with self.subscribe("TIMESYNC") as sub:
                ts1 = self._send_timesync()
                left = Timeout(self.clock, self.config.timeout_s).left
                while (m := sub.get(left())) is not None:
                    if m.tc1 != 0 and m.ts1 == ts1:
                        break
            self._acct.timesync_abandoned(ts1)
        if self._acct.rtt is None:
            try:
                self.command_long(mavlink2.MAV_CMD_REQUEST_MESSAGE, mavlink2.MAVLINK_MSG_ID_HEARTBEAT, retries=1)
            except (CommandRejected, LinkTimeout) as exc:
                log.warning("round trip not measured: %s", exc)
        return self.rtt


def _strip_address(exc: BaseException, address: str) -> str:
    """The message of ``exc`` without a leading ``ADDRESS: `` (the caller names the address once)."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[len(address) + 2 :] if text.startswith(address + ": ") else text


def _signing_problem(sg) -> str | None:
    """What pymavlink's signing state ``sg`` (``conn.mav.signing``, or None) says is wrong between us and the
    vehicle: it signs and we do not, our keys differ, or we sign and it does not. None when nothing points
    at signing."""
    if sg is None:
        return None
    if sg.secret_key is None and sg.sig_count > 0:
        # the vehicle signs what it sends and ignores our unsigned commands
        return f"it sends signed frames: {_SIGNING_HINT}"
    if sg.secret_key is not None and sg.badsig_count > 0 and sg.goodsig_count == 0:
        return "its frames fail our signature check: the signing key differs from the vehicle's"
    if sg.secret_key is not None and sg.goodsig_count == 0 and sg.reject_count > 0:
        return (
            "it sends unsigned frames, which a signing link drops: the vehicle has no signing key "
            "set; connect without one, or set it on the vehicle"
        )
    return None


def _speak_as_configured(conn, config: LinkConfig) -> None:
    """Make a freshly opened pymavlink connection speak MAVLink 2 as ``config`` says: our source system and
    component, and signing when ``config.signing_key`` is set (unsigned frames accepted only for
    :data:`_UNSIGNED_OK`)."""
    if getattr(conn, "WIRE_PROTOCOL_VERSION", "2.0") != "2.0":
        # pymavlink was imported elsewhere before MAVLINK20 was set: force MAVLink 2 on this connection
        conn.mav = mavlink2.MAVLink(
            conn, srcSystem=config.source_system, srcComponent=config.source_component, use_native=False
        )
        conn.mav.robust_parsing = True
        conn.WIRE_PROTOCOL_VERSION = "2.0"
        conn.first_byte = False
    conn.mav.srcSystem, conn.mav.srcComponent = config.source_system, config.source_component
    if config.signing_key is not None:
        conn.setup_signing(
            secret_from_key(config.signing_key),
            sign_outgoing=True,
            allow_unsigned_callback=lambda _mav, msgid: msgid in _UNSIGNED_OK,
        )


def _hook_transport_end(conn) -> None:
    """Make pymavlink's TCP/UDS EOF and reset hooks raise :class:`_TransportClosed` on this connection.

    pymavlink's ``mavtcp.recv`` calls ``handle_eof`` (print "EOF on TCP socket", then a reconnect
    that does nothing without autoreconnect) and returns ``b""``; a reader polling it spins, printing
    on every pass (181,004 lines in ~2 s were seen against SITL). Raising ends the read at once.
    """
    if not hasattr(conn, "handle_eof"):
        return
    name = type(conn).__name__.removeprefix("mav").upper()

    def eof():
        raise _TransportClosed(f"EOF on {name} socket: the vehicle closed the connection")

    def reset():
        raise _TransportClosed(f"connection reset on {name} socket")

    conn.handle_eof = eof
    conn.handle_disconnect = reset


def _text(m) -> str:
    t = m.text
    if isinstance(t, (bytes, bytearray)):
        t = bytes(t).decode("ascii", "replace")
    return t.rstrip("\x00")
