"""Learning at sea in the loop: between legs, a few gradient steps on what the mission has reconstructed,
kept only when they explain the next leg's samples better (``model_update``, off by default).

The mission's states are the first leg's initial state and every reconstruction since (one per leg,
field units, at field times a whole number of snapshots apart). When leg ``n``'s samples arrive and
before they enter the estimate, :meth:`OnlineUpdate.consider` fine-tunes a copy of the loop's
predictor on the last ``window`` of those states (:func:`passt_mav.models.online.update_online`:
roll-out loss, consecutive states ``interval`` snapshots apart) and scores the current model and the
copy by the innovation log likelihood (nats) of leg ``n``'s samples under each one's forecast of the
leg from the leg's initial state (:meth:`PasstLoop.loglik_at
<passt_mav.loop.passt.PasstLoop.loglik_at>`: the GP's stationary kernels and noise as they stand
before the leg's fit, the score the prior blend and the guard use). The copy replaces the loop's
predictor, and its forecast the leg's, only when its score is strictly higher; otherwise nothing
changes. The model alone (the guard's and the blend's open loop, the campaign's ``model`` method,
the run's ``rmse_model``) stays the predictor the loop was built with.

Determinism: the gradient steps are deterministic on one CPU thread (no random draw); a budget in
seconds is not (a slower machine takes fewer steps). ``max_steps`` caps the steps; with a budget
large enough for them, the number of steps and so the decision do not depend on the machine's speed
(what the offline campaign and the tests do). A replay (:mod:`passt_mav.analysis.replay`) takes each
leg's recorded number of steps (:attr:`OnlineUpdate.replay_steps`) whatever the budget.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from passt_mav.errors import ModelError
from passt_mav.loop.blend import model_forecast

__all__ = ["MODEL_UPDATES", "ModelUpdate", "OnlineUpdate", "model_update_problem"]

#: values of ``ModelUpdate.online``
MODEL_UPDATES = ("off", "on")


@dataclass(frozen=True)
class ModelUpdate:
    """The ``model_update`` options (mission key, :class:`~passt_mav.loop.passt.LoopOptions`,
    ``passt-mav evaluate --model-update``).

    online: "off" (default) or "on". budget_s: seconds of gradient steps per leg (wall clock; the
    update overruns it by at most one step). lr: Adam's learning rate. horizon: later states each
    state's roll-out is compared with (1 = the next one). max_steps: a cap on the gradient steps per
    leg (``None``: the budget alone; set it for a run that must not depend on the machine's speed).
    window: the most recent states trained on (>= 2).
    """

    online: str = "off"
    budget_s: float = 5.0
    lr: float = 1e-4
    horizon: int = 1
    max_steps: int | None = None
    window: int = 10

    def record(self) -> dict:
        """The options as a JSON-able dict (a run's or campaign's configuration)."""
        return asdict(self)


def _positive_int(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, np.integer)) and v >= 1


def model_update_problem(mu: ModelUpdate | None) -> str | None:
    """One line naming a bad ``model_update`` option, or None (``None`` options: off, fine)."""
    if mu is None:
        return None
    if mu.online not in MODEL_UPDATES:
        return f"model_update.online must be one of {', '.join(MODEL_UPDATES)}, got {mu.online!r}"
    for name, v in (("budget_s", mu.budget_s), ("lr", mu.lr)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            return f"model_update.{name} must be a positive number, got {v!r}"
    if not _positive_int(mu.horizon):
        return f"model_update.horizon must be a positive integer, got {mu.horizon!r}"
    if mu.max_steps is not None and not _positive_int(mu.max_steps):
        return f"model_update.max_steps must be a positive integer or null, got {mu.max_steps!r}"
    if not _positive_int(mu.window) or mu.window < 2:
        return f"model_update.window must be an integer >= 2, got {mu.window!r}"
    return None


class OnlineUpdate:
    """One loop's online model update (module docstring): the mission's states and each leg's decision.

    ``options``: :class:`ModelUpdate` with ``online="on"``. ``record_``: the last leg's record
    (:func:`passt_mav.models.online.update_online`'s ``kept``, ``seconds``, ``steps``, ``scores``
    (nats), ``loss``, ``reason``, plus ``states`` trained on and their ``interval`` in snapshots), or
    ``None`` before the first leg; ``history_``: one record per leg; ``kept_``: legs whose update was kept.
    """

    def __init__(self, options: ModelUpdate):
        problem = model_update_problem(options)
        if problem:
            raise ModelError(problem)
        self.options = options
        self.states_: list[tuple[float, np.ndarray]] = []  # (field time, (2, R, C) float32)
        self.record_: dict | None = None
        self.history_: list[dict] = []
        self.kept_ = 0
        self._leg: int | None = None
        #: leg index -> gradient steps to take there whatever the budget (a replay repeats a run's legs)
        self.replay_steps: dict[int, int] = {}

    @classmethod
    def of(cls, options: ModelUpdate | None, predictor) -> OnlineUpdate | None:
        """An updater when ``options`` turn it on and there is a predictor, else ``None`` (options still checked)."""
        problem = model_update_problem(options)
        if problem:
            raise ModelError(problem)
        if options is None or options.online != "on" or predictor is None:
            return None
        return cls(options)

    def remember(self, state, t: float) -> None:
        """Add a reconstructed ``state`` ((2, R, C) field units, NaN on land) at field time ``t``."""
        s = np.asarray(state, np.float32)
        self.states_.append((float(t), np.where(np.isfinite(s), s, np.float32(0))))
        del self.states_[: -self.options.window]

    def training_states(self, dt: float) -> tuple[np.ndarray | None, int]:
        """``(states (T, 2, R, C), interval)``: the longest run of the most recent states evenly
        spaced by ``interval`` snapshots (``dt`` field time apart), or ``(None, 0)`` with fewer than 2."""
        if len(self.states_) < 2:
            return None, 0
        gaps = np.round(np.diff([t for t, _ in self.states_]) / float(dt)).astype(int)
        n = 1
        while n < gaps.size and gaps[-1 - n] == gaps[-1]:
            n += 1
        if gaps[-1] < 1:
            return None, 0
        return np.stack([s for _, s in self.states_[-(n + 1) :]]), int(gaps[-1])

    def consider(self, loop, leg, samples) -> None:
        """Once per leg, before ``samples`` enter the estimate: train a candidate on the states so far
        and keep it (``loop.predictor`` and ``leg.forecast`` replaced) only when it scores higher at
        ``samples`` (module docstring). ``leg``: the :class:`~passt_mav.loop.passt.LegPlan` whose
        ``forecast`` ((S+1, 2, R, C)) is the current model's from the leg's initial state."""
        if self._leg == loop.leg_index:
            return
        self._leg = loop.leg_index
        if not self.states_:  # the first leg's initial state
            self.remember(leg.forecast[0], leg.t_start)
        states, interval = self.training_states(leg.dt)
        rec = {"kept": False, "seconds": 0.0, "steps": 0, "scores": {}, "loss": [], "reason": None}
        if states is None:
            rec["reason"] = "fewer than 2 evenly spaced states so far"
        elif len(samples) < 2 or not hasattr(loop.gp, "kernels_"):
            rec["reason"] = "nothing to score the update with (no GP kernels or fewer than 2 samples)"
        else:
            rec = self._update(loop, leg, samples, states, interval)
        rec["leg"] = int(loop.leg_index)
        self.record_ = rec
        self.history_.append(rec)

    def _update(self, loop, leg, samples, states, interval) -> dict:
        """:func:`update_online` with the leg's innovation log likelihood as the score."""
        from passt_mav.fields.field import FlowField
        from passt_mav.models.online import update_online

        fc, o = leg.forecast, self.options
        steps = self.replay_steps.pop(loop.leg_index, None)
        budget_s, max_steps = (math.inf, steps) if steps is not None else (o.budget_s, o.max_steps)
        times = leg.t_start + leg.dt * np.arange(fc.shape[0])
        ts = np.clip(samples.t, times[0], times[-1])
        st = samples.t if loop.hyper != "state" else None  # as PasstLoop.update scores the leg
        loglik = loop.loglik_at(samples, samples.xy(loop.grid), st)
        forecasts: dict[int, np.ndarray] = {}

        def score(p) -> float:
            f = fc if p is loop.predictor else model_forecast(p, fc[0], fc.shape[0] - 1, loop.land)
            forecasts[id(p)] = f
            at = FlowField(np.where(np.isfinite(f), f, np.nan), loop.grid, times).interp(ts, samples.r, samples.c)
            return loglik(samples.uv - at)

        cand, rec = update_online(
            loop.predictor,
            states,
            budget_s=budget_s,
            score=score,
            lr=o.lr,
            horizon=o.horizon,
            interval=interval,
            max_steps=max_steps,
        )
        rec.update(states=int(len(states)), interval=interval)
        if rec["kept"]:
            loop.predictor, leg.forecast = cand, forecasts[id(cand)]
            self.kept_ += 1
        return rec
