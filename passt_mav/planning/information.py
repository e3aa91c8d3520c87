"""Information reward: the expected reduction of the estimate's error variance along a path.

Why. The speed reward says where the current is strong, not where the estimate is wrong;
in the same model + GP loop it is level with a random walk. What a leg's samples buy is a
smaller error in the reconstruction that follows, and under a Gaussian prior that gain is
known *before* the boat moves: the posterior covariance of a GP does not depend on the
values it will observe, only on where (Krause, Singh & Guestrin 2008, "Near-optimal sensor
placements in Gaussian processes", JMLR 9). Ensemble targeting asks the same question of a
forecast's error covariance (Bishop, Etherton & Majumdar 2001, "Adaptive sampling with the
ensemble transform Kalman filter", Mon. Wea. Rev. 129). Here the prior is exactly the one
the loop's reconstruction uses (:class:`passt_mav.reconstruction.GPReconstructor`): the
model's background modes times their fitted factor, the fitted stationary kernels of u and
v, and the sensor noise.

The maths (A-optimality). Stack the grid's error as one vector of 2N rows (u at the N cells,
then v). Its prior covariance is written

    Sigma = F F^T + D,      F: (2N, r),   D = diag(d) >= 0,

with ``F = [sqrt(f) b_1 .. b_m | U_u L_u^1/2 | U_v L_v^1/2]``: the m background modes and the
leading eigenpairs of each component's stationary kernel on the grid; ``d`` holds what the
truncated eigenpairs leave on the diagonal (the kernel's local, sample-scale variance, kept
so that a sample still removes the variance of its own cell). Sampling a set S of distinct
cells observes rows S (u and v of each cell) with noise variances ``s``; let
``e_j = d_j + s_j``. The total variance removed over the region,

    R(S) = tr( Sigma_GS (Sigma_SS + diag s)^-1 Sigma_SG ),

follows from Woodbury's identity with ``Q = sum_j f_j f_j^T / e_j`` (f_j: row j of F),
``P = (I + Q)^-1`` and ``W = F^T F``:

    R(S) = tr W + sum_j d_j^2 / e_j - tr(P M),
    M    = W + sum_j (w_j^2 - 2 w_j) f_j f_j^T,     w_j = d_j / e_j,

(using ``Q P = I - P``; the cross terms ``F F_S^T A^-1 D_S`` give the ``-2 w_j`` part and
``D_S A^-1 D_S`` the ``w_j^2`` part). Adding one cell (rows a = u, v; F_c (2, r)) is a
rank-2 update: with ``Y = P F_c^T``, ``T = F_c Y``, ``S = diag(e_c) + T``,

    P'        = P - Y S^-1 Y^T
    tr(P'M')  = tr(P M) - tr(S^-1 Y^T M Y) + sum_a (w_a^2 - 2 w_a) [T - T S^-1 T]_aa,

so a candidate costs O(r^2) and a whole path of L cells O(L r^2) (r = m + 2 r_k, about
50-140 here). :class:`InformationModel` scores single cells (the reward map) and grows
paths cell by cell (the beam-search planner,
:class:`passt_mav.planning.information.InformationPlanner`). The set function is
monotone; A-optimality is not exactly submodular in general, which is why the planner
searches whole paths (a beam) instead of trusting greedy's guarantee alone.

Approximations, stated: the samples of a leg are scored at the reconstructed time (the
kernel's time axis at zero lag: exact for the offline protocol, which reads every cell at
the leg's end; a boat's samples spread over a leg are a little less informative than
scored); a cell sampled twice is scored once (the planners revisit only when boxed in).

Frames and units: cells (row north, col east) of the reconstruction grid; variances in
(field velocity units)^2, summed over u and v and over water cells. Pure numpy, no I/O.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import PlannerError
from passt_mav.planning.grid import (
    MOVES8,
    allowed_moves,
    best_with_ties,
    check_inputs,
    rank_with_ties,
    tie_tolerance,
)

__all__ = ["InformationModel", "InformationPlanner", "brute_force_reduction"]


def _inv2(S: np.ndarray) -> np.ndarray:
    """Inverse of a stack of symmetric positive-definite 2 x 2 matrices (..., 2, 2)."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
    det = a * c - b * b
    out = np.empty_like(S)
    out[..., 0, 0] = c / det
    out[..., 1, 1] = a / det
    out[..., 0, 1] = out[..., 1, 0] = -b / det
    return out


class InformationModel:
    """Posterior variance bookkeeping of the reconstruction's prior over a grid (module docstring).

    Args:
        F: (2N, r) factor of the low-rank prior covariance; row ``k * N + cell`` = component k
            (0 = u east, 1 = v north) at the flat cell index ``row * C + col``.
        d: (2N,) diagonal remainder of the prior covariance (>= 0).
        noise: (2N,) sensor-noise variance of an observation of that row (> 0).
        shape: (R, C) grid shape, N = R * C.

    The model starts unconditioned (no cell observed); :meth:`conditioned` returns a copy
    that has observed given cells (another boat's cells this leg). Immutable otherwise.
    """

    def __init__(self, F, d, noise, shape):
        self.shape = (int(shape[0]), int(shape[1]))
        N = self.shape[0] * self.shape[1]
        F = np.ascontiguousarray(np.asarray(F, dtype=np.float64))
        d = np.asarray(d, dtype=np.float64).reshape(-1)
        s = np.asarray(noise, dtype=np.float64).reshape(-1)
        if F.ndim != 2 or F.shape[0] != 2 * N or d.shape != (2 * N,) or s.shape != (2 * N,):
            raise PlannerError(
                f"information model: F must be (2N, r), d and noise (2N,) with N = {N}; got {F.shape}, {d.shape}, {s.shape}"
            )
        if not (np.isfinite(F).all() and np.isfinite(d).all() and (d >= 0).all() and (s > 0).all()):
            raise PlannerError("information model: F and d must be finite, d >= 0 and the noise variance > 0")
        self.F, self.d, self.noise = F, d, s
        self.N = N
        r = F.shape[1]
        self.W = F.T @ F
        self.trW = float(np.trace(self.W))
        self.prior_total = self.trW + float(d.sum())
        # state: P = (I + Q)^-1, M, tr(P M), sum d^2/e over observed rows, observed cells
        self.P = np.eye(r)
        self.M = self.W.copy()
        self.trPM = self.trW
        self.sumd = 0.0
        self.observed = np.zeros(N, bool)

    # -- per-cell quantities ---------------------------------------------------------
    def _rows(self, cells: np.ndarray):
        """F rows (n, 2, r), e (n, 2), w (n, 2), d (n, 2) of flat cell indices ``cells`` (n,)."""
        idx = np.stack([cells, cells + self.N], axis=1)  # (n, 2)
        Fc = self.F[idx]  # (n, 2, r)
        d = self.d[idx]
        e = d + self.noise[idx]
        return Fc, e, d / e, d

    @property
    def reduction(self) -> float:
        """Variance removed so far by the observed cells (summed over u, v and cells)."""
        return self.trW + self.sumd - self.trPM

    @property
    def remaining(self) -> float:
        """Total posterior variance left over the region."""
        return self.prior_total - self.reduction

    def gains(self, cells=None) -> np.ndarray:
        """Variance each cell would remove if sampled next (one u + v sample), (n,) or (R, C).

        ``cells``: flat indices; default every cell (returned as an (R, C) map). Cells
        already observed gain 0 (the planners score a revisit as nothing).
        """
        full = cells is None
        c = np.arange(self.N) if full else np.asarray(cells, dtype=np.int64).reshape(-1)
        Fc, e, w, d = self._rows(c)
        g = (
            candidate_scores(
                self.P[None],
                self.M[None],
                np.array([self.trPM]),
                np.array([self.sumd]),
                self.trW,
                Fc[None],
                e[None],
                w[None],
                d[None],
            )[0][0]
            - self.reduction
        )
        g = np.where(self.observed[c], 0.0, np.maximum(g, 0.0))
        return g.reshape(self.shape) if full else g

    def conditioned(self, cells) -> InformationModel:
        """A copy that has observed the distinct cells ``cells`` ((n, 2) row/col or flat indices)."""
        out = object.__new__(InformationModel)
        out.__dict__.update(self.__dict__)
        out.P, out.M, out.observed = self.P.copy(), self.M.copy(), self.observed.copy()
        for c in _flat(cells, self.shape):
            if not out.observed[c]:
                out._add(int(c))
        return out

    def _add(self, c: int) -> None:
        Fc, e, w, d = self._rows(np.array([c]))
        P, M, trPM, sumd = commit(self.P[None], self.M[None], np.array([self.trPM]), np.array([self.sumd]), Fc, e, w, d)
        self.P, self.M, self.trPM, self.sumd = P[0], M[0], float(trPM[0]), float(sumd[0])
        self.observed[c] = True

    def path_reduction(self, path) -> float:
        """Variance removed by sampling the distinct cells of ``path`` ((L+1, 2) row/col), the start included."""
        return self.conditioned(path).reduction - self.reduction


def _flat(cells, shape) -> np.ndarray:
    a = np.asarray(cells, dtype=np.int64)
    if a.ndim == 2 and a.shape[1] == 2:
        a = a[:, 0] * shape[1] + a[:, 1]
    return list(dict.fromkeys(int(x) for x in a.reshape(-1)))


def candidate_scores(P, M, trPM, sumd, trW, Fc, e, w, d):
    """Total reduction after adding one candidate cell to each of K states.

    P, M: (K, r, r); trPM, sumd: (K,); Fc: (K, n, 2, r), n candidates per state; e, w, d:
    (K, n, 2). Returns ``(R_new (K, n), Y^T (K, n, 2, r), S^-1 (K, n, 2, 2), tr(P'M') (K, n),
    sum d^2/e (K, n))`` (module docstring, the rank-2 update).
    """
    K, n, _, r = Fc.shape
    Yt = np.matmul(Fc.reshape(K, 2 * n, r), P).reshape(K, n, 2, r)  # rows of Y^T (P symmetric)
    T = np.einsum("knar,knbr->knab", Yt, Fc)
    S = T.copy()
    S[..., 0, 0] += e[..., 0]
    S[..., 1, 1] += e[..., 1]
    Si = _inv2(S)
    MYt = np.matmul(Yt.reshape(K, 2 * n, r), M).reshape(K, n, 2, r)
    YMY = np.einsum("knar,knbr->knab", MYt, Yt)
    Tn = T - T @ Si @ T
    c = w * w - 2.0 * w
    trPM_new = (
        trPM[:, None] - np.einsum("knab,knba->kn", Si, YMY) + (c * np.stack([Tn[..., 0, 0], Tn[..., 1, 1]], -1)).sum(-1)
    )
    sumd_new = sumd[:, None] + (d * w).sum(-1)
    return trW + sumd_new - trPM_new, Yt, Si, trPM_new, sumd_new


def commit(P, M, trPM, sumd, Fc, e, w, d):
    """States after adding one cell each: P, M (K, r, r), trPM, sumd (K,); Fc (K, 2, r), e/w/d (K, 2)."""
    Fc, e, w, d = (np.asarray(a)[:, None] for a in (Fc, e, w, d))
    _, Yt, Si, trPM_new, sumd_new = candidate_scores(P, M, trPM, sumd, 0.0, Fc, e, w, d)
    Yt, Si = Yt[:, 0], Si[:, 0]  # (K, 2, r), (K, 2, 2)
    P_new = P - np.einsum("kar,kab,kbs->krs", Yt, Si, Yt)
    c = w[:, 0] * w[:, 0] - 2.0 * w[:, 0]  # (K, 2)
    M_new = M + np.einsum("kar,ka,kas->krs", Fc[:, 0], c, Fc[:, 0])
    return P_new, M_new, trPM_new[:, 0], sumd_new[:, 0]


def brute_force_reduction(F, d, noise, rows) -> float:
    """R(S) from dense matrices (tests): ``tr(Sigma_GS (Sigma_SS + diag s)^-1 Sigma_SG)`` for
    observed row indices ``rows`` of the 2N-row prior ``F F^T + diag(d)``."""
    Sig = F @ F.T + np.diag(d)
    rows = np.asarray(rows, dtype=np.int64)
    A = Sig[np.ix_(rows, rows)] + np.diag(np.asarray(noise)[rows])
    B = Sig[:, rows]
    return float(np.trace(B @ np.linalg.solve(A, B.T)))


class InformationPlanner:
    """Direct path optimiser: beam search over whole paths of ``budget`` moves.

    Scores a path by the variance its distinct cells remove under the reconstruction's
    prior (:class:`InformationModel`, passed by the loop as ``info=``), or, with no model,
    by the sum of the reward map over its distinct cells (any reward: the paper's speed map
    with a better optimiser). At each move every beam is extended by each allowed
    8-neighbour (unvisited water; a visited one only when no unvisited neighbour is left,
    scoring nothing) and the ``beam_width`` best partial paths by total score are kept
    (duplicates of one cell with one score merged). ``beam_width=1`` is greedy. Totals within
    :data:`~passt_mav.planning.grid.TIE_RTOL` (relative) of each other are a tie, broken by the
    cell's flat index ``row * cols + col`` (then the beam, then the move), so float noise
    (BLAS threads, summation order) cannot flip a path; ``seed`` is not used.

    Options (keyword-only): ``beam_width`` (default 8).
    """

    uses_information = True

    def __init__(self, *, beam_width: int = 8):
        self.beam_width = beam_width

    def plan(self, reward, start, budget, seed=0, mask=None, info: InformationModel | None = None) -> np.ndarray:
        q, (r0, c0), L, trav = check_inputs(reward, start, budget, mask)
        moves = allowed_moves(trav, mask) if mask is not None and np.ndim(mask) == 3 else None
        K = int(self.beam_width)
        if K < 1:
            raise PlannerError(f"beam_width must be >= 1, got {self.beam_width!r}")
        R, C = q.shape
        if info is not None and info.shape != (R, C):
            raise PlannerError(f"information model grid {info.shape} does not match the reward map {(R, C)}")
        start_flat = r0 * C + c0
        if info is not None:
            base = info if info.observed[start_flat] else info.conditioned([start_flat])
            st = _InfoBeams(base)
        else:
            st = _AdditiveBeams(q.ravel())
        visited = np.zeros((1, R * C), bool)
        visited[0, start_flat] = True
        pos = np.array([[r0, c0]], np.int64)
        score = np.zeros(1)
        paths = np.empty((1, L + 1, 2), np.int64)
        paths[0, 0] = (r0, c0)
        for i in range(1, L + 1):
            cells = pos[:, None, :] + MOVES8[None]  # (B, 8, 2)
            inside = (cells[..., 0] >= 0) & (cells[..., 0] < R) & (cells[..., 1] >= 0) & (cells[..., 1] < C)
            rr, cc = np.clip(cells[..., 0], 0, R - 1), np.clip(cells[..., 1], 0, C - 1)
            flat = rr * C + cc
            ok = inside & trav[rr, cc]
            if moves is not None:  # the moves the mask allows from each beam's cell
                ok &= moves[pos[:, 0], pos[:, 1]]
            fresh = ok & ~np.take_along_axis(visited, flat, axis=1)
            allow = np.where(fresh.any(axis=1, keepdims=True), fresh, ok)
            total = np.where(allow, st.totals(flat, fresh & allow), -np.inf)
            chosen = _best_distinct(total, flat, K)
            bi = np.array([b for b, _ in chosen])
            ai = np.array([a for _, a in chosen])
            new_flat = flat[bi, ai]
            new_fresh = (fresh & allow)[bi, ai]
            st.advance(bi, new_flat, new_fresh)
            visited = visited[bi].copy()
            visited[np.arange(len(bi)), new_flat] = True
            pos = np.stack([rr[bi, ai], cc[bi, ai]], axis=1)
            score = total[bi, ai]
            paths = paths[bi].copy()
            paths[:, i] = pos
        # the beams are in rank order: beam 0 is the best (ties: the smaller cells)
        return paths[int(best_with_ties(score))]


def _best_distinct(total, flat, K: int) -> list[tuple[int, int]]:
    """The (beam, move) pairs of the ``K`` best finite candidate scores ``total`` (B, 8), ranked by
    :func:`~passt_mav.planning.grid.rank_with_ties` (totals within ``TIE_RTOL`` of each other are one
    tie, broken by the candidate's flat cell index ``flat`` (B, 8), then its beam and move), one per
    (cell, score): two paths that reach the same cell with tied scores are the same cells visited,
    and keeping both would waste a beam slot."""
    B = total.shape[0]
    keys = np.stack(
        [flat, np.broadcast_to(np.arange(B)[:, None], flat.shape), np.broadcast_to(np.arange(8), flat.shape)], -1
    )
    tol = tie_tolerance(total)
    chosen: list[tuple[int, int]] = []
    seen: dict[int, list[float]] = {}
    for o in rank_with_ties(total, keys):
        b, a = divmod(int(o), 8)
        cell, t = int(flat[b, a]), float(total[b, a])
        if any(abs(t - u) <= tol for u in seen.get(cell, ())):
            continue
        seen.setdefault(cell, []).append(t)
        chosen.append((b, a))
        if len(chosen) == K:
            break
    return chosen


class _AdditiveBeams:
    """Beam scores for a reward map: the sum over distinct cells (no interaction)."""

    def __init__(self, q_flat):
        self.q = q_flat
        self.score = np.zeros(1)

    def totals(self, flat, fresh):
        """(B, n) path score after each candidate move (a revisit adds nothing)."""
        return self.score[:, None] + np.where(fresh, self.q[flat], 0.0)

    def advance(self, parents, cells, fresh):
        self.score = self.score[parents] + np.where(fresh, self.q[cells], 0.0)


class _InfoBeams:
    """Beam states of an :class:`InformationModel`: P, M, tr(P M), sum d^2/e per beam."""

    def __init__(self, model: InformationModel):
        self.m = model
        self.P, self.M = model.P[None].copy(), model.M[None].copy()
        self.trPM, self.sumd = np.array([model.trPM]), np.array([model.sumd])
        self.offset = model.reduction  # the start cell (and anything conditioned) is not the path's

    def totals(self, flat, fresh):
        """(B, n) variance removed by the path after each candidate move (a revisit adds nothing)."""
        B, n = flat.shape
        Fc, e, w, d = self.m._rows(flat.reshape(-1))
        r = Fc.shape[-1]
        Rn = candidate_scores(
            self.P,
            self.M,
            self.trPM,
            self.sumd,
            self.m.trW,
            Fc.reshape(B, n, 2, r),
            e.reshape(B, n, 2),
            w.reshape(B, n, 2),
            d.reshape(B, n, 2),
        )[0]
        base = (self.m.trW + self.sumd - self.trPM)[:, None]
        return np.where(fresh, Rn, base) - self.offset

    def advance(self, parents, cells, fresh):
        P, M, trPM, sumd = self.P[parents], self.M[parents], self.trPM[parents], self.sumd[parents]
        idx = np.flatnonzero(fresh)
        if idx.size:
            Fc, e, w, d = self.m._rows(cells[idx])
            P2, M2, t2, s2 = commit(P[idx], M[idx], trPM[idx], sumd[idx], Fc, e, w, d)
            P, M, trPM, sumd = P.copy(), M.copy(), trPM.copy(), sumd.copy()
            P[idx], M[idx], trPM[idx], sumd[idx] = P2, M2, t2, s2
        self.P, self.M, self.trPM, self.sumd = P, M, trPM, sumd
