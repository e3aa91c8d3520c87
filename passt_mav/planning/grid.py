"""Grid-path helpers shared by every planner: moves, input validation, scoring.

Conventions (DESIGN.md): a reward map is ``(rows, cols)`` float, row 0 = south;
a path is an ``(L+1, 2)`` int array of ``(row, col)`` whose consecutive cells are
8-neighbours. ``traversable`` is an ``(rows, cols)`` bool array, True where the
robot may go (water). A planner's ``mask`` is that array, or an ``(rows, cols, 8)`` bool
array of allowed moves (``mask[r, c, k]``: the move :data:`MOVES8` ``[k]`` from ``(r, c)``
may be taken; e.g. the moves a boat can make in the forecast current,
:func:`passt_mav.planning.transit.feasible_moves`); every planner enumerates its moves
through :func:`allowed_moves`. Pure numpy; no I/O.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import PlannerError

__all__ = [
    "MOVES8",
    "MOVES4",
    "check_inputs",
    "check_many",
    "path_reward",
    "top_l_bound",
    "check_path",
    "allowed_moves",
    "bfs_path",
    "cheapest_path",
    "TIE_RTOL",
    "tie_tolerance",
    "best_with_ties",
    "rank_with_ties",
]

#: The 8 king moves (drow, dcol), counter-clockwise from east. Index = action id.
MOVES8 = np.array([(0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1)], dtype=np.int64)
#: The 4 rook moves (subset of MOVES8).
MOVES4 = MOVES8[::2].copy()
#: MOVES8 as plain-Python (drow, dcol) tuples, for loops over single cells.
MOVES8_TUPLES = tuple((int(a), int(b)) for a, b in MOVES8)


#: relative tolerance under which two planning totals are one tie: float noise (another BLAS thread
#: count, another summation order) moves a total by ~1e-15..1e-12 of its size, far below this, and a
#: planner must not take another path because of it
TIE_RTOL = 1e-9


def tie_tolerance(totals, rtol: float = TIE_RTOL) -> float:
    """Absolute tolerance of a tie among ``totals`` (any shape): ``rtol`` times the largest finite
    magnitude (0 when none is finite; exact ties are then still ties)."""
    a = np.abs(np.asarray(totals, dtype=np.float64))
    return float(rtol) * float(a[np.isfinite(a)].max(initial=0.0))


def best_with_ties(scores, keys=None, rtol: float = TIE_RTOL) -> np.ndarray:
    """Index of the best score along the last axis of ``scores`` (..., n), ties within
    :func:`tie_tolerance` of the row's best broken by the smallest ``keys`` (same shape; default the
    index itself), so float noise cannot pick another entry. Rows with no finite score give 0."""
    s = np.asarray(scores, dtype=np.float64)
    k = np.broadcast_to(np.arange(s.shape[-1]), s.shape) if keys is None else np.asarray(keys)
    fin = np.isfinite(s)
    top = np.where(fin, s, -np.inf).max(axis=-1, keepdims=True)
    tol = float(rtol) * np.where(fin, np.abs(s), 0.0).max(axis=-1, keepdims=True)
    tied = fin & (s >= top - tol)
    big = np.iinfo(np.int64).max
    return np.argmin(np.where(tied, k.astype(np.int64), big), axis=-1)


def rank_with_ties(totals, keys, rtol: float = TIE_RTOL) -> np.ndarray:
    """Flat indices of the finite ``totals`` (any shape), best first, in groups of ties: each group is
    its best remaining total and every total within :func:`tie_tolerance` of it, ordered by ascending
    ``keys`` (a (..., k) int array of sort keys per entry, the first most significant; e.g. the
    cell's flat index, then the beam). Float noise reorders only totals that straddle a group's
    edge, not near-equal ones."""
    t = np.asarray(totals, dtype=np.float64).reshape(-1)
    kk = np.asarray(keys).reshape(t.size, -1)
    tol = tie_tolerance(t, rtol)
    order = [int(i) for i in np.argsort(-t, kind="stable") if np.isfinite(t[i])]
    out: list[int] = []
    j = 0
    while j < len(order):
        lead = t[order[j]]
        g = j
        while g < len(order) and t[order[g]] >= lead - tol:
            g += 1
        group = order[j:g]
        out += sorted(group, key=lambda i: tuple(int(x) for x in kk[i]))
        j = g
    return np.asarray(out, dtype=np.int64)


def check_inputs(reward, start, budget, mask=None) -> tuple[np.ndarray, tuple[int, int], int, np.ndarray]:
    """Validate and normalise a planning request once, at the edge.

    Returns ``(reward float64 (R,C) with blocked cells = 0, start (r, c), budget int,
    traversable bool (R,C))``. Non-finite reward cells are blocked (land), as are
    cells where ``mask`` (traversable, True = water) is False; an (R, C, 8) move ``mask``
    blocks the cells it allows no move from (:func:`allowed_moves` gives the moves).
    Raises :class:`PlannerError` naming the problem.
    """
    q = np.asarray(reward, dtype=np.float64)
    if q.ndim != 2 or min(q.shape) < 2:
        raise PlannerError(f"reward map must be a 2-D (rows, cols) array of at least 2x2, got shape {q.shape}")
    trav = np.isfinite(q)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape == q.shape + (8,):
            m = m.any(axis=2)
        if m.shape != q.shape:
            raise PlannerError(f"traversable mask shape {m.shape} does not match the reward map {q.shape}")
        trav &= m
    q = np.where(trav, q, 0.0)
    if np.any(q < 0):
        raise PlannerError("reward map must be non-negative")
    try:
        r, c = (int(v) for v in np.asarray(start).reshape(-1)[:2])
        if np.asarray(start).size != 2:
            raise ValueError
    except (TypeError, ValueError):
        raise PlannerError(f"start must be a (row, col) cell, got {start!r}") from None
    R, C = q.shape
    if not (0 <= r < R and 0 <= c < C):
        raise PlannerError(f"start cell ({r}, {c}) lies outside the {R}x{C} grid")
    if not trav[r, c]:
        raise PlannerError(f"start cell ({r}, {c}) is land / not traversable")
    if int(budget) != budget or int(budget) < 1:
        raise PlannerError(f"path budget must be a positive integer number of moves, got {budget!r}")
    if not allowed_moves(trav, mask)[r, c].any():
        raise PlannerError(f"start cell ({r}, {c}) has no traversable neighbour it may move to")
    return q, (r, c), int(budget), trav


def allowed_moves(trav: np.ndarray, mask=None) -> np.ndarray:
    """(R, C, 8) bool: the move :data:`MOVES8` ``[k]`` from ``(r, c)`` stays in the grid, starts and
    ends on ``trav`` cells ((R, C) bool, as :func:`check_inputs` gives it) and, when ``mask`` is an
    (R, C, 8) move mask, is allowed by it. A 2-D or absent ``mask`` adds nothing."""
    t = np.asarray(trav, bool)
    R, C = t.shape
    tr = np.arange(R)[:, None, None] + MOVES8[:, 0]
    tc = np.arange(C)[None, :, None] + MOVES8[:, 1]
    inside = (tr >= 0) & (tr < R) & (tc >= 0) & (tc < C)
    ok = inside & t[..., None] & t[np.clip(tr, 0, R - 1), np.clip(tc, 0, C - 1)]
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.ndim == 3:
            ok &= m
    return ok


def check_many(rewards, starts, budget, seeds, masks=None) -> tuple[list, list, int, list]:
    """:func:`check_inputs` for a batch of G planning requests on one grid (``plan_many``).

    Returns ``(rewards, starts, budget, traversables)``: lists of G as check_inputs gives
    them (``budget`` is None for an empty batch). Raises :class:`PlannerError` when the
    lists differ in length or the maps in shape.
    """
    G = len(rewards)
    if not (len(starts) == len(seeds) == G) or (masks is not None and len(masks) != G):
        raise PlannerError("plan_many needs one start, seed (and mask) per reward map")
    qs, st, travs, L = [], [], [], None
    for i in range(G):
        q, s0, L, trav = check_inputs(rewards[i], starts[i], budget, None if masks is None else masks[i])
        if qs and q.shape != qs[0].shape:
            raise PlannerError(
                f"plan_many: reward map {i} has shape {q.shape}, map 0 {qs[0].shape}; one grid per batch"
            )
        qs.append(q)
        st.append(s0)
        travs.append(trav)
    return qs, st, L, travs


def path_reward(reward, path, *, include_start: bool = False) -> float:
    """Reward a path collects: the sum over its DISTINCT cells (a cell pays once).

    The start cell is excluded unless ``include_start`` (the robot is already
    there when the leg is planned). NaN rewards count as 0.
    """
    q = np.nan_to_num(np.asarray(reward, dtype=np.float64), nan=0.0)
    p = np.asarray(path, dtype=np.int64)
    cells = {(int(a), int(b)) for a, b in (p if include_start else p[1:])}
    if not include_start:
        cells.discard((int(p[0, 0]), int(p[0, 1])))
    return float(sum(q[a, b] for a, b in cells))


def top_l_bound(reward, start, budget) -> float:
    """Upper bound on :func:`path_reward`: the sum of the ``budget`` largest rewards
    over all cells except the start (a path of L moves visits at most L new cells)."""
    q = np.nan_to_num(np.asarray(reward, dtype=np.float64), nan=0.0).copy()
    q[int(start[0]), int(start[1])] = -np.inf
    flat = np.sort(q.ravel())[::-1]
    flat = flat[np.isfinite(flat)]
    return float(flat[: int(budget)].sum())


def check_path(path, rows: int, cols: int, *, traversable=None, budget: int | None = None, start=None) -> None:
    """Raise ``PlannerError`` unless ``path`` is a valid grid path.

    Valid: integer ``(L+1, 2)``; every cell inside the grid (and traversable when
    given); consecutive cells are distinct 8-neighbours; ``L == budget`` and
    ``path[0] == start`` when given; a cell is revisited only when every
    traversable neighbour of the previous cell had already been visited. An (R, C, 8) move
    mask as ``traversable`` (module docstring) also requires every move to be allowed, and
    the neighbours of the revisit rule are those the mask allows moving to.
    """
    p = np.asarray(path)
    if p.ndim != 2 or p.shape[1] != 2 or not np.issubdtype(p.dtype, np.integer):
        raise PlannerError(f"path must be an integer (L+1, 2) array, got {p.dtype} {p.shape}")
    if budget is not None and p.shape[0] != budget + 1:
        raise PlannerError(f"path has {p.shape[0] - 1} moves, expected {budget}")
    if start is not None and tuple(p[0]) != tuple(int(s) for s in start):
        raise PlannerError(f"path starts at {tuple(p[0])}, expected {tuple(start)}")
    if np.any(p[:, 0] < 0) or np.any(p[:, 0] >= rows) or np.any(p[:, 1] < 0) or np.any(p[:, 1] >= cols):
        raise PlannerError("path leaves the grid")
    d = np.diff(p, axis=0)
    if np.any(np.abs(d).max(axis=1) != 1):
        raise PlannerError("consecutive path cells must be distinct 8-neighbours")
    trav = None if traversable is None else np.asarray(traversable, bool)
    moves = None
    if trav is not None and trav.ndim == 3:
        moves, trav = trav, trav.any(axis=2)
        k = [MOVES8_TUPLES.index((int(a), int(b))) for a, b in d]
        if len(k) and not np.all(moves[p[:-1, 0], p[:-1, 1], k]):
            raise PlannerError("path takes a move the move mask does not allow")
    if moves is None and trav is not None and not np.all(trav[p[:, 0], p[:, 1]]):
        raise PlannerError("path crosses a non-traversable cell")
    seen = {tuple(p[0])}
    for i in range(1, len(p)):
        cell = tuple(p[i])
        if cell in seen:
            prev = p[i - 1]
            nb = prev + MOVES8
            ok = (nb[:, 0] >= 0) & (nb[:, 0] < rows) & (nb[:, 1] >= 0) & (nb[:, 1] < cols)
            if moves is not None:
                ok &= moves[prev[0], prev[1]]
            nb = nb[ok]
            if trav is not None and moves is None:
                nb = nb[trav[nb[:, 0], nb[:, 1]]]
            if any(tuple(n) not in seen for n in nb):
                raise PlannerError(f"path revisits {cell} at move {i} although an unvisited neighbour existed")
        seen.add(cell)


def neighbours(cell, traversable: np.ndarray) -> np.ndarray:
    """Traversable 8-neighbours of ``cell`` as a (k, 2) int array (MOVES8 order)."""
    R, C = traversable.shape
    nb = np.asarray(cell, dtype=np.int64) + MOVES8
    ok = (nb[:, 0] >= 0) & (nb[:, 0] < R) & (nb[:, 1] >= 0) & (nb[:, 1] < C)
    nb = nb[ok]
    return nb[traversable[nb[:, 0], nb[:, 1]]]


def bfs_path(src, dst, traversable: np.ndarray) -> list[tuple[int, int]] | None:
    """Shortest 8-connected cell sequence from ``src`` to ``dst`` (both included)
    over traversable cells, or None when unreachable. Plain BFS: 30x30 grids are tiny."""
    src, dst = (int(src[0]), int(src[1])), (int(dst[0]), int(dst[1]))
    if src == dst:
        return [src]
    if not traversable[dst]:
        return None
    prev = {src: None}
    frontier = [src]
    while frontier:
        nxt = []
        for cell in frontier:
            for n in neighbours(cell, traversable):
                t = (int(n[0]), int(n[1]))
                if t in prev:
                    continue
                prev[t] = cell
                if t == dst:
                    out = [t]
                    while prev[out[-1]] is not None:
                        out.append(prev[out[-1]])
                    return out[::-1]
                nxt.append(t)
        frontier = nxt
    return None


def _free_straight_line(
    src, dst, traversable: np.ndarray, visited: np.ndarray, moves=None
) -> list[tuple[int, int]] | None:
    """The straight row or column run from ``src`` to ``dst`` when every cell after ``src``
    is traversable and unvisited, else None.

    Such a run is :func:`cheapest_path`'s unique answer, so Dijkstra need not search: it
    costs n (n unit moves at cost 1). Any other route needs at least n moves (the
    Chebyshev distance); one of exactly n moves must leave the row (or column) and come
    back, so it has at least two diagonal moves and costs >= n - 2 + 2 sqrt 2 > n; one
    of more moves costs >= n + 1 (every move costs >= 1 while ``revisit_cost`` >= 1,
    the only case it is used in). A lawnmower's lane sweeps and lane changes are such
    runs (most of its calls); searching them cost ~1 ms each on a 30x30 grid.
    """
    (r0, c0), (r1, c1) = src, dst
    if r0 == r1:
        step = 1 if c1 > c0 else -1
        cells = [(r0, c) for c in range(c0 + step, c1 + step, step)]
    elif c0 == c1:
        step = 1 if r1 > r0 else -1
        cells = [(r, c0) for r in range(r0 + step, r1 + step, step)]
    else:
        return None
    idx = tuple(np.array(cells).T)
    if not np.asarray(traversable, bool)[idx].all() or np.asarray(visited, bool)[idx].any():
        return None
    if moves is not None:  # every move of the run allowed (the same move, from each cell but the last)
        d = (int(np.sign(r1 - r0)), int(np.sign(c1 - c0)))
        frm = np.array([src, *cells[:-1]])
        if not np.asarray(moves, bool)[frm[:, 0], frm[:, 1], MOVES8_TUPLES.index(d)].all():
            return None
    return [src, *cells]


def cheapest_path(
    src, dst, traversable: np.ndarray, visited: np.ndarray, *, revisit_cost: float = 8.0, moves=None
) -> list[tuple[int, int]] | None:
    """Dijkstra over traversable cells from ``src`` to ``dst`` (both included), where
    a move costs its length (1 or sqrt 2) times ``revisit_cost`` when it enters a visited
    cell, so a transfer between
    lanes crosses new water rather than old track whenever a short detour exists.
    ``moves``: an (R, C, 8) mask of the allowed moves (:func:`allowed_moves`; None = all)."""
    src, dst = (int(src[0]), int(src[1])), (int(dst[0]), int(dst[1]))
    if src == dst:
        return [src]
    if not traversable[dst]:
        return None
    line = _free_straight_line(src, dst, traversable, visited, moves) if revisit_cost >= 1.0 else None
    return line if line is not None else _dijkstra(src, dst, traversable, visited, revisit_cost, moves)


def _dijkstra(
    src: tuple[int, int],
    dst: tuple[int, int],
    traversable: np.ndarray,
    visited: np.ndarray,
    revisit_cost: float,
    moves=None,
) -> list[tuple[int, int]] | None:
    """The search of :func:`cheapest_path` (int ``src``, ``dst``; ``dst`` traversable)."""
    import heapq

    # Plain-Python inner loop over nested lists: on a 30x30 grid the per-node numpy calls of
    # neighbours() cost ~10x the search itself (lawnmower planning was the slowest planner).
    # Same neighbour order (MOVES8), costs and heap, so the same path as before, bit for bit.
    R, C = traversable.shape
    trav = np.asarray(traversable, bool).tolist()
    cost = np.where(np.asarray(visited, bool), float(revisit_cost), 1.0).tolist()
    allow = None if moves is None else np.asarray(moves, bool).tolist()
    dist = {src: 0.0}
    prev: dict = {src: None}
    heap = [(0.0, src)]
    while heap:
        d, cell = heapq.heappop(heap)
        if cell == dst:
            out = [cell]
            while prev[out[-1]] is not None:
                out.append(prev[out[-1]])
            return out[::-1]
        if d > dist.get(cell, np.inf):
            continue
        r, c = cell
        for k, (dr, dc) in enumerate(MOVES8_TUPLES):
            tr, tc = r + dr, c + dc
            if not (0 <= tr < R and 0 <= tc < C and trav[tr][tc]) or (allow is not None and not allow[r][c][k]):
                continue
            t = (tr, tc)
            # Euclidean step length: among equally short 8-connected routes prefer the
            # straight one (a lawnmower lane stays on its row)
            step = 1.4142135623730951 if (dr != 0 and dc != 0) else 1.0
            nd = d + step * cost[tr][tc]
            if nd < dist.get(t, np.inf):
                dist[t] = nd
                prev[t] = cell
                heapq.heappush(heap, (nd, t))
    return None
