"""Several simulated boats in one process: one current field, one clock (:class:`Fleet`).

The layout is ArduPilot SITL's for several vehicles: boat ``i`` (0-based, the SITL
instance number ``-I i``) listens on ``tcp:127.0.0.1:5760 + 10*i`` and has system id
``i + 1`` (parameter ``MAV_SYSID``, Rover 4.7's name). Each boat is a whole
:class:`vehicle_sim.Simulator` (autopilot, mission server, modes, arming, links,
sockets, tlog); what they share:

* **the current**: one :class:`~vehicle_sim.boat.CurrentModel` (field, start time,
  scales), so every boat samples the same field at the same field time;
* **the clock**: the fleet advances every boat by the same physics sub-step, one after
  the other, under one lock; a boat's :meth:`Simulator.step` (used by in-process
  clients and the lockstep ``mavfile``) advances the whole fleet. The boats' clocks are
  therefore always equal (a rebooting boat's ``clock`` runs on, like a single boat's);
* **the serving thread** (:meth:`Fleet.serve`): one thread moves every boat's sockets,
  at ``speedup`` x wall time, or in lockstep: COMMAND_LONG 31010 (MAV_CMD_USER_1,
  param1 = seconds) sent to *any* boat advances *all* of them (send it on one link;
  requests on several links add up), acknowledged when done, after every boat's output
  of the step has been sent.

What is per boat: everything a vehicle owns (its sockets, links, autopilot state,
stored mission, parameters, noise generators: sensor and link-loss seeds are
``seed + i``, so boat 0 is the single-boat simulator). A closed, dropped or silent
link of one boat touches no other boat: each boat's links live in its own
:class:`Simulator`. :meth:`Fleet.drop_clients` closes one boat's TCP clients from the
vehicle side (a fault test's "link lost").

Start positions: :func:`spread_starts` spreads boats over a field's region (a
``ceil(sqrt(N))``-column layout of cell centres, moved to the nearest cell with
data), :func:`line_starts` lines them up east of a home without a field.
"""

from __future__ import annotations

import math
import select
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from vehicle_sim.boat import CurrentModel, LocalFrame
from vehicle_sim.config import LinkConfig, SimConfig
from vehicle_sim.link import parse_link_spec
from vehicle_sim.sim import STEP_COMMAND, Clocked, Simulator, serve_paced

__all__ = ["Fleet", "BASE_PORT", "PORT_STRIDE", "boat_config", "boat_listen", "spread_starts", "line_starts"]

#: ArduPilot SITL instance 0's TCP port, and the port step between instances (``-I N``: 5760 + 10 N)
BASE_PORT = 5760
PORT_STRIDE = 10


def boat_listen(listen: Iterable[str], index: int) -> list[str]:
    """Boat ``index``'s listen specs: every port of ``listen`` + 10 * index (port 0 stays 0: OS-chosen)."""
    out = []
    for spec in listen:
        _kind, host, port = parse_link_spec(spec)
        prefix = spec.split(":", 1)[0]
        out.append(f"{prefix}:{host}:{port + PORT_STRIDE * index if port else 0}")
    return out


def boat_config(config: SimConfig, index: int) -> SimConfig:
    """Boat ``index``'s config from the fleet's: system id ``index + 1`` unless its params set
    ``MAV_SYSID`` (as a SITL params file does), seed ``seed + index``, tlog ``NAME-<sysid>.tlog``."""
    params = dict(config.params)
    sysid = int(params.get("MAV_SYSID", index + 1))
    if not 1 <= sysid <= 255:
        raise ValueError(f"boat {index}: MAV_SYSID must be 1..255, got {sysid}")
    tlog = None
    if config.tlog:
        p = Path(config.tlog)
        tlog = str(p.with_name(f"{p.stem}-{sysid}{p.suffix or '.tlog'}"))
    return config.replace(sysid=sysid, seed=config.seed + index, tlog=tlog)


def spread_starts(field, n: int) -> list[tuple[float, float]]:
    """``n`` start positions (lat, lon degrees) spread over ``field``'s region.

    The region is cut into ``rows_n x cols_n`` blocks (``cols_n = ceil(sqrt(n))``,
    ``rows_n = ceil(n / cols_n)``); boat ``i`` starts at the centre of block
    ``(i // cols_n, i % cols_n)``, counted from the south-west corner (one boat: the
    region's centre, the single-boat default). A block centre on land or a missing
    cell moves to the nearest cell with data in the first snapshot.
    """
    import numpy as np

    if n < 1:
        raise ValueError("a fleet needs at least one boat")
    g = field.grid
    R, C = g.shape
    cols_n = math.ceil(math.sqrt(n))
    rows_n = math.ceil(n / cols_n)
    ok = np.isfinite(field.data[0, 0]) & np.isfinite(field.data[0, 1])
    if not ok.any():
        raise ValueError("the field has no cell with data to start a boat in")
    rr, cc = np.nonzero(ok)
    out = []
    for i in range(n):
        # fractional cell index of the block centre (cell centres sit at integer indices)
        r = (i // cols_n + 0.5) / rows_n * R - 0.5
        c = (i % cols_n + 0.5) / cols_n * C - 0.5
        if n == 1:
            r, c = (R - 1) / 2.0, (C - 1) / 2.0
        if not ok[int(round(r)), int(round(c))]:
            k = int(np.argmin((rr - r) ** 2 + (cc - c) ** 2))
            r, c = float(rr[k]), float(cc[k])
        lat, lon = g.fcell_to_latlon(r, c)
        out.append((float(lat), float(lon)))
    return out


def line_starts(home: tuple[float, float], n: int, spacing_m: float = 20.0) -> list[tuple[float, float]]:
    """``n`` start positions (lat, lon degrees): boat ``i`` ``i * spacing_m`` metres east of ``home``."""
    frame = LocalFrame(*home)
    return [frame.to_latlon(i * spacing_m, 0.0) for i in range(n)]


class Fleet(Clocked):
    """N boats on one current field and one clock (see the module docstring).

    Args:
        field: a :class:`passt_mav.fields.FlowField`, or None for still water.
        starts: ``[(lat, lon), ...]`` degrees, one per boat: start position and home.
        config: the boats' common :class:`SimConfig` (each boat gets :func:`boat_config`),
            or ``configs``: one ready config per boat (their ``physics_dt`` must agree).
        velocity_scale, time_scale, start_time, uniform_current: the shared
            :class:`~vehicle_sim.boat.CurrentModel`.
        link_config: default impairment of new links, or ``link_configs`` one per boat.
        epoch0: UTC epoch seconds at boot, the same for every boat (default: now).
    """

    def __init__(
        self,
        field=None,
        *,
        starts: Sequence[tuple[float, float]],
        config: SimConfig | None = None,
        configs: Sequence[SimConfig] | None = None,
        velocity_scale: float = 1.0,
        time_scale: float = 1.0,
        start_time: float | None = None,
        uniform_current: tuple[float, float] = (0.0, 0.0),
        link_config: LinkConfig | None = None,
        link_configs: Sequence[LinkConfig] | None = None,
        epoch0: float | None = None,
    ):
        n = len(starts)
        if n < 1:
            raise ValueError("a fleet needs at least one boat")
        if configs is None:
            base = config or SimConfig()
            configs = [boat_config(base, i) for i in range(n)]
        if len(configs) != n or (link_configs is not None and len(link_configs) != n):
            raise ValueError(f"{n} boats need {n} configs and link configs")
        if len({c.physics_dt for c in configs}) != 1:
            raise ValueError("the boats of a fleet share one clock: their physics_dt must agree")
        sysids = [c.sysid for c in configs]
        if len(set(sysids)) != n:
            raise ValueError(f"two boats share a system id: {sysids}")
        self.field = field
        self.current = CurrentModel(
            field, start_time=start_time, velocity_scale=velocity_scale, time_scale=time_scale, uniform=uniform_current
        )
        self.epoch0 = time.time() if epoch0 is None else float(epoch0)
        self.physics_dt = configs[0].physics_dt
        # one lock for every boat: the serving thread and a client stepping a boat must not interleave
        self._lock = threading.RLock()
        self._wake = threading.Event()  # set by a write to any boat's in-process endpoint
        self.boats: list[Simulator] = []
        for i, (home, cfg) in enumerate(zip(starts, configs)):
            sim = Simulator(
                field,
                home=home,
                config=cfg,
                link_config=(link_configs[i] if link_configs else link_config),
                epoch0=self.epoch0,
                current=self.current,
            )
            sim._lock = self._lock
            sim._fleet = self
            sim._wake = self._wake  # a write to any boat's endpoint wakes the fleet's serving thread
            self.boats.append(sim)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._drop_requests: list[tuple[int, threading.Event]] = []
        self.running = False
        self.error: BaseException | None = None
        self._lockstep = False
        self._budget = 0.0
        self._waiters: list = []

    def __len__(self) -> int:
        return len(self.boats)

    def __getitem__(self, i: int) -> Simulator:
        return self.boats[i]

    # -- clock -------------------------------------------------------------------------
    @property
    def t(self) -> float:
        """Simulated seconds since the fleet started (every boat's ``clock``)."""
        return self.boats[0].autopilot.clock

    def step(self, dt: float | None = None) -> None:
        """Advance every boat by ``dt`` simulated seconds (default one physics step), in physics sub-steps."""
        dt = self.physics_dt if dt is None else float(dt)
        with self._lock:
            remaining = dt
            while remaining > 1e-12:
                h = min(self.physics_dt, remaining)
                for b in self.boats:
                    b._tick(h)
                remaining -= h

    # -- faults ----------------------------------------------------------------------------
    def drop_clients(self, index: int) -> None:
        """Close boat ``index``'s TCP client connections from the vehicle side (its clients see
        EOF); the other boats and this boat's listener are untouched (a client may reconnect)."""
        if not 0 <= index < len(self.boats):
            raise IndexError(f"no boat {index} in a fleet of {len(self.boats)}")
        if self._thread is not None and self._thread.is_alive():
            done = threading.Event()
            with self._lock:
                self._drop_requests.append((index, done))  # done by the serving thread, which owns the sockets
            # returns once closed: a client's next request is already served without that boat's links
            done.wait(timeout=10.0)
        else:
            self._drop_now(index)

    def _drop_now(self, index: int) -> None:
        b = self.boats[index]
        for e in [e for e in b._sockets if e["kind"] == "tcp-client"]:
            b._close_entry(e)

    # -- serving ---------------------------------------------------------------------------
    def serve(
        self,
        listen: Iterable[str] = (f"tcp:127.0.0.1:{BASE_PORT}",),
        speedup: float = 1.0,
        wait_for_client: bool = False,
        poll_s: float = 0.002,
        lockstep: bool = False,
        per_boat: Sequence[Sequence[str]] | None = None,
    ) -> None:
        """Serve every boat from one background thread (see :meth:`Simulator.serve` for the specs).

        ``listen``: the specs of boat 0; boat ``i`` gets each port + 10 * i (:func:`boat_listen`;
        port 0: every boat an OS-chosen port, see :meth:`ports`). ``per_boat``: each boat's own
        specs instead. ``wait_for_client``: hold the clock at 0 until a first TCP client connects
        to any boat (one clock: SITL instances each wait for their own). ``lockstep``: see the
        module docstring. Sockets are opened before this returns (a bind error raises, and
        nothing stays open).
        """
        if self._thread is not None:
            raise RuntimeError("fleet already serving")
        if speedup <= 0:
            raise ValueError("speedup must be positive")
        listen = list(listen)
        specs = (
            [list(s) for s in per_boat]
            if per_boat is not None
            else [boat_listen(listen, i) for i in range(len(self.boats))]
        )
        if len(specs) != len(self.boats):
            raise ValueError(f"per_boat needs {len(self.boats)} lists of specs")
        opened = []
        try:
            for b, s in zip(self.boats, specs):
                b._open_listeners(s, None)
                opened.append(b)
        except BaseException:
            for b in opened:
                for e in b._sockets:
                    e["sock"].close()
                b._sockets = []
            raise
        self._lockstep = bool(lockstep)
        for b in self.boats:
            b._lockstep = self._lockstep  # each boat takes 31010 out of its own input; the fleet adds them up
            b.running = True
        self._stop.clear()
        self.running = True
        self._thread = threading.Thread(
            target=self._serve_loop, args=(speedup, wait_for_client, poll_s), name="vehicle-sim-fleet", daemon=True
        )
        self._thread.start()

    def ports(self) -> list[list[tuple[str, int]]]:
        """Per boat, (spec, bound port) of each listening socket."""
        return [b.ports() for b in self.boats]

    def tcp_ports(self) -> list[int]:
        """Each boat's first TCP listening port."""
        out = []
        for b in self.boats:
            p = [e["sock"].getsockname()[1] for e in b._sockets if e["kind"] == "tcp-listen"]
            out.append(p[0] if p else 0)
        return out

    def _poll(self, timeout: float) -> None:
        socks = [e["sock"] for b in self.boats for e in b._sockets]
        if not socks:
            self._wake.wait(timeout)
            self._wake.clear()  # what was written before this is taken in by the round that follows
            return
        try:
            ready, _, _ = select.select(socks, [], [], timeout)
        except (OSError, ValueError):
            ready = []
        if ready:
            ready = set(ready)
            for b in self.boats:
                b._handle_ready(ready)

    def _flush(self) -> None:
        for b in self.boats:
            b._flush_sockets()

    def _serve_loop(self, speedup: float, wait_for_client: bool, poll_s: float) -> None:
        try:
            serve_paced(self, speedup, wait_for_client, poll_s, self.physics_dt)
        except BaseException as exc:  # noqa: BLE001 - recorded and re-raised by stop()
            self.error = exc
        finally:
            for b in self.boats:
                for e in b._sockets:
                    try:
                        e["sock"].close()
                    except OSError:
                        pass
                b.running = False
            self.running = False

    # what serve_paced asks of the fleet (one clock, every boat's sockets)
    def _serve_sockets(self):
        return [e for b in self.boats for e in b._sockets]

    def _serve_budget(self) -> float:
        return self._budget

    def _serve_tick(self) -> None:
        self._do_drops()

    def _poll_sockets(self, timeout: float) -> None:
        self._poll(timeout)

    def _flush_sockets(self) -> None:
        self._flush()

    def _do_drops(self) -> None:
        if self._drop_requests:
            with self._lock:
                reqs, self._drop_requests = self._drop_requests, []
                for i, done in reqs:
                    self._drop_now(i)
                    done.set()

    def _gather(self) -> None:
        """Move the step requests (31010) each boat took from its input into the fleet's budget."""
        for b in self.boats:
            if b._step_budget or b._step_waiters:
                self._budget += b._step_budget
                b._step_budget = 0.0
                self._waiters.extend((b, link, msg) for link, msg in b._step_waiters)
                b._step_waiters.clear()

    def _lockstep_round(self, max_dt: float) -> None:
        with self._lock:
            for b in self.boats:
                b._process_incoming()
            self._gather()
            steps = 0
            while self._budget > 1e-9 and steps < 200:
                h = min(max_dt, self._budget)
                for b in self.boats:
                    b._tick(h)
                self._budget -= h
                steps += 1
                self._gather()  # a request that arrived during the step adds to the budget
            acks = []
            if self._budget <= 1e-9 and self._waiters:
                self._budget = 0.0
                acks, self._waiters = self._waiters, []
            for b in self.boats:
                b._deliver_inprocess()
        self._flush()
        if acks:
            # acknowledged only after every boat's output of the step has gone out: a client that
            # has the ACK (on one boat's link) has everything the other boats said until now
            with self._lock:
                for b, link, msg in acks:
                    link.send(
                        b.autopilot.MAVLINK.MAVLink_command_ack_message(
                            STEP_COMMAND, 0, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                        ),
                        b.autopilot.clock,
                    )
                for b in self.boats:
                    b._deliver_inprocess()
            self._flush()

    def stop(self) -> None:
        """Stop serving (joins the thread); closes every boat's sockets and tlog."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None
        for b in self.boats:
            if b.tlog is not None:
                b.tlog.close()
        if self.error is not None:
            err, self.error = self.error, None
            raise err

    def close(self) -> None:
        self.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
