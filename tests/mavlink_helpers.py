"""Test helpers for passt_mav.mavlink: a simulator served at high speed-up and a Link on it.

The simulator runs in its own thread at ``speedup`` x wall time (sim time is what the
vehicle's timers use); the Link talks to it through an in-process endpoint (a
``mavutil.mavfile``), exactly as it would through a socket. Wall-clock timeouts of
the controller are set small (``timeout_s``) to match the speed-up.

Or in the controller-driven lockstep (:func:`open_in_lockstep`, or a Link with ``lockstep_s``): the
simulator's clock runs only while the controller waits for the vehicle, so simulated time follows the
controller, whatever the machine's load. :class:`Router` shares one vehicle link between several clients
(as MAVProxy or mavlink-router do), :class:`Wire` records the identities the controller sends with.
"""

from __future__ import annotations

import contextlib
import threading

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from passt_mav.mavlink import Link, LinkConfig, MissionClient, Vehicle
from passt_mav.mission.items import MissionItem
from vehicle_sim import LinkConfig as SimLinkConfig
from vehicle_sim import SimConfig, Simulator

HOME = (40.0, -63.0)
SPEEDUP = 50.0


def link_config(**kw) -> LinkConfig:
    base = dict(
        connect="tcp:127.0.0.1:5760",
        timeout_s=0.25,
        link_lost_s=0.5,
        connect_timeout_s=5.0,
        heartbeat_period_s=0.05,
        reconnect_backoff_s=(0.05, 0.2),
    )
    base.update(kw)
    return LinkConfig(**base)


def inprocess_factory(sim: Simulator, sim_link: SimLinkConfig | None = None):
    return lambda: sim.connect_inprocess(sim_link).mavlink_connection()


@contextlib.contextmanager
def served(
    config: SimConfig | None = None,
    *,
    field=None,
    speedup: float = SPEEDUP,
    sim_link: SimLinkConfig | None = None,
    link_kw: dict | None = None,
    connect: bool = True,
    **sim_kw,
):
    """(sim, link) with the sim served in a thread and the link connected (closed on exit)."""
    sim = Simulator(field, home=HOME, config=config or SimConfig.fast(), **sim_kw)
    link = Link(link_config(**(link_kw or {})), connection_factory=inprocess_factory(sim, sim_link))
    sim.serve([], speedup=speedup)
    try:
        if connect:
            link.connect()
        yield sim, link
    finally:
        link.close()
        sim.stop()


def vehicle(link: Link, **kw) -> Vehicle:
    mc = MissionClient(link, no_space_delay_s=0.05, **kw)
    return Vehicle(link, mc, retry_delay_s=0.05)


def waypoints(offsets_deg, mission_type: int = 0) -> list[MissionItem]:
    """NAV_WAYPOINTs at HOME + (dlat, dlon) offsets (seq set later by with_home)."""
    return [
        MissionItem(0, lat=HOME[0] + a, lon=HOME[1] + b, param2=2.0, mission_type=mission_type) for a, b in offsets_deg
    ]


def open_in_lockstep(monkeypatch, sim: Simulator, wrap=None) -> None:
    """Serve ``sim`` in the controller-driven lockstep (its clock runs only for the COMMAND_LONG 31010 steps a
    ground station sends) and make ``LinkConfig.open`` open an in-process connection to it (``wrap(endpoint)``
    first, e.g. :meth:`Wire.wrap`): ``passt-mav run ... --lockstep STEP_S`` then steps its clock while the
    controller waits for the vehicle. The caller stops ``sim``."""
    from passt_mav.mavlink import link as link_mod
    from vehicle_sim.inprocess import InProcessMavfile

    sim.serve([], lockstep=True)
    monkeypatch.setattr(
        link_mod.LinkConfig,
        "open",
        lambda self: InProcessMavfile(sim.connect_inprocess() if wrap is None else wrap(sim.connect_inprocess())),
    )


class Router:
    """An in-process MAVLink router on one simulator link, as MAVProxy ``--out`` or mavlink-router serve
    a ground station and the controller: every frame of the vehicle goes to every port (replies
    addressed to one client reach all), every port's frames go to the vehicle."""

    def __init__(self, sim):
        self.sim = sim
        self.ep = sim.connect_inprocess()
        self._lock = threading.Lock()
        self.ports: list[_RouterPort] = []

    def port(self) -> _RouterPort:
        p = _RouterPort(self)
        with self._lock:
            self.ports.append(p)
        return p

    def _pump(self) -> None:
        data = self.ep.read()
        if data:
            for p in self.ports:
                p.buf += data


class _RouterPort:
    """One client's side of a :class:`Router` (the endpoint interface: ``write``, ``read``, ``sim``)."""

    def __init__(self, router: Router):
        self.router, self.sim, self.buf = router, router.sim, bytearray()

    def write(self, buf) -> int:
        return self.router.ep.write(bytes(buf))

    def read(self, n=None) -> bytes:
        with self.router._lock:
            self.router._pump()
            k = len(self.buf) if n is None else min(n, len(self.buf))
            out = bytes(self.buf[:k])
            del self.buf[:k]
            return out

    def wait_readable(self, timeout: float) -> bool:
        """Wait at most ``timeout`` s for bytes for this port (the router's link, or what another port pumped)."""
        return bool(self.buf) or self.router.ep.wait_readable(timeout) or bool(self.buf)

    def close(self) -> None:
        with self.router._lock:
            if self in self.router.ports:
                self.router.ports.remove(self)


class Wire:
    """Identity of every frame the controller writes to the vehicle (parsed independently of passt_mav)."""

    def __init__(self):
        self.mav = mavlink2.MAVLink(None, use_native=False)
        self.mav.robust_parsing = True
        self.ids: set[tuple[int, int]] = set()

    def wrap(self, ep):
        orig = ep.write

        def write(buf):
            for m in self.mav.parse_buffer(bytes(buf)) or []:
                if m.get_type() != "BAD_DATA":
                    self.ids.add((m.get_srcSystem(), m.get_srcComponent()))
            return orig(buf)

        ep.write = write
        return ep
