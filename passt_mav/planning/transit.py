"""Legs timed in the current: ground speed, duration and arrival time of each move of a grid path.

A boat that holds its track in a current crabs: it points its water velocity ``w`` (``|w| = V``,
the speed through the water) so that ``w + c`` lies along the track. With the current split into
its along-track part ``c_par`` and its cross-track part ``c_perp`` (both m/s), the water velocity
cancels ``c_perp`` and the rest of it drives the boat along the track::

    g = sqrt(V**2 - c_perp**2) + c_par          (ground speed along the track, m/s)

That is ``hold="water"``: a boat at a fixed speed through the water. An autopilot may hold its
speed over ground instead: ArduPilot Rover's speed controller holds the ground velocity projected
on the bow at the commanded speed ``V`` (``AR_AttitudeControl::get_forward_speed``; SITL in a
0.5 m/s current flew 5.0 m/s over ground with and against it, vehicle_sim does the same), asking
the hull for whatever water speed that takes, up to its top speed ``V_max`` (``max_water_speed``,
default ``V``). With ``hold="ground"`` the ground speed along the track is the ``g`` whose
projection on the crabbed bow is ``V`` (``g * cos(crab) = V``, a little above ``V`` in a cross
current), or, where the hull cannot give the water speed that takes, full throttle, the crab
formula above with ``V_max``: ``g = min(g_hold, sqrt(V_max**2 - c_perp**2) + c_par)``. With
``V_max = V`` a leg against the current is timed as with ``hold="water"`` and a leg with it at
about ``V``.

A move is *feasible* when ``|c_perp| < V_max`` (``V`` for ``hold="water"``) and
``g >= margin * V`` (:data:`FEASIBLE_MARGIN`): below that the boat barely makes way (against a
Gulf-Stream-like jet of 1.67 m/s a 2 m/s boat makes 0.33 m/s) and the leg's timing is at the
mercy of the forecast's error.

Frames and units (DESIGN.md): a current array is the field's layout, ``(2, rows, cols)`` or
``(time, 2, rows, cols)`` float, channel 0 ``u`` along +col (east on an unrotated grid),
channel 1 ``v`` along +row (north), row 0 the southern edge, in m/s (a caller multiplies the
field's units by ``field.velocity_scale``; a rotated grid's u/v are already in the grid's frame,
as the moves are). Cell sizes are the grid's ``cell_size_m`` ``(dy, dx)``: metres between row
centres and between column centres. A move ``(drow, dcol)`` is the displacement
``(dcol * dx, drow * dy)`` metres (x along +col, y along +row). Times are seconds from the leg's
start. A move is timed in :data:`SUBSTEPS` equal sub-steps: each takes the current bilinear in space
at its midpoint (the corners that are NaN left out, their weight shared by the rest) and linear in
time at the moment the boat begins it, and the move's duration is the sum of the sub-steps' length
over ground speed. Because ``1 / g`` is convex and steep where ``g`` is small, one mean current for
the whole move (its two cells' average) times a move through a varying current short; the
sub-steps also make a move feasible only where every one of them is. A move with no finite current
is infeasible. Pure numpy; no I/O.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from passt_mav.planning.grid import MOVES8

__all__ = [
    "FEASIBLE_MARGIN",
    "SUBSTEPS",
    "HOLDS",
    "ground_speed",
    "segment_timing",
    "move_feasibility",
    "feasible_moves",
    "leg_timing",
    "LegTiming",
    "corners_to_path",
]

#: a move is offered only when its ground speed is at least this fraction of the speed through the
#: water (and the cross-track current is weaker than the boat): 0.25 x 2 m/s = 0.5 m/s
FEASIBLE_MARGIN = 0.25

#: equal sub-steps a move is timed and checked in (module docstring; 1 is one current per move, at
#: its midpoint)
SUBSTEPS = 4

#: what the commanded speed is: the speed through the water, or over ground (ArduPilot Rover)
HOLDS = ("water", "ground")


def _crab(cpar, cperp, vw: float) -> np.ndarray:
    """Ground speed along the track at water speed ``vw``, crab held (NaN where ``|c_perp| >= vw``)."""
    with np.errstate(invalid="ignore"):
        under = vw * vw - cperp * cperp
        return np.where(under > 0, np.sqrt(np.where(under > 0, under, 0.0)) + cpar, np.nan)


def _held(cpar, cperp, V: float) -> np.ndarray:
    """Ground speed ``g`` along the track whose projection on the crabbed bow is ``V``: with ``a = g - c_par``
    the water speed along the track, ``(a + c_par) * a / hypot(a, c_perp) = V``, increasing in ``a >= 0``
    (solved by bisection; a current along the track faster than ``V`` carries the boat at its own speed)."""
    cpar, cperp = np.broadcast_arrays(np.asarray(cpar, np.float64), np.asarray(cperp, np.float64))
    lo = np.maximum(0.0, -cpar)
    hi = V + np.abs(cpar) + np.abs(cperp) + 1e-9  # f(hi) >= 0 (module docstring's bound)

    def f(a):
        return (a + cpar) * a / np.maximum(np.hypot(a, cperp), 1e-12) - V

    with np.errstate(invalid="ignore"):
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            up = f(mid) < 0
            lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
    return 0.5 * (lo + hi) + cpar


def ground_speed(
    c_par,
    c_perp,
    speed: float,
    margin: float = FEASIBLE_MARGIN,
    *,
    hold: str = "water",
    max_water_speed: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(g, feasible)``: ground speed along the track (m/s, NaN where the cross-track current beats the
    hull or the current is NaN) and whether it is at least ``margin * speed`` (module docstring), for any
    broadcastable shapes.

    c_par, c_perp: current along / across the track (m/s); speed: the commanded speed ``V`` (m/s, > 0),
    through the water (``hold="water"``) or over ground along the bow (``"ground"``, up to the hull's
    ``max_water_speed``, default ``speed``).
    """
    V = float(speed)
    if not V > 0:
        raise ValueError(f"speed must be positive, got {speed!r}")
    if hold not in HOLDS:
        raise ValueError(f"unknown speed hold {hold!r}; choose one of {', '.join(HOLDS)}")
    cpar = np.asarray(c_par, np.float64)
    cperp = np.asarray(c_perp, np.float64)
    if hold == "water":
        g = _crab(cpar, cperp, V)
    else:
        vmax = V if max_water_speed is None else float(max_water_speed)
        if not vmax >= V:
            raise ValueError(f"the hull's top speed {max_water_speed!r} must be at least the commanded {V:g} m/s")
        g = np.fmin(_held(cpar, cperp, V), _crab(cpar, cperp, vmax))
        g = np.where(np.isfinite(_crab(cpar, cperp, vmax)), g, np.nan)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(g) & (g >= float(margin) * V)
    return g, ok


def _components(d, c) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(length m, c_par, c_perp) of displacements ``d`` (..., 2) x/y metres in currents ``c`` (..., 2)."""
    d = np.asarray(d, np.float64)
    n = np.hypot(d[..., 0], d[..., 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        ex, ey = d[..., 0] / n, d[..., 1] / n
    c = np.asarray(c, np.float64)
    cpar = c[..., 0] * ex + c[..., 1] * ey
    cperp = -c[..., 0] * ey + c[..., 1] * ex  # left of the track positive
    return n, cpar, cperp


def segment_timing(displacement, current, speed: float, margin: float = FEASIBLE_MARGIN, **hold):
    """``(duration s, ground speed m/s, feasible)`` of straight segments.

    displacement: (..., 2) x/y metres; current: (..., 2) u/v m/s (broadcast); ``hold``: ``hold`` /
    ``max_water_speed`` of :func:`ground_speed`. A zero-length segment takes 0 s and is feasible; an
    infeasible one's duration is its length over its ground speed when that is positive, else inf.
    """
    n, cpar, cperp = _components(displacement, current)
    g, ok = ground_speed(cpar, cperp, speed, margin, **hold)
    zero = n <= 0
    with np.errstate(invalid="ignore", divide="ignore"):
        dur = np.where(zero, 0.0, np.where(g > 0, n / np.where(g > 0, g, 1.0), np.inf))
    return dur, g, ok | zero


def _bilinear(cur, fr, fc) -> np.ndarray:
    """(T, ..., 2) current of ``cur`` (T, 2, R, C) at fractional cells ``fr``, ``fc`` (broadcastable, clipped to
    the grid): bilinear, the NaN corners left out and their weight shared by the finite ones; NaN where
    no corner with weight is finite."""
    T, _, R, C = cur.shape
    fr, fc = np.broadcast_arrays(
        np.clip(np.asarray(fr, np.float64), 0, R - 1), np.clip(np.asarray(fc, np.float64), 0, C - 1)
    )
    r0 = np.minimum(np.floor(fr).astype(np.int64), max(R - 2, 0))
    c0 = np.minimum(np.floor(fc).astype(np.int64), max(C - 2, 0))
    wr, wc = fr - r0, fc - c0
    acc = np.zeros((T, *fr.shape, 2))
    wsum = np.zeros((T, *fr.shape, 2))
    for dr, w_r in ((0, 1.0 - wr), (1, wr)):
        for dc, w_c in ((0, 1.0 - wc), (1, wc)):
            v = np.moveaxis(cur[:, :, np.minimum(r0 + dr, R - 1), np.minimum(c0 + dc, C - 1)], 1, -1)
            w = (w_r * w_c)[None, ..., None]
            f = np.isfinite(v) & (w > 0)
            acc += np.where(f, v * w, 0.0)
            wsum += np.where(f, w, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(wsum > 1e-12, acc / np.where(wsum > 0, wsum, 1.0), np.nan)


def _substep_points(substeps: int) -> np.ndarray:
    """Midpoints (K,) of ``substeps`` equal sub-steps of a move, as fractions of it."""
    k = int(substeps)
    if k < 1:
        raise ValueError(f"substeps must be at least 1, got {substeps!r}")
    return (np.arange(k) + 0.5) / k


def _as_sequence(currents) -> np.ndarray:
    c = np.asarray(currents)  # (no copy: a field's snapshots are read where they lie)
    if c.ndim == 3:
        c = c[None]
    if c.ndim != 4 or c.shape[1] != 2:
        raise ValueError(f"currents must be (2, R, C) or (T, 2, R, C), got shape {c.shape}")
    return c


def move_feasibility(
    currents, cell_size_m, speed: float, margin: float = FEASIBLE_MARGIN, *, substeps: int = SUBSTEPS, **hold
):
    """``(feasible (R, C, 8) bool, ground speed (T, R, C, 8) m/s)`` of every :data:`MOVES8` move from
    every cell, in each snapshot of ``currents`` ((2, R, C) or (T, 2, R, C), m/s).

    A move is feasible when each of its ``substeps`` is, in every snapshot (the leg may make it at any
    of them: the conservative rule); a move off the grid is not. Its ground speed in a snapshot is
    that of its slowest sub-step. ``cell_size_m``: ``(dy, dx)`` metres; ``hold``: ``hold`` /
    ``max_water_speed`` of :func:`ground_speed`.
    """
    cur = _as_sequence(currents)
    R, C = cur.shape[2:]
    dy, dx = (float(x) for x in cell_size_m)
    s = _substep_points(substeps)
    rr, cc = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
    tr = rr[..., None] + MOVES8[:, 0]
    tc = cc[..., None] + MOVES8[:, 1]
    inside = (tr >= 0) & (tr < R) & (tc >= 0) & (tc < C)
    fr = rr[..., None, None] + MOVES8[:, 0, None] * s  # (R, C, 8, K)
    fc = cc[..., None, None] + MOVES8[:, 1, None] * s
    c = _bilinear(cur, fr, fc)  # (T, R, C, 8, K, 2)
    d = np.stack([MOVES8[:, 1] * dx, MOVES8[:, 0] * dy], axis=-1).astype(np.float64)[:, None, :]  # (8, 1, 2)
    _, cpar, cperp = _components(d, c)
    g, ok = ground_speed(cpar, cperp, speed, margin, **hold)
    g = np.where(np.isfinite(g).all(axis=-1), g.min(axis=-1), np.nan)
    return inside & ok.all(axis=(0, -1)), np.where(inside, g, np.nan)


def feasible_moves(
    currents, cell_size_m, speed: float, traversable=None, margin: float = FEASIBLE_MARGIN, **hold
) -> np.ndarray:
    """The planners' move mask: (R, C, 8) bool, move ``MOVES8[k]`` from ``(r, c)`` allowed.

    A move must stay in the grid, start and end on ``traversable`` cells ((R, C) bool; default all)
    and be feasible in the current (:func:`move_feasibility`). Where the current leaves a
    traversable cell no feasible move, its fastest traversable move (largest worst-case ground
    speed over the snapshots) stays allowed: the boat is swept there and must still go on (a
    planner with no move to offer would have to stop the mission).
    """
    ok, g = move_feasibility(currents, cell_size_m, speed, margin, **hold)
    R, C = ok.shape[:2]
    trav = np.ones((R, C), bool) if traversable is None else np.asarray(traversable, bool)
    tr = np.arange(R)[:, None, None] + MOVES8[:, 0]
    tc = np.arange(C)[None, :, None] + MOVES8[:, 1]
    inside = (tr >= 0) & (tr < R) & (tc >= 0) & (tc < C)
    geo_ok = inside & trav[..., None] & trav[np.clip(tr, 0, R - 1), np.clip(tc, 0, C - 1)]
    allowed = geo_ok & ok
    stuck = geo_ok.any(axis=2) & ~allowed.any(axis=2)
    if stuck.any():
        worst = np.where(geo_ok, np.min(np.where(np.isfinite(g), g, -np.inf), axis=0), -np.inf)
        best = worst == worst.max(axis=2, keepdims=True)
        allowed = np.where(stuck[..., None], geo_ok & best, allowed)
    return allowed


@dataclass
class LegTiming:
    """A path's timing in the current (:func:`leg_timing`); arrays per move (L,) or per cell (L+1,).

    ground_speed: m/s along each move (NaN when the cross-track current is too strong);
    duration: s per move (inf when the boat cannot make way); arrival: s from the leg's start at
    each cell (``arrival[0]`` = the start offset); feasible: per move (:data:`FEASIBLE_MARGIN`).
    """

    ground_speed: np.ndarray
    duration: np.ndarray
    arrival: np.ndarray
    feasible: np.ndarray

    @property
    def total_s(self) -> float:
        """Seconds from the leg's start to its last cell."""
        return float(self.arrival[-1])

    @property
    def all_feasible(self) -> bool:
        return bool(np.all(self.feasible))


def leg_timing(
    path,
    currents,
    cell_size_m,
    speed: float,
    *,
    snapshot_s: float | None = None,
    start_s: float = 0.0,
    margin: float = FEASIBLE_MARGIN,
    substeps: int = SUBSTEPS,
    **hold,
) -> LegTiming:
    """Each move's ground speed and duration, and each cell's arrival time, of a grid ``path``.

    path: (L+1, 2) int (row, col), 8-neighbour moves; currents: (2, R, C) (one snapshot, held over
    the whole leg) or (T, 2, R, C) snapshots ``snapshot_s`` seconds apart, snapshot 0 at the
    leg's start (m/s, module docstring). Each move is timed in ``substeps`` sub-steps, each with the
    current at its midpoint when the boat begins it (linear between snapshots, held after the last);
    a move's ground speed is its length over its duration, and it is feasible when every sub-step
    is. ``start_s``: seconds already spent before the first move (e.g. reaching the start cell's
    centre). ``cell_size_m``: ``(dy, dx)``; ``hold``: ``hold`` / ``max_water_speed`` of
    :func:`ground_speed`.
    """
    p = np.asarray(path, np.int64)
    cur = _as_sequence(currents)
    T = cur.shape[0]
    dy, dx = (float(x) for x in cell_size_m)
    L = max(len(p) - 1, 0)
    s = _substep_points(substeps)
    K = len(s)
    d = np.diff(p, axis=0).astype(np.float64)
    disp = np.stack([d[:, 1] * dx, d[:, 0] * dy], axis=-1)  # (L, 2) x/y metres
    c = _bilinear(cur, p[:-1, 0, None] + d[:, 0, None] * s, p[:-1, 1, None] + d[:, 1, None] * s)  # (T, L, K, 2)
    arrival = np.empty(L + 1)
    arrival[0] = float(start_s)
    if T == 1 or L == 0:
        dur, _, ok = segment_timing(disp[:, None, :] / K, c[0], speed, margin, **hold)
        arrival[1:] = arrival[0] + np.cumsum(dur.sum(axis=1))
        return _timing(disp, arrival, ok.all(axis=1))
    if not (snapshot_s and snapshot_s > 0):
        raise ValueError("several current snapshots need their spacing snapshot_s > 0")
    # one pass along the path: a sub-step's current depends on when the boat makes it (the midpoint
    # in time too: timed first with the current as it begins, then again with the current half that
    # time later; second order in the sub-step's duration, like the midpoint in space)
    ok = np.ones(L, bool)
    t = arrival[0]
    for i in range(L):
        for j in range(K):
            dur_ij = 0.0
            for _ in range(2):
                ci = _at_time(c[:, i, j], (t + 0.5 * dur_ij) / snapshot_s)
                dur_ij, _, ok_ij = segment_timing(disp[i] / K, ci, speed, margin, **hold)
                dur_ij = float(dur_ij)
                if not np.isfinite(dur_ij):
                    break
            ok[i] &= bool(ok_ij)
            t += dur_ij
        arrival[i + 1] = t
    return _timing(disp, arrival, ok)


def _at_time(c, x: float) -> np.ndarray:
    """(2,) current of ``c`` (T, 2) snapshots at fractional snapshot ``x``: linear between, held outside."""
    T = c.shape[0]
    x = min(max(x, 0.0), T - 1.0)
    k = min(int(np.floor(x)), T - 2)
    w = x - k
    return (1 - w) * c[k] + w * c[k + 1]


def _timing(disp, arrival, ok) -> LegTiming:
    """:class:`LegTiming` of moves ``disp`` (L, 2) m arriving at ``arrival`` (L+1,) s."""
    with np.errstate(invalid="ignore"):  # (after a move the boat cannot make, every arrival is inf)
        dur = np.diff(arrival)
    n = np.hypot(disp[:, 0], disp[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.where(np.isfinite(dur) & (dur > 0), n / np.where(dur > 0, dur, 1.0), np.where(n > 0, np.nan, 0.0))
    return LegTiming(g, dur, arrival, np.asarray(ok, bool))


def corners_to_path(cells) -> np.ndarray:
    """The grid path (L+1, 2) int of the straight 8-neighbour runs between consecutive corner cells
    ``cells`` (n, 2) (a mission's waypoint cells: :func:`geo.waypoint_cells` keeps one per run).
    Raises ``ValueError`` when two corners are not on one row, column or diagonal."""
    c = np.asarray(cells, np.int64).reshape(-1, 2)
    out = [c[:1]]
    for a, b in itertools.pairwise(c):
        d = b - a
        n = int(np.abs(d).max())
        if n == 0:
            continue
        if not (d[0] == 0 or d[1] == 0 or abs(d[0]) == abs(d[1])):
            raise ValueError(f"cells {tuple(a)} and {tuple(b)} are not joined by one straight run of moves")
        out.append(a + np.sign(d) * np.arange(1, n + 1)[:, None])
    return np.concatenate(out, axis=0)
