"""Policy-gradient planner (the paper's planner, after Manjanna et al. 2018,
"Reinforcement learning with non-uniform state representations for adaptive search").

MDP: state = (robot cell, visited set, steps left) on a reward map ``q`` (rows, cols)
in [0, 1]; actions = the 8 king moves (or 4); a move into an unvisited cell earns
``q`` there, a visited cell earns 0; horizon = the path budget L.

Non-uniform state representation: for each move direction ``d`` the policy sees the
not-yet-collected reward in windows along that direction, fine near the robot and
coarser farther out - the neighbour cell itself, then square blocks of side 3, 7 and
15 centred 3, 7 and 15 cells away (:data:`SCALES`). Each block's feature is its sum of
uncollected reward divided by its full area (cells off the grid or on land count 0,
so the edge of the world looks poor). The same per-direction features are also given
relative to their maximum over the 8 directions, plus the fraction of budget left.

Policy: one small MLP scores every direction from that direction's features (weights
shared across directions, so the policy is rotation-equivariant and tiny); a softmax
over the scores of the ALLOWED moves gives the move distribution. Invalid moves
(off-grid, land) are masked rather than penalised - the policy never proposes them,
so no training signal is spent learning walls. Visited neighbours are masked too
whenever an unvisited one exists (the path contract: revisit only when boxed in).

Training (:func:`train_policy`): REINFORCE with a per-time-step batch-mean baseline
on random Gaussian-mixture reward maps (torch, seeded). Test phase
(:class:`PolicyGradientPlanner`): the best of ``n_rollouts`` stochastic roll-outs and
the greedy (argmax) roll-out on the actual reward map, all batched in numpy.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from passt_mav.errors import PlannerError
from passt_mav.planning.grid import MOVES4, MOVES8, allowed_moves, best_with_ties, check_many, top_l_bound

__all__ = [
    "SCALES",
    "N_FEATURES",
    "PolicyGradientPlanner",
    "PolicyWeights",
    "features",
    "rollout",
    "random_reward_map",
    "train_policy",
    "save_policy",
    "load_policy",
    "cache_policy",
    "DEFAULT_CHECKPOINT",
]

#: (distance of the window centre along the direction, half-size) per scale level
SCALES = ((1, 0), (3, 1), (7, 3), (15, 7))
#: per-direction features: absolute and relative window means, plus budget fraction left
N_FEATURES = 2 * len(SCALES) + 1
DEFAULT_CHECKPOINT = Path(__file__).resolve().parent.parent / "assets" / "pg_planner.pt"


@dataclass
class PolicyWeights:
    """Per-direction scorer ``s = w2 . tanh(W1 x + b1) + b2`` (numpy float64)."""

    W1: np.ndarray  # (hidden, N_FEATURES)
    b1: np.ndarray  # (hidden,)
    w2: np.ndarray  # (hidden,)
    b2: float

    def scores(self, feats: np.ndarray) -> np.ndarray:
        """feats (..., 8, F) -> scores (..., 8)."""
        h = np.tanh(feats @ self.W1.T + self.b1)
        return h @ self.w2 + self.b2


def _integral(eff: np.ndarray) -> np.ndarray:
    """(B, R, C) -> (B, R+1, C+1) summed-area table with a zero first row/col."""
    B, R, C = eff.shape
    S = np.zeros((B, R + 1, C + 1))
    S[:, 1:, 1:] = eff.cumsum(1).cumsum(2)
    return S


def features(
    q: np.ndarray, trav: np.ndarray, visited: np.ndarray, pos: np.ndarray, frac_left: float, moves: np.ndarray = MOVES8
) -> np.ndarray:
    """Per-direction features, batched.

    q, trav: (R, C) reward (0 on land) and traversable mask, shared by the batch, or
    (B, R, C) each; visited: (B, R, C) bool; pos: (B, 2) int cells; frac_left: budget
    fraction left in [0, 1]. Returns (B, n_moves, N_FEATURES) float64.
    """
    return _features_eff(_uncollected(q, trav, visited), pos, frac_left, moves)


def _uncollected(q: np.ndarray, trav: np.ndarray, visited: np.ndarray) -> np.ndarray:
    """(B, R, C) float64 reward still to collect: ``q`` on traversable, unvisited cells, else 0."""
    return np.broadcast_to(q * trav, visited.shape) * ~visited


def _features_eff(
    eff: np.ndarray, pos: np.ndarray, frac_left: float, moves: np.ndarray, buf: dict | None = None
) -> np.ndarray:
    """:func:`features` from the uncollected reward ``eff`` (B, R, C) = q * trav * ~visited.

    ``buf``: a dict the caller keeps across the steps of one roll-out; the summed-area
    table is allocated once in it and rebuilt in place (same numbers as :func:`_integral`).
    """
    B, R, C = eff.shape
    if buf is None:
        S = _integral(eff)
    else:
        if "S" not in buf:
            buf["S"] = np.zeros((B, R + 1, C + 1))
        S = buf["S"]
        # eff.cumsum(1).cumsum(2) written into S one row, then one column, at a time:
        # the same additions in the same order (bit-identical, tested against
        # _integral), but ~R + C vector adds instead of numpy's element-by-element
        # cumsum loops (measured 0.5 vs 1.4 ms for 195 x 30 x 30, most of a roll-out step)
        for i in range(R):
            np.add(S[:, i, 1:], eff[:, i], out=S[:, i + 1, 1:])
        for j in range(1, C):
            np.add(S[:, 1:, j], S[:, 1:, j + 1], out=S[:, 1:, j + 1])
    D = np.array([s[0] for s in SCALES])
    H = np.array([s[1] for s in SCALES])
    # window centres (B, M, K, 2)
    cen = pos[:, None, None, :] + moves[None, :, None, :] * D[None, None, :, None]
    r0 = np.clip(cen[..., 0] - H, 0, R)
    r1 = np.clip(cen[..., 0] + H + 1, 0, R)
    c0 = np.clip(cen[..., 1] - H, 0, C)
    c1 = np.clip(cen[..., 1] + H + 1, 0, C)
    b = np.arange(B)[:, None, None]
    tot = S[b, r1, c1] - S[b, r0, c1] - S[b, r1, c0] + S[b, r0, c0]
    area = (2 * H + 1) ** 2
    absf = tot / area  # (B, M, K)
    rel = absf / (absf.max(axis=1, keepdims=True) + 1e-6)
    left = np.full(absf.shape[:2] + (1,), float(frac_left))
    return np.concatenate([absf, rel, left], axis=-1)


def _allowed(
    trav: np.ndarray, visited: np.ndarray, pos: np.ndarray, moves: np.ndarray, move_ok: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(B, M) allowed-move mask and the (B, M, 2) target cells (clipped). ``move_ok``: (B, R, C, M)
    bool, the moves a move mask allows from each cell (None: all)."""
    R, C = visited.shape[1:]
    nb = pos[:, None, :] + moves[None]
    inside = (nb[..., 0] >= 0) & (nb[..., 0] < R) & (nb[..., 1] >= 0) & (nb[..., 1] < C)
    rr = np.clip(nb[..., 0], 0, R - 1)
    cc = np.clip(nb[..., 1], 0, C - 1)
    b = np.arange(pos.shape[0])[:, None]
    tr = trav[rr, cc] if trav.ndim == 2 else trav[b, rr, cc]
    ok = inside & tr
    if move_ok is not None:
        ok &= move_ok[b[:, 0], pos[:, 0], pos[:, 1]]
    fresh = ok & ~visited[b, rr, cc]
    allowed = np.where(fresh.any(axis=1, keepdims=True), fresh, ok)
    return allowed, np.stack([rr, cc], axis=-1)


def rollout(
    weights: PolicyWeights,
    q,
    trav,
    start,
    budget: int,
    *,
    n: int,
    rng,
    greedy_first: bool = False,
    moves: np.ndarray = MOVES8,
    record: bool = False,
    temperature: float = 1.0,
    move_ok: np.ndarray | None = None,
):
    """Run ``n`` roll-outs of ``budget`` moves in parallel.

    ``move_ok``: (n, R, C, M) bool, the moves (of ``moves``) allowed from each cell (a move mask,
    :mod:`passt_mav.planning.grid`); None = every move onto a traversable cell.

    q, trav: (R, C) or (B=n, R, C); start: (2,) or (n, 2). With ``greedy_first`` the
    first roll-out takes the argmax move every step. Returns ``paths (n, L+1, 2)``,
    ``returns (n,)`` and, with ``record``, ``(feats (L, n, M, F), allowed (L, n, M),
    actions (L, n), rewards (L, n))`` for training.

    ``rng``: one generator for all ``n`` roll-outs, or a list of G generators for G
    equal groups of ``n // G`` consecutive roll-outs (G independent planning requests
    advanced together; group g draws its uniforms from ``rng[g]`` exactly as a call
    with ``n // G`` roll-outs and that generator would, and ``greedy_first`` applies to
    each group's first roll-out). Every row's arithmetic is independent of the others,
    so a group's paths equal those of its own call (tested).
    """
    R, C = q.shape[-2:]
    rngs, ng = _split_generators(rng, n)
    L = int(budget)
    pos, visited, paths = _start(start, n, R, C, L)
    b = np.arange(n)
    rets = np.zeros(n)
    rec = ([], [], [], []) if record else None
    # the uncollected reward, kept up to date cell by cell (a move zeroes one cell per
    # row) instead of being rebuilt from q, trav and visited every step: same values
    eff = _uncollected(q, trav, visited)
    buf: dict = {}
    for t in range(L):
        f = _features_eff(eff, pos, 1.0 - t / L, moves, buf)
        allowed, tgt = _allowed(trav, visited, pos, moves, move_ok)
        s, p = _move_probabilities(weights, f, allowed, temperature)
        a = _sample_moves(p, s, allowed, rngs, ng, greedy_first)
        new = tgt[b, a]
        gain = _gain(q, visited, new)
        rets += gain
        if record:
            for kept, x in zip(rec, (f, allowed, a, gain), strict=True):
                kept.append(x)
        visited[b, new[:, 0], new[:, 1]] = True
        eff[b, new[:, 0], new[:, 1]] = 0.0
        pos = new
        paths[:, t + 1] = pos
    if record:
        return paths, rets, tuple(np.stack(x) for x in rec)
    return paths, rets


def _split_generators(rng, n: int) -> tuple[list, int]:
    """:func:`rollout`'s ``rng`` as a list of G generators, and the group size ``n // G``.

    Raises :class:`PlannerError` when ``n`` roll-outs do not split into G equal groups.
    """
    rngs = list(rng) if isinstance(rng, (list, tuple)) else [rng]
    G = len(rngs)
    if n % G:
        raise PlannerError(f"{n} roll-outs do not split into {G} equal groups")
    return rngs, n // G


def _start(start, n: int, R: int, C: int, L: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first state of ``n`` roll-outs of ``L`` moves on an (R, C) grid.

    Returns the start cells ``pos`` (n, 2) int64 (``start`` is (2,) or (n, 2)), the visited
    masks (n, R, C) with each start cell visited, and ``paths`` (n, L+1, 2) with the start
    cells as first row (the rest left to fill).
    """
    pos = np.broadcast_to(np.asarray(start, dtype=np.int64), (n, 2)).copy()
    visited = np.zeros((n, R, C), bool)
    visited[np.arange(n), pos[:, 0], pos[:, 1]] = True
    paths = np.empty((n, L + 1, 2), np.int64)
    paths[:, 0] = pos
    return pos, visited, paths


def _move_probabilities(
    weights: PolicyWeights, f: np.ndarray, allowed: np.ndarray, temperature: float
) -> tuple[np.ndarray, np.ndarray]:
    """The policy's move distribution from the features ``f`` (B, M, F) over the ``allowed`` moves (B, M).

    Returns the scores divided by ``temperature``, shifted so each row's maximum is 0, with -inf
    on disallowed moves, and their softmax ``p`` (B, M) (0 on disallowed moves).
    """
    s = weights.scores(f) / max(temperature, 1e-6)
    s = np.where(allowed, s, -np.inf)
    s = s - s.max(axis=1, keepdims=True)
    p = np.exp(s)
    p /= p.sum(axis=1, keepdims=True)
    return s, p


def _sample_moves(
    p: np.ndarray, s: np.ndarray, allowed: np.ndarray, rngs: list, ng: int, greedy_first: bool
) -> np.ndarray:
    """One move index per roll-out (n,), drawn from ``p`` (n, M) by inverse CDF.

    Group g (``ng`` consecutive rows) draws its uniforms from ``rngs[g]``; a draw that lands on a
    disallowed move by round-off at the top end takes the most likely move instead. With
    ``greedy_first`` each group's first roll-out takes the argmax of its scores ``s``, scores within
    :data:`~passt_mav.planning.grid.TIE_RTOL` (relative) a tie taken by the first move in order (as
    exact ties always were), so float noise cannot pick another.
    """
    n, M = p.shape
    b = np.arange(n)
    u = rngs[0].random((n, 1)) if len(rngs) == 1 else np.concatenate([g.random((ng, 1)) for g in rngs])
    a = np.minimum((p.cumsum(axis=1) < u).sum(axis=1), M - 1)
    a = np.where(allowed[b, a], a, np.argmax(p, axis=1))  # guard against round-off at the top end
    if greedy_first:
        firsts = np.arange(0, n, ng)
        a[firsts] = best_with_ties(s[firsts])
    return a


def _gain(q: np.ndarray, visited: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Reward (n,) of each roll-out's move into the cells ``new`` (n, 2): ``q`` there (``q`` is (R, C)
    or (n, R, C)), 0 for a cell already visited."""
    b = np.arange(len(new))
    qv = q[new[:, 0], new[:, 1]] if q.ndim == 2 else q[b, new[:, 0], new[:, 1]]
    return np.where(visited[b, new[:, 0], new[:, 1]], 0.0, qv)


# -- training -------------------------------------------------------------------


def random_reward_map(
    rng: np.random.Generator, rows: int, cols: int, *, land: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """A random Gaussian-mixture reward map in [0, 1] and its traversable mask.

    1-6 Gaussian bumps (widths 1.5-8 cells, amplitudes 0.2-1), a weak random
    background, and with probability 0.3 (when ``land``) a disc of land.
    """
    rr, cc = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    q = np.zeros((rows, cols))
    for _ in range(int(rng.integers(1, 7))):
        r0, c0 = rng.uniform(0, rows - 1), rng.uniform(0, cols - 1)
        w = rng.uniform(1.5, 8.0)
        q += rng.uniform(0.2, 1.0) * np.exp(-((rr - r0) ** 2 + (cc - c0) ** 2) / (2 * w * w))
    q += rng.uniform(0, 0.1) * rng.random((rows, cols))
    trav = np.ones((rows, cols), bool)
    if land and rng.random() < 0.3:
        r0, c0 = rng.uniform(0, rows - 1), rng.uniform(0, cols - 1)
        trav &= (rr - r0) ** 2 + (cc - c0) ** 2 > rng.uniform(2, 6) ** 2
    q = np.where(trav, q, 0.0)
    return q / q.max(), trav


def _init_weights(rng: np.random.Generator, hidden: int) -> PolicyWeights:
    return PolicyWeights(
        W1=rng.normal(0, 1 / np.sqrt(N_FEATURES), (hidden, N_FEATURES)),
        b1=np.zeros(hidden),
        w2=rng.normal(0, 1 / np.sqrt(hidden), hidden),
        b2=0.0,
    )


def train_policy(
    *,
    episodes: int = 6000,
    batch: int = 32,
    hidden: int = 16,
    lr: float = 0.01,
    gamma: float = 0.97,
    entropy: float = 0.01,
    seed: int = 0,
    grid_range=(16, 36),
    budget_range=(10, 120),
    progress: bool = True,
):
    """REINFORCE on random Gaussian-mixture maps. Returns ``(weights, curve)``.

    Each iteration draws one grid size and budget, ``batch`` maps and start cells,
    rolls the current policy out (numpy), then takes one Adam step on
    ``-mean(log pi(a|s) * A) - entropy * H`` with ``A`` the discounted return-to-go
    minus its batch mean at that step, divided by the batch std. ``curve`` holds per
    iteration: episodes so far, mean return / top-L bound (fraction collected).
    """
    import torch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    w = _init_weights(rng, hidden)
    params = [torch.tensor(x, dtype=torch.float64, requires_grad=True) for x in (w.W1, w.b1, w.w2, np.array(w.b2))]
    opt = torch.optim.Adam(params, lr=lr)
    n_iter = max(1, episodes // batch)
    curve = []
    it_range = range(n_iter)
    if progress:
        from tqdm import tqdm

        it_range = tqdm(it_range, desc="train policy", unit="it")
    for it in it_range:
        q, trav, starts, L = _training_batch(rng, batch, grid_range, budget_range)
        _, rets, (F, A, act, rew) = rollout(_numpy_weights(params), q, trav, starts, L, n=batch, rng=rng, record=True)
        loss = _reinforce_loss(params, F, A, act, _advantages(rew, gamma), entropy)
        opt.zero_grad()
        loss.backward()
        opt.step()
        bound = np.mean([top_l_bound(q[i], starts[i], L) for i in range(batch)])
        curve.append([(it + 1) * batch, float(rets.mean() / max(bound, 1e-9))])
    return _numpy_weights(params), curve


def _training_batch(
    rng: np.random.Generator, batch: int, grid_range, budget_range
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """One training iteration's problems, drawn from ``rng``: a grid size (rows, cols in ``grid_range``,
    inclusive) and budget ``L`` (in ``budget_range``, inclusive) shared by the batch, ``batch``
    random reward maps and a random traversable start cell on each.

    Returns ``q`` (batch, rows, cols), ``trav`` (same shape, bool), ``starts`` (batch, 2) int64 and ``L``.
    """
    rows, cols = (int(x) for x in rng.integers(grid_range[0], grid_range[1] + 1, 2))
    L = int(rng.integers(budget_range[0], budget_range[1] + 1))
    maps = [random_reward_map(rng, rows, cols) for _ in range(batch)]
    q = np.stack([m[0] for m in maps])
    trav = np.stack([m[1] for m in maps])
    starts = np.empty((batch, 2), np.int64)
    for i in range(batch):
        cells = np.argwhere(trav[i])
        starts[i] = cells[rng.integers(len(cells))]
    return q, trav, starts, L


def _numpy_weights(params) -> PolicyWeights:
    """A numpy copy of the torch parameters ``[W1, b1, w2, b2]`` being trained."""
    return PolicyWeights(*(p.detach().numpy().copy() for p in params[:3]), float(params[3].detach()))


def _advantages(rew: np.ndarray, gamma: float) -> np.ndarray:
    """REINFORCE advantages (L, B) from the rewards ``rew`` (L, B): the return-to-go discounted by
    ``gamma``, minus its batch mean at each step, divided by the std over all steps and roll-outs."""
    G = np.zeros_like(rew)
    acc = np.zeros(rew.shape[1])
    for t in range(rew.shape[0] - 1, -1, -1):
        acc = rew[t] + gamma * acc
        G[t] = acc
    adv = G - G.mean(axis=1, keepdims=True)
    return adv / (adv.std() + 1e-8)


def _reinforce_loss(params, F: np.ndarray, A: np.ndarray, act: np.ndarray, adv: np.ndarray, entropy: float):
    """The policy-gradient loss ``-mean(log pi(a|s) * adv) - entropy * H`` (a torch scalar) of the
    recorded roll-outs: features ``F`` (L, B, M, F), allowed moves ``A`` (L, B, M), actions ``act``
    (L, B), advantages ``adv`` (L, B); ``H`` is the mean entropy of the move distributions."""
    import torch

    Ft = torch.from_numpy(F)
    h = torch.tanh(Ft @ params[0].T + params[1])
    s = h @ params[2] + params[3]
    s = s.masked_fill(~torch.from_numpy(A), -1e9)
    logp = torch.log_softmax(s, dim=-1)
    lp = logp.gather(-1, torch.from_numpy(act)[..., None])[..., 0]
    ent = -(logp.exp() * logp).sum(-1).mean()
    return -(lp * torch.from_numpy(adv)).mean() - entropy * ent


def save_policy(weights: PolicyWeights, path: str | Path, meta: dict) -> tuple[Path, Path]:
    """Write ``path`` (.pt state_dict of float32 tensors) and ``path.json`` (metadata)."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sd = {
        "W1": torch.tensor(weights.W1, dtype=torch.float32),
        "b1": torch.tensor(weights.b1, dtype=torch.float32),
        "w2": torch.tensor(weights.w2, dtype=torch.float32),
        "b2": torch.tensor([weights.b2], dtype=torch.float32),
    }
    torch.save(sd, path)
    meta = dict(
        meta,
        architecture={
            "type": "per-direction MLP",
            "hidden": int(weights.W1.shape[0]),
            "n_features": N_FEATURES,
            "scales": [list(s) for s in SCALES],
        },
    )
    jpath = path.with_suffix(".json")
    jpath.write_text(json.dumps(meta, indent=1) + "\n")
    return path, jpath


def load_policy(path: str | Path | None = None) -> PolicyWeights:
    """Load a checkpoint written by :func:`save_policy` (``weights_only=True``)."""
    path = Path(path) if path is not None else DEFAULT_CHECKPOINT
    if not path.exists():
        raise PlannerError(
            f"policy checkpoint {path} not found; train one with 'python -m passt_mav.planning.train --out {path}'"
        )
    import torch

    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
        w = PolicyWeights(
            sd["W1"].double().numpy(), sd["b1"].double().numpy(), sd["w2"].double().numpy(), float(sd["b2"][0])
        )
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is a user error
        raise PlannerError(f"cannot read policy checkpoint {path}: {exc}") from None
    if w.W1.shape[1] != N_FEATURES:
        raise PlannerError(
            f"policy checkpoint {path} expects {w.W1.shape[1]} features, this version computes {N_FEATURES}"
        )
    return w


_CACHE: dict[str, PolicyWeights] = {}


def cache_policy(checkpoint: str | Path, weights: PolicyWeights) -> None:
    """Serve ``weights`` for ``checkpoint`` (a path) to every :class:`PolicyGradientPlanner` of this
    process, without reading the file (a policy just trained, before or instead of its file)."""
    _CACHE[str(checkpoint)] = weights


class PolicyGradientPlanner:
    """Test phase of the policy-gradient planner.

    Options (keyword-only): ``checkpoint`` (path; default the shipped
    ``passt_mav/assets/pg_planner.pt``), ``n_rollouts`` stochastic roll-outs (the
    greedy argmax roll-out is always added), ``moves`` (8 or 4), ``temperature``.
    ``plan`` returns the roll-out collecting the most reward (ties: the greedy one).
    """

    def __init__(
        self, *, checkpoint: str | Path | None = None, n_rollouts: int = 12, moves: int = 8, temperature: float = 1.0
    ):
        self.checkpoint = checkpoint
        self.n_rollouts = n_rollouts
        self.moves = moves
        self.temperature = temperature

    def _weights(self) -> PolicyWeights:
        key = str(self.checkpoint or DEFAULT_CHECKPOINT)
        if key not in _CACHE:
            _CACHE[key] = load_policy(self.checkpoint)
        return _CACHE[key]

    def plan(self, reward, start, budget, seed=0, mask=None) -> np.ndarray:
        return self.plan_many([reward], [start], budget, [seed], None if mask is None else [mask])[0]

    def plan_many(self, rewards, starts, budget, seeds, masks=None) -> list[np.ndarray]:
        """``[plan(rewards[i], starts[i], budget, seeds[i], masks[i]) for i ...]`` in one batched roll-out.

        The G requests' roll-outs advance together (G x (1 + n_rollouts) rows per step),
        which amortises numpy's per-call cost over the batch: the campaign engine plans
        all trials of a leg at once. Same paths as G calls of :meth:`plan` (the rows do
        not interact, each request draws from its own seeded generator; tested).
        """
        raw, st, L, travs = check_many(rewards, starts, budget, seeds, masks)
        G = len(raw)
        if G == 0:
            return []
        qs = [q / m if (m := q.max()) > 0 else q for q in raw]  # the policy was trained on maps scaled to [0, 1]
        if self.moves not in (4, 8):
            raise PlannerError(f"moves must be 4 or 8, got {self.moves!r}")
        if int(self.n_rollouts) < 0:
            raise PlannerError(f"n_rollouts must be >= 0, got {self.n_rollouts!r}")
        moves = MOVES8 if self.moves == 8 else MOVES4
        n = 1 + int(self.n_rollouts)
        Q = np.repeat(np.stack(qs), n, axis=0)
        T = np.repeat(np.stack(travs), n, axis=0)
        S0 = np.repeat(np.array(st, dtype=np.int64), n, axis=0)
        move_ok = None  # a request's move mask, as the moves of this policy (MOVES4 = MOVES8[::2])
        if masks is not None and any(m is not None and np.ndim(m) == 3 for m in masks):
            mv = np.stack([allowed_moves(t, m) for t, m in zip(travs, masks)])
            move_ok = np.repeat(mv if self.moves == 8 else mv[..., ::2], n, axis=0)
        rngs = [np.random.default_rng(sd) for sd in seeds]
        paths, rets = rollout(
            self._weights(),
            Q,
            T,
            S0,
            L,
            n=G * n,
            rng=rngs,
            greedy_first=True,
            moves=moves,
            temperature=self.temperature,
            move_ok=move_ok,
        )
        # the best roll-out's path; returns within TIE_RTOL (float noise) go to the first roll-out
        return [paths[g * n + int(best_with_ties(rets[g * n : (g + 1) * n]))] for g in range(G)]
