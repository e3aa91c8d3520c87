"""Learning at sea: a few gradient steps on what the mission has seen, kept only if they help.

:func:`update_online` fine-tunes a copy of a fitted KNODE on a sequence of reconstructed states
(the GP estimates of earlier legs, one per snapshot interval) within a budget of seconds, then
asks a scoring callback (higher is better; in the loop the innovation log-likelihood of the next
leg's samples under each model's forecast) whether the copy explains the new data better than the
original. The copy is returned only when its score is strictly higher; otherwise the original
predictor comes back unchanged (the same object). Nothing here knows about legs or samples: the
loop decides what the states and the score are.

Loss: the KNODE's roll-out error in its own scaled units (``z = (u - mean) / std`` per pixel, water
cells only): from every state that has ``horizon`` successors, the model is rolled out ``interval``
snapshot steps per successor and compared with each of the next ``min(horizon, T - 1)`` states
(mean squared error averaged over them); Adam, gradient-norm clip 1.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable

import numpy as np

from passt_mav.errors import ModelError

__all__ = ["update_online"]


def update_online(
    predictor,
    states,
    *,
    budget_s: float,
    score: Callable[[object], float],
    lr: float = 1e-4,
    horizon: int = 1,
    interval: int = 1,
    max_steps: int | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> tuple[object, dict]:
    """``(predictor_out, record)``: ``predictor`` fine-tuned on ``states`` if that raises ``score``, else itself.

    ``states``: ``(T, 2, rows, cols)`` field units (u east, v north; row 0 south), ``T >= 2``,
    consecutive states ``interval`` snapshot intervals apart (e.g. one reconstruction per leg
    of 10 snapshots: ``interval=10``), finite (land filled, as the loop does before
    predicting). ``budget_s``: seconds (by ``clock``) for the gradient steps; a step starts only
    while the budget lasts, so the update overruns it by at most one step. ``max_steps``: a cap
    on the steps (``None``: the budget alone). ``score(p)``: higher is better; called on the
    original and, when at least one step was taken, on the updated copy.

    ``record``: ``kept`` (bool), ``seconds`` (by ``clock``, steps and scoring), ``steps``,
    ``scores`` (``{"original": s0, "updated": s1}``; ``updated`` absent without a step),
    ``loss`` (``[first, last]`` training loss, scaled units, or ``[]``) and ``reason`` (why not
    kept, or ``None``). A predictor without trainable weights (DMD, persistence) is returned
    unchanged with ``reason`` saying so.
    """
    t0 = clock()
    s = np.asarray(states, dtype=np.float32)
    record = {"kept": False, "seconds": 0.0, "steps": 0, "scores": {}, "loss": [], "reason": None}
    if getattr(predictor, "net_", None) is None:
        record["reason"] = f"{type(predictor).__name__} has no trainable weights"
        return predictor, record
    grid = tuple(predictor.grid_shape_)
    if s.ndim != 4 or s.shape[1:] != (2, *grid) or s.shape[0] < 2:
        raise ModelError(f"states must be (time >= 2, 2, {grid[0]}, {grid[1]}), got {s.shape}")
    if not np.isfinite(s).all():
        raise ModelError("states hold NaN/inf; fill land or missing cells (e.g. with 0) before updating")
    if not budget_s >= 0:
        raise ModelError(f"budget_s must be >= 0 seconds, got {budget_s!r}")
    for name, v in (("horizon", horizon), ("interval", interval)):
        if isinstance(v, bool) or int(v) != v or v < 1:
            raise ModelError(f"{name} must be a positive integer, got {v!r}")
    record["scores"]["original"] = float(score(predictor))
    cand, losses = _fine_tune(predictor, s, budget_s, lr, (int(horizon), int(interval)), max_steps, clock, t0)
    record["steps"], record["loss"] = len(losses), [losses[0], losses[-1]] if losses else []
    if not losses:
        record["reason"] = "no gradient step fitted in the budget"
    else:
        record["scores"]["updated"] = float(score(cand))
        record["kept"] = record["scores"]["updated"] > record["scores"]["original"]
        if not record["kept"]:
            record["reason"] = "the update did not raise the score"
    record["seconds"] = float(clock() - t0)
    return (cand if record["kept"] else predictor), record


def _fine_tune(predictor, states: np.ndarray, budget_s, lr, roll, max_steps, clock, t0) -> tuple[object, list]:
    """A deep copy of ``predictor`` after Adam steps on ``states`` while ``clock() - t0 < budget_s``
    (and fewer than ``max_steps``); ``roll``: ``(horizon, interval)``. Returns the copy and the loss
    before each step (scaled units)."""
    import torch

    cand = copy.deepcopy(predictor)
    cand.__dict__.pop("_fast_step", None)  # a compiled step belongs to the original's network
    net = cand.net_
    dev = next(net.parameters()).device
    z = torch.from_numpy(((states - cand.mean_) / cand.std_ * cand.water_).astype(np.float32)).to(dev)
    w = torch.from_numpy(cand.water_.astype(np.float32)).to(dev)
    n_w = float(cand.water_.sum()) * 2
    H, interval = min(roll[0], len(z) - 1), roll[1]
    z0, target = z[: len(z) - H], torch.stack([z[k : len(z) - H + k] for k in range(1, H + 1)], dim=1)
    opt = torch.optim.Adam(net.parameters(), lr=float(lr))

    def rollout_loss():
        zc, tot = z0, 0.0
        for j in range(H):
            for _ in range(interval):
                zc = cand._advance(net, zc)
            tot = tot + (((zc - target[:, j]) ** 2) * w).sum() / (n_w * len(z0))
        return tot / H

    losses: list[float] = []
    net.train()
    while clock() - t0 < budget_s and (max_steps is None or len(losses) < max_steps):
        loss = rollout_loss()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        losses.append(float(loss.detach()))
    net.eval()
    return cand, losses
