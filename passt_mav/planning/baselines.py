"""Baseline planners: lawnmower, greedy look-ahead and random walk.

Each planner is a class with keyword-only options and
``plan(reward, start, budget, seed=0, mask=None) -> (budget+1, 2) int path``.
Inputs are validated once by :func:`passt_mav.planning.grid.check_inputs`.
All obey the path contract: 8-connected, inside the grid, on traversable cells,
exactly ``budget`` moves, revisits only when no unvisited neighbour exists.
"""

from __future__ import annotations

import itertools

import numpy as np

from passt_mav.errors import PlannerError
from passt_mav.planning.grid import MOVES8, check_inputs, cheapest_path, neighbours

__all__ = ["LawnmowerPlanner", "GreedyPlanner", "RandomPlanner"]


def _fallback_step(cell, visited: np.ndarray, trav: np.ndarray, rng: np.random.Generator) -> tuple[int, int]:
    """An unvisited traversable neighbour if any (random), else any traversable one."""
    nb = neighbours(cell, trav)
    fresh = nb[~visited[nb[:, 0], nb[:, 1]]]
    pool = fresh if len(fresh) else nb
    n = pool[rng.integers(len(pool))]
    return int(n[0]), int(n[1])


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
                leg = cheapest_path(path[-1], tgt, trav, visited) if trav[tgt] else None
                if leg is not None and (len(leg) < 2 or visited[tgt]):
                    leg = None  # already there / already swept
            if leg is None:  # sweep done (or nothing reachable): keep moving, prefer new cells
                nxt = _fallback_step(path[-1], visited, trav, rng)
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
    taken (ties: first in :data:`MOVES8` order). The first move is restricted to
    unvisited neighbours when one exists.
    """

    def __init__(self, *, lookahead: int = 2):
        self.lookahead = lookahead

    def plan(self, reward, start, budget, seed=0, mask=None) -> np.ndarray:
        q, (r0, c0), L, trav = check_inputs(reward, start, budget, mask)
        k = int(self.lookahead)
        if k < 1:
            raise PlannerError(f"greedy look-ahead must be >= 1, got {self.lookahead!r}")
        R, C = q.shape
        rng = np.random.default_rng(seed)
        visited = np.zeros((R, C), bool)
        visited[r0, c0] = True
        path = [(r0, c0)]
        seqs = np.array(list(itertools.product(range(8), repeat=k)), dtype=np.int64)  # (8^k, k)
        steps = MOVES8[seqs]  # (8^k, k, 2)
        for _ in range(L):
            cur = np.array(path[-1])
            cells = cur + np.cumsum(steps, axis=1)  # (n, k, 2)
            inside = (cells[..., 0] >= 0) & (cells[..., 0] < R) & (cells[..., 1] >= 0) & (cells[..., 1] < C)
            rr = np.clip(cells[..., 0], 0, R - 1)
            cc = np.clip(cells[..., 1], 0, C - 1)
            ok = inside & trav[rr, cc]
            feasible = np.cumprod(ok, axis=1).astype(bool)  # a sequence stops being valid at its first bad cell
            gain = np.where(feasible & ~visited[rr, cc], q[rr, cc], 0.0)
            # a cell entered twice within one sequence pays once
            idx = rr * C + cc
            for j in range(1, k):
                dup = (idx[:, j : j + 1] == idx[:, :j]).any(axis=1)
                gain[:, j] = np.where(dup, 0.0, gain[:, j])
            score = np.where(feasible[:, 0], gain.sum(axis=1), -np.inf)
            first_fresh = feasible[:, 0] & ~visited[rr[:, 0], cc[:, 0]]
            if first_fresh.any():
                score = np.where(first_fresh, score, -np.inf)
            if not np.isfinite(score).any():  # cannot happen after check_inputs, kept for safety
                nxt = _fallback_step(path[-1], visited, trav, rng)
            else:
                b = int(np.argmax(score))
                nxt = (int(rr[b, 0]), int(cc[b, 0]))
            path.append(nxt)
            visited[nxt] = True
        return np.asarray(path, dtype=np.int64)


class RandomPlanner:
    """Seeded random walk: a uniformly random unvisited traversable neighbour,
    or any traversable neighbour when all are visited."""

    def plan(self, reward, start, budget, seed=0, mask=None) -> np.ndarray:
        _, (r0, c0), L, trav = check_inputs(reward, start, budget, mask)
        rng = np.random.default_rng(seed)
        visited = np.zeros(trav.shape, bool)
        visited[r0, c0] = True
        path = [(r0, c0)]
        for _ in range(L):
            nxt = _fallback_step(path[-1], visited, trav, rng)
            path.append(nxt)
            visited[nxt] = True
        return np.asarray(path, dtype=np.int64)
