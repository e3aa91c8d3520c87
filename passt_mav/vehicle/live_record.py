"""What the controller tells the live view: a boat's status and the run's metadata, read off a controller.

Kept out of :mod:`passt_mav.vehicle.controller` so that the controller only calls its
:class:`~passt_mav.runs.live.RecordWriter` (the files and their layout are described there).
These functions run in the writer's status thread: they only read what the link's reader
thread keeps (latest messages, counters) and never send anything to the vehicle.
"""

from __future__ import annotations

import numpy as np

__all__ = ["live_status", "live_meta", "field_time_now"]


def field_time_now(ctl) -> float | None:
    """The field time the vehicle's clock says now (None before its first time stamp)."""
    return ctl.run_clock.field_time_now()


def live_status(ctl) -> dict:
    """One boat's status (``live/boat_K.json``): position, heading, mode, link, leg progress."""
    link, v = ctl.link, ctl.vehicle
    g = link.latest("GLOBAL_POSITION_INT")
    pos = v.position()
    hdg = None if g is None or int(g.hdg) == 65535 else round(int(g.hdg) / 100.0, 1)
    st = link.stats
    leg, end_up = ctl.live_leg
    flying = ctl.collector is not None and ctl.collector.leg is not None
    up = link.vehicle_uptime_s()
    left = None if not flying or end_up is None or up is None else max(0.0, end_up - up)
    k = ctl.share.leg_k(leg, flying)
    rtt = link.rtt
    return {
        "sysid": int(link.target_system or 0),
        "lat": None if pos is None else pos[0],
        "lon": None if pos is None else pos[1],
        "heading_deg": hdg,
        "mode": v.mode_name,
        "armed": bool(v.armed),
        "link_lost": bool(link.lost),
        "rtt_ms": None if rtt is None else round(rtt * 1000.0, 1),
        "loss_pct": round(100.0 * st.loss, 2),
        "leg": leg,
        "leg_k": k,
        "legs_n": ctl.n_legs,
        "flying": flying,
        "samples_leg": ctl.collector.leg_counts(leg)["emitted"] if flying else 0,
        "leg_end_s": None if left is None else round(left, 1),
        "leg_end_wall_s": None if left is None else round(left / ctl.speedup, 1),
        "status": ctl.status,
        "field_time": field_time_now(ctl),
    }


def live_meta(ctl, n_boats: int = 1) -> dict:
    """The run's metadata for the view (``live/meta.json``): grid, land, geofence margin, boats, legs, skill."""
    from passt_mav.models.evaluate import skill_warning

    cfg = ctl.config
    try:
        skill = skill_warning(getattr(ctl.predictor, "metadata_", None) or {})
    except (KeyError, TypeError):  # a checkpoint's skill report of another form: no warning
        skill = None
    return {
        "mission": cfg.name,
        "grid": ctl.grid.describe(),
        "land": np.asarray(ctl.land, bool).astype(int).tolist(),
        "geofence_margin_m": float(cfg.geofence_margin_m),
        "boats": int(n_boats),
        "legs_per_boat": ctl.n_legs,
        "model": ctl.predictor_info.get("used"),
        "planner": cfg.planner.name,
        "reward": cfg.planner.reward,
        "truth_known": bool(ctl.truth_known),
        "skill_warning": skill,
        "speedup": ctl.speedup,
        "field_time_origin": ctl.field.time_origin,
        "velocity_scale": float(cfg.field.velocity_scale),
    }
