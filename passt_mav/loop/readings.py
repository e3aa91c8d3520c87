"""The readings a boat takes along a planned leg on a known field, without a vehicle.

For offline studies of the live loop (:class:`passt_mav.loop.legstep.LegStep`): a boat follows the
planned cells' centres in straight lines at a constant speed from the leg's start time and reads
the field (bilinear in space and time) plus Gaussian sensor noise at a fixed interval of vehicle
time, as ``vehicle_sim``'s current sensor does in flight (without its turns, waypoint radius or
drift). The records have the sample store's columns, so :meth:`LegStep.absorb` takes them as it
takes a live leg's.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fly_legs", "track_readings"]


def track_readings(
    field,
    path,
    t_start: float,
    *,
    speed_mps: float,
    every_s: float,
    noise_std: float,
    rng,
    t_boot0: float,
    time_scale: float = 1.0,
    velocity_scale: float = 1.0,
) -> list[dict]:
    """Readings along ``path`` ((L+1, 2) cells, row north, col east) from field time ``t_start``.

    ``speed_mps``: boat speed over ground (m/s); ``every_s``: vehicle seconds between readings;
    ``noise_std``: sensor noise (m/s, each of u, v); ``rng``: a numpy Generator; ``t_boot0``: the
    field time of the vehicle's boot (``time_boot_ms`` counts from it); ``time_scale``: vehicle
    seconds per field time unit; ``velocity_scale``: m/s per field velocity unit. Returns records
    ``{time_boot_ms, boot, lat, lon, u, v}`` (deg, m/s east/north), none where the field has no data.
    """
    grid = field.grid
    cells = np.asarray(path, float)
    lat, lon = grid.fcell_to_latlon(cells[:, 0], cells[:, 1])
    x, y = grid.latlon_to_xy(np.asarray(lat, float), np.asarray(lon, float))
    xy = np.column_stack([np.asarray(x, float).reshape(-1), np.asarray(y, float).reshape(-1)])
    s_at = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    n = max(2, int(s_at[-1] / speed_mps / every_s) + 1)
    s = np.linspace(0.0, s_at[-1], n)
    plat, plon = grid.xy_to_latlon(np.interp(s, s_at, xy[:, 0]), np.interp(s, s_at, xy[:, 1]))
    plat, plon = np.asarray(plat, float).reshape(-1), np.asarray(plon, float).reshape(-1)
    t = float(t_start) + s / speed_mps / float(time_scale)  # field time of each reading
    r, c = grid.latlon_to_fcell(plat, plon)
    uv = field.interp(np.minimum(t, field.times[-1]), np.asarray(r, float), np.asarray(c, float))
    uv = uv * float(velocity_scale) + rng.normal(0.0, noise_std, uv.shape)
    tb = np.round((t - float(t_boot0)) * float(time_scale) * 1000.0).astype(np.int64)
    ok = np.isfinite(uv).all(axis=1)
    return [
        {"time_boot_ms": int(a), "boot": 0, "lat": float(b), "lon": float(d), "u": float(e), "v": float(f)}
        for a, b, d, e, f in zip(tb[ok], plat[ok], plon[ok], uv[ok, 0], uv[ok, 1])
    ]


def fly_legs(step, start, legs: int, *, every_s: float, noise_std: float, rng, strict: bool = True):
    """Fly ``legs`` legs of ``step`` (a :class:`~passt_mav.loop.legstep.LegStep`) offline, from the mission's
    initial state and cell ``start`` (row, col): each leg planned at once (no snapshots waited), its
    readings taken along the planned track by :func:`track_readings` at the mission's speed
    (``vehicle.speed_mps``) and time scale, every ``every_s`` vehicle seconds with ``noise_std`` (m/s) noise
    from ``rng``, and absorbed as ``passt-mav run`` absorbs a live leg (``strict``: see
    :meth:`LegStep.absorb`). Yields ``(planned, absorbed)`` per leg; the next leg starts where the path
    ended, from the absorbed state (a caller may stop early)."""
    from passt_mav.loop.legstep import FieldClock

    field, cfg = step.field, step.config
    state, t_state = step.initial_state()
    clock = FieldClock(t_boot0=float(field.times[0]), time_scale=float(cfg.field.time_scale))
    start = tuple(int(x) for x in start)
    for i in range(int(legs)):
        planned = step.plan(i, state, t_state, start, k=0)
        step.forecast_leg(planned)
        recs = track_readings(
            field,
            planned.plan.path,
            planned.t_start,
            speed_mps=float(cfg.vehicle.speed_mps),
            every_s=every_s,
            noise_std=noise_std,
            rng=rng,
            t_boot0=clock.t_boot0,
            time_scale=float(cfg.field.time_scale),
            velocity_scale=float(cfg.field.velocity_scale),
        )
        ab = step.absorb(planned, recs, clock, strict=strict)
        yield planned, ab
        state, t_state, start = ab.state, ab.t_state, tuple(int(x) for x in planned.plan.path[-1])
