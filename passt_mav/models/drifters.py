"""Virtual drifters: the separation skill of an estimated current against the true one.

Ocean-current forecasts are scored by where a drifter would go: drifters seeded on a regular subset of
the wet cells are advected through the estimated field and through the true field over the same
horizon, and the mean distance between each pair at the end (km, and km per day of horizon) is the
skill (lower is better; persistence, the first true snapshot held fixed, is the usual reference).

Frames and units: fields ``(time, 2, rows, cols)`` float, u east and v north in m/s, row 0 the southern
edge; positions in fractional (row, col) cells internally, distances in metres and km. Advection is
midpoint (RK2) with bilinear interpolation in space and linear interpolation in time between snapshots,
in sub-steps of at most half a cell. A drifter that leaves the grid (half a cell beyond the edge
centres) stops where it left; next to land (NaN) the velocity is interpolated from the wet corners only,
and a drifter with no wet corner stops. Pure (no I/O).
"""

from __future__ import annotations

import numpy as np

__all__ = ["advect", "drifter_separation", "seed_cells"]

#: drifters seeded by default (about; on every ``stride``-th wet cell in both directions)
N_DRIFTERS = 100
#: a sub-step moves a drifter at most this many cells
MAX_CELLS_PER_SUBSTEP = 0.5
#: and a snapshot interval is cut into at most this many sub-steps
MAX_SUBSTEPS = 200


def _velocity(frame, pos, cell_m) -> np.ndarray:
    """Bilinear (u, v) of ``frame`` (2, R, C) m/s at ``pos`` (n, 2) fractional (row, col), as cells per second
    (n, 2) in (row, col) order; positions clamped to the edge centres; corners that are NaN left out
    (weights renormalised), no wet corner: 0."""
    R, C = frame.shape[1:]
    r = np.clip(pos[:, 0], 0.0, R - 1.0)
    c = np.clip(pos[:, 1], 0.0, C - 1.0)
    r0 = np.minimum(np.floor(r).astype(int), max(R - 2, 0))
    c0 = np.minimum(np.floor(c).astype(int), max(C - 2, 0))
    fr, fc = r - r0, c - c0
    r1, c1 = np.minimum(r0 + 1, R - 1), np.minimum(c0 + 1, C - 1)
    acc, wsum = np.zeros((len(pos), 2)), np.zeros(len(pos))
    for rr, cc, w in (
        (r0, c0, (1 - fr) * (1 - fc)),
        (r0, c1, (1 - fr) * fc),
        (r1, c0, fr * (1 - fc)),
        (r1, c1, fr * fc),
    ):
        val = frame[:, rr, cc].T  # (n, 2): u, v
        ok = np.isfinite(val).all(axis=1)
        acc[ok] += w[ok, None] * val[ok]
        wsum[ok] += w[ok]
    vel = np.where(wsum[:, None] > 0, acc / np.maximum(wsum, 1e-300)[:, None], 0.0)
    dy, dx = cell_m
    return np.column_stack([vel[:, 1] / dy, vel[:, 0] / dx])  # north -> rows, east -> cols


def _between(f0, f1, a: float, pos, cell_m) -> np.ndarray:
    """:func:`_velocity` (cells per second) at the time ``a`` (0..1) of the way from snapshot ``f0`` to ``f1``."""
    return (1 - a) * _velocity(f0, pos, cell_m) + a * _velocity(f1, pos, cell_m)


def advect(frames, dt_s: float, cell_m, starts) -> np.ndarray:
    """Positions (n, 2) fractional (row, col) of drifters started at ``starts`` (n, 2) (row, col) after the
    whole of ``frames`` (K+1, 2, R, C) m/s, snapshots ``dt_s`` seconds apart, cells ``cell_m`` = (north-south,
    east-west) metres. Midpoint steps, the field linear in time between snapshots."""
    f = np.asarray(frames, np.float64)
    R, C = f.shape[2:]
    pos = np.asarray(starts, np.float64).reshape(-1, 2).copy()
    live = np.ones(len(pos), bool)
    speed = float(np.nanmax(np.hypot(f[:, 0], f[:, 1]), initial=0.0)) if np.isfinite(f).any() else 0.0
    cells_per_interval = speed * float(dt_s) / min(cell_m)
    n_sub = int(np.clip(np.ceil(cells_per_interval / MAX_CELLS_PER_SUBSTEP), 1, MAX_SUBSTEPS))
    h = float(dt_s) / n_sub
    for k in range(f.shape[0] - 1):
        for j in range(n_sub):
            a0, a1 = j / n_sub, (j + 0.5) / n_sub
            p = pos[live]
            mid = p + 0.5 * h * _between(f[k], f[k + 1], a0, p, cell_m)
            pos[live] = p + h * _between(f[k], f[k + 1], a1, mid, cell_m)
            out = (pos[:, 0] < -0.5) | (pos[:, 0] > R - 0.5) | (pos[:, 1] < -0.5) | (pos[:, 1] > C - 0.5)
            pos[out & live] = np.clip(pos[out & live], -0.5, [R - 0.5, C - 0.5])
            live &= ~out
    return pos


def seed_cells(wet, n: int = N_DRIFTERS) -> np.ndarray:
    """(m, 2) integer (row, col) of about ``n`` drifters on a regular subset of the ``wet`` (R, C) cells:
    every ``stride``-th row and column (``stride`` = round(sqrt(wet cells / n)), at least 1), centred."""
    wet = np.asarray(wet, bool)
    stride = max(1, int(round(np.sqrt(wet.sum() / max(n, 1)))))
    rr, cc = np.meshgrid(np.arange(wet.shape[0]), np.arange(wet.shape[1]), indexing="ij")
    pick = wet & (rr % stride == stride // 2) & (cc % stride == stride // 2)
    return np.argwhere(pick)


def drifter_separation(estimate, truth, dt_s: float, cell_m, *, n: int = N_DRIFTERS) -> dict | None:
    """Mean separation of drifters advected through ``estimate`` and through ``truth`` (each (K+1, 2, R, C),
    m/s, snapshots ``dt_s`` seconds apart; ``cell_m`` (north-south, east-west) metres) over the whole
    horizon ``K dt_s``, seeded on about ``n`` wet cells of the first snapshot (:func:`seed_cells`).
    Returns ``{"sep_km": mean separation (km), "km_per_day": sep_km / horizon (km/day), "horizon_h": hours,
    "n": drifters}`` or None (no wet cell, no time step)."""
    est = np.asarray(estimate, np.float64)
    tru = np.asarray(truth, np.float64)
    if est.shape != tru.shape or est.shape[0] < 2 or not float(dt_s) > 0:
        return None
    seeds = seed_cells(np.isfinite(tru[0]).all(0) & np.isfinite(est[0]).all(0), n)
    if len(seeds) == 0:
        return None
    pe, pt = advect(est, dt_s, cell_m, seeds), advect(tru, dt_s, cell_m, seeds)
    dy, dx = cell_m
    sep_km = float(np.mean(np.hypot((pe[:, 0] - pt[:, 0]) * dy, (pe[:, 1] - pt[:, 1]) * dx))) / 1000.0
    horizon_s = (est.shape[0] - 1) * float(dt_s)
    return {
        "sep_km": sep_km,
        "km_per_day": sep_km / (horizon_s / 86400.0),
        "horizon_h": horizon_s / 3600.0,
        "n": int(len(seeds)),
    }
