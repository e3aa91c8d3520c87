"""Baseline planners: lawnmower, greedy look-ahead and random walk.

Each planner is a class with keyword-only options and
``plan(reward, start, budget, seed=0, mask=None) -> (budget+1, 2) int path``.
Inputs are validated once by :func:`passt_mav.planning.grid.check_inputs`.
All obey the path contract: 8-connected, inside the grid, on traversable cells,
exactly ``budget`` moves, revisits only when no unvisited neighbour exists. A ``mask``
of allowed moves ((R, C, 8), :mod:`passt_mav.planning.grid`) is obeyed move by move.
"""

from __future__ import annotations

import itertools

import numpy as np

from passt_mav.errors import PlannerError
from passt_mav.planning.grid import (
    MOVES8,
    MOVES8_TUPLES,
    allowed_moves,
    best_with_ties,
    cheapest_path,
    check_inputs,
    check_many,
)

__all__ = ["LawnmowerPlanner", "GreedyPlanner", "RandomPlanner"]


def _move_mask(trav: np.ndarray, mask) -> np.ndarray | None:
    """The (R, C, 8) allowed moves when ``mask`` is a move mask, else None (the cells decide alone)."""
    return allowed_moves(trav, mask) if mask is not None and np.ndim(mask) == 3 else None


def _fallback_step(
    cell, visited: np.ndarray, trav: np.ndarray, rng: np.random.Generator, moves=None
) -> tuple[int, int]:
    """An unvisited traversable neighbour if any (random), else any traversable one
    (among the moves ``moves`` allows, when given: (R, C, 8)).

    Candidates in :data:`MOVES8` order, as :func:`~passt_mav.planning.grid.neighbours`
    lists them; plain Python, because the random walk takes this step on every move
    and numpy's per-call cost on 8 cells was most of its planning time.
    """
    r, c = int(cell[0]), int(cell[1])
    R, C = trav.shape
    ok = [True] * 8 if moves is None else moves[r, c].tolist()
    nb = [
        (r + dr, c + dc)
        for (dr, dc), a in zip(MOVES8_TUPLES, ok)
        if a and 0 <= r + dr < R and 0 <= c + dc < C and trav[r + dr, c + dc]
    ]
    pool = [n for n in nb if not visited[n]] or nb
    return pool[rng.integers(len(pool))]


class LawnmowerPlanner:
    """Boustrophedon sweep of the region from the start cell, clipped to the budget.

    Lanes are grid rows ``spacing`` apart. The first lane is the start row, swept
    toward its farther end; following lanes step toward the farther row edge and
    alternate direction; when that edge is reached the rows on the other side of
    the start are swept. Transfers avoid old track where a detour exists (Dijkstra
    with a revisit penalty); a target already reached on the way is skipped. ``spacing="auto"`` spreads the lanes so that one full
    sweep of the region fits the budget (at least 1 row apart), which is what a
    survey boat with a fixed leg length would fly. Consecutive lane targets are
    joined by shortest 8-connected paths over water (BFS), so land is skirted.
    """

    def __init__(self, *, spacing: int | str = "auto"):
        self.spacing = spacing

    def _spacing(self, R: int, C: int, L: int) -> int:
        if self.spacing == "auto":
            # a lane costs about C moves: spread the L // C lanes the budget affords over the rows
            n = max(1, L // max(C, 1))
            return int(np.clip(int(np.ceil(R / n)), 1, max(R - 1, 1)))
        s = int(self.spacing)
        if s < 1:
            raise PlannerError(f"lawnmower spacing must be >= 1, got {self.spacing!r}")
        return s

    def plan(self, reward, start, budget, seed=0, mask=None) -> np.ndarray:
        _, (r0, c0), L, trav = check_inputs(reward, start, budget, mask)
        moves = _move_mask(trav, mask)
        R, C = trav.shape
        # at least one lane beyond the start row must fit on the farther side
        s = min(self._spacing(R, C, L), max(r0, R - 1 - r0, 1))
        rdir = 1 if (R - 1 - r0) >= r0 else -1
        cdir = 1 if (C - 1 - c0) >= c0 else -1
        lanes = [r0 + k * rdir * s for k in range(1, R) if 0 <= r0 + k * rdir * s < R]
        lanes += [r0 - k * rdir * s for k in range(1, R) if 0 <= r0 - k * rdir * s < R]
        targets = [(r0, C - 1 if cdir > 0 else 0)]
        end_col = targets[0][1]
        for lane in lanes:
            other = 0 if end_col == C - 1 else C - 1
            targets += [(lane, end_col), (lane, other)]
            end_col = other
        rng = np.random.default_rng(seed)
        visited = np.zeros((R, C), bool)
        visited[r0, c0] = True
        path = [(r0, c0)]
        queue = list(targets)
        while len(path) <= L:
            leg = None
            while queue and leg is None:
                tgt = queue.pop(0)
                leg = cheapest_path(path[-1], tgt, trav, visited, moves=moves) if trav[tgt] else None
                if leg is not None and (len(leg) < 2 or visited[tgt]):
                    leg = None  # already there / already swept
            if leg is None:  # sweep done (or nothing reachable): keep moving, prefer new cells
                nxt = _fallback_step(path[-1], visited, trav, rng, moves)
                path.append(nxt)
                visited[nxt] = True
                continue
            for cell in leg[1:]:
                if len(path) > L:
                    break
                path.append(cell)
                visited[cell] = True
        return np.asarray(path[: L + 1], dtype=np.int64)


class GreedyPlanner:
    """Best neighbour by reward with a ``lookahead``-move exhaustive look-ahead.

    At each move every sequence of ``lookahead`` moves is scored by the reward of
    the distinct unvisited cells it enters; the first move of the best sequence is
    taken (ties: totals within :data:`~passt_mav.planning.grid.TIE_RTOL`, relative, go to the first
    sequence in :data:`MOVES8` order, so float noise cannot pick another). The first move is restricted to
    unvisited neighbours when one exists.
    """

    def __init__(self, *, lookahead: int = 2):
        self.lookahead = lookahead

    def plan(self, reward, start, budget, seed=0, mask=None) -> np.ndarray:
        return self.plan_many([reward], [start], budget, [seed], None if mask is None else [mask])[0]

    def plan_many(self, rewards, starts, budget, seeds, masks=None) -> list[np.ndarray]:
        """``[plan(rewards[i], starts[i], budget, seeds[i], masks[i]) for i ...]``, the G
        paths advanced together (one set of numpy calls per move for all of them).

        The campaign engine plans all trials of a leg at once: one path's move costs
        ~15 numpy calls on 8^k sequences, so a batch amortises the per-call cost. The
        rows do not interact (same element-wise arithmetic and per-row arg-max as one
        call each; each request's fall-back draws from its own seeded generator), so
        the paths are those of G :meth:`plan` calls (tested).
        """
        k = int(self.lookahead)
        if k < 1:
            raise PlannerError(f"greedy look-ahead must be >= 1, got {self.lookahead!r}")
        qs, st, L, travs = check_many(rewards, starts, budget, seeds, masks)
        if not qs:
            return []
        G = len(qs)
        Q, T = np.stack(qs), np.stack(travs)
        _, R, C = Q.shape
        Mv = None  # (G, R, C, 8) allowed moves, when a request has a move mask
        if masks is not None and any(m is not None and np.ndim(m) == 3 for m in masks):
            Mv = np.stack([allowed_moves(t, m) for t, m in zip(travs, masks)])
        rngs = [np.random.default_rng(sd) for sd in seeds]
        visited = np.zeros((G, R, C), bool)
        cur = np.array(st, dtype=np.int64)  # (G, 2)
        rows = np.arange(G)
        visited[rows, cur[:, 0], cur[:, 1]] = True
        paths = np.empty((G, L + 1, 2), np.int64)
        paths[:, 0] = cur
        seqs = np.array(list(itertools.product(range(8), repeat=k)), dtype=np.int64)  # (8^k, k)
        offsets = np.cumsum(MOVES8[seqs], axis=1)  # (n, k, 2): cells entered, relative to the current one
        g = rows[:, None, None]
        for i in range(1, L + 1):
            cells = cur[:, None, None, :] + offsets  # (G, n, k, 2)
            inside = (cells[..., 0] >= 0) & (cells[..., 0] < R) & (cells[..., 1] >= 0) & (cells[..., 1] < C)
            rr = np.clip(cells[..., 0], 0, R - 1)
            cc = np.clip(cells[..., 1], 0, C - 1)
            ok = inside & T[g, rr, cc]
            if Mv is not None:  # each move allowed from the cell it leaves (the first: the current cell)
                pr = np.concatenate([np.broadcast_to(cur[:, None, None, 0], rr[..., :1].shape), rr[..., :-1]], axis=2)
                pc = np.concatenate([np.broadcast_to(cur[:, None, None, 1], cc[..., :1].shape), cc[..., :-1]], axis=2)
                ok &= Mv[g, pr, pc, seqs[None]]
            feasible = np.cumprod(ok, axis=2).astype(bool)  # a sequence stops being valid at its first bad cell
            seen = visited[g, rr, cc]
            gain = np.where(feasible & ~seen, Q[g, rr, cc], 0.0)
            # a cell entered twice within one sequence pays once
            idx = rr * C + cc
            for j in range(1, k):
                dup = (idx[..., j : j + 1] == idx[..., :j]).any(axis=2)
                gain[..., j] = np.where(dup, 0.0, gain[..., j])
            score = np.where(feasible[..., 0], gain.sum(axis=2), -np.inf)  # (G, n)
            first_fresh = feasible[..., 0] & ~seen[..., 0]
            # restrict to sequences that start on an unvisited cell where there is one
            score = np.where(first_fresh | ~first_fresh.any(axis=1, keepdims=True), score, -np.inf)
            # float noise in the reward map must not pick another move: totals within TIE_RTOL are a
            # tie, taken by the first sequence in MOVES8 order (as exact ties always were)
            best = best_with_ties(score)
            nxt = np.stack([rr[rows, best, 0], cc[rows, best, 0]], axis=1)
            for b in np.flatnonzero(
                ~np.isfinite(score).any(axis=1)
            ):  # cannot happen after check_inputs, kept for safety
                nxt[b] = _fallback_step(tuple(cur[b]), visited[b], T[b], rngs[b], None if Mv is None else Mv[b])
            cur = nxt
            visited[rows, cur[:, 0], cur[:, 1]] = True
            paths[:, i] = cur
        return list(paths)


class RandomPlanner:
    """Seeded random walk: a uniformly random unvisited traversable neighbour,
    or any traversable neighbour when all are visited."""

    def plan(self, reward, start, budget, seed=0, mask=None) -> np.ndarray:
        _, (r0, c0), L, trav = check_inputs(reward, start, budget, mask)
        moves = _move_mask(trav, mask)
        rng = np.random.default_rng(seed)
        visited = np.zeros(trav.shape, bool)
        visited[r0, c0] = True
        path = [(r0, c0)]
        for _ in range(L):
            nxt = _fallback_step(path[-1], visited, trav, rng, moves)
            path.append(nxt)
            visited[nxt] = True
        return np.asarray(path, dtype=np.int64)
