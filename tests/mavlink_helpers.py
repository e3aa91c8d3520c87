"""Test helpers for passt_mav.mavlink: a simulator served at high speed-up and a Link on it.

The simulator runs in its own thread at ``speedup`` x wall time (sim time is what the
vehicle's timers use); the Link talks to it through an in-process endpoint (a
``mavutil.mavfile``), exactly as it would through a socket. Wall-clock timeouts of
the controller are set small (``timeout_s``) to match the speed-up.
"""

from __future__ import annotations

import contextlib

from passt_mav.mavlink import Link, LinkConfig, MissionClient, Vehicle
from passt_mav.mission.items import MissionItem
from vehicle_sim import LinkConfig as SimLinkConfig
from vehicle_sim import SimConfig, Simulator

HOME = (40.0, -63.0)
SPEEDUP = 50.0


def link_config(**kw) -> LinkConfig:
    base = dict(connect="tcp:127.0.0.1:5760", timeout_s=0.25, link_lost_s=0.5, connect_timeout_s=5.0,
                heartbeat_period_s=0.05, reconnect_backoff_s=(0.05, 0.2))
    base.update(kw)
    return LinkConfig(**base)


def inprocess_factory(sim: Simulator, sim_link: SimLinkConfig | None = None):
    return lambda: sim.connect_inprocess(sim_link).mavlink_connection()


@contextlib.contextmanager
def served(config: SimConfig | None = None, *, field=None, speedup: float = SPEEDUP, sim_link: SimLinkConfig | None = None,
           link_kw: dict | None = None, connect: bool = True, **sim_kw):
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
    return [MissionItem(0, lat=HOME[0] + a, lon=HOME[1] + b, param2=2.0, mission_type=mission_type)
            for a, b in offsets_deg]
