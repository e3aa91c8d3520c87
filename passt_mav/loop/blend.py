"""A prior that knows when it is wrong: the weights of the candidate priors of a PASST loop.

Each leg's samples are evidence about the whole-field forecasts that could have been the leg's
background (:data:`PRIOR_CANDIDATES`): the model restarted from the last estimate (``model``), the model
alone from the first leg's initial state (``open_loop``, never re-initialised, so what no leg could see
is never lost) and persistence (the leg's initial state held). :class:`PasstLoop
<passt_mav.loop.passt.PasstLoop>` scores each by the innovation log likelihood of its residual at the
samples (nats) and hands the scores to :meth:`PriorBlend.observe`; the weights it keeps say which
candidate, or which mixture, is the leg's prior and carries the estimate between legs
(:meth:`PriorBlend.mix`).

Modes (``PasstLoop(prior_blend=...)``):

* ``"off"``: the model restarted from the last estimate is the prior, always;
* ``"bma"``: Bayesian model averaging (Hoeting et al. 1999, Statist. Sci. 14) with a forgetting factor
  towards the uniform (``lw <- forgetting * lw + ll``; Raftery, Karny & Ettler 2010, Technometrics 52),
  the candidates mixed by their weights;
* ``"select"``: forgetting towards the start weights (``lw <- forgetting * lw + (1 - forgetting) * log
  p0 + ll``) and the most probable candidate alone (the model on a tie), so a right model is never mixed
  with a share of a worse one.

A ``share`` ("fixed share", Herbster & Warmuth 1998, Machine Learning 32) mixes the weights with
``share`` of the uniform before each leg, so no candidate falls below ``share / K`` and one leg where a
good model misses costs at most about ln(K / share) nats to win back; with a share the blend starts on
the model alone.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["PRIOR_BLENDS", "PRIOR_CANDIDATES", "PRIOR_START_WEIGHTS", "PriorBlend", "prior_weights", "model_forecast"]

#: the priors a ``prior_blend="bma"`` / ``"select"`` loop weighs, each a whole-field forecast: the model
#: restarted from the last estimate, the model alone from the first leg's initial state, persistence
#: (the leg's initial state held)
PRIOR_CANDIDATES = ("model", "open_loop", "persistence")
#: their weights before any leg: the model trusted (its own validation said it beats persistence)
PRIOR_START_WEIGHTS = (0.9, 0.1, 0.1)
#: values of ``PasstLoop(prior_blend=...)``
PRIOR_BLENDS = ("off", "bma", "select")


def prior_weights(share: float) -> np.ndarray:
    """The weights ``"select"``'s forgetting factor pulls :data:`PRIOR_CANDIDATES` back to where legs bring
    no evidence: :data:`PRIOR_START_WEIGHTS`, or with a ``share`` the model alone mixed with the share
    (``1 - share + share / K`` against ``share / K``; finite, unlike the start)."""
    if share <= 0:
        return np.array(PRIOR_START_WEIGHTS, np.float64)
    return (1.0 - share) * np.eye(len(PRIOR_CANDIDATES))[0] + share / len(PRIOR_CANDIDATES)


class PriorBlend:
    """The candidate priors' log weights, leg by leg (module docstring).

    Args:
        mode: ``"off"``, ``"bma"`` or ``"select"``.
        forgetting: forgetting factor in [0, 1] (memory of about 1 / (1 - forgetting) legs).
        share: fixed share in [0, 1] (0 = off).
    """

    def __init__(self, mode: str = "off", forgetting: float = 1.0, share: float = 0.0):
        self.mode = mode
        self.forgetting = float(forgetting)
        self.share = float(share)
        #: what the forgetting factor returns the weights to without evidence (:func:`prior_weights`)
        self.log_prior = np.log(prior_weights(self.share))
        # the start: those weights, but with a share the model alone (the share's first mixing gives the
        # others share / K: the share is the only doubt a trusted model starts with); log 0 = -inf, mixed before use
        with np.errstate(divide="ignore"):
            self.log_weights = np.log(np.eye(len(PRIOR_CANDIDATES))[0]) if self.share > 0 else self.log_prior.copy()
        #: one record per leg observed: its log likelihoods (nats), the weights the prior used, and with
        #: ``"select"`` the posterior behind them
        self.history: list[dict] = []

    def weights(self) -> np.ndarray:
        """Current weights of :data:`PRIOR_CANDIDATES` (sum 1)."""
        lw = self.log_weights - self.log_weights.max()
        w = np.exp(lw)
        return w / w.sum()

    def mixing_weights(self) -> np.ndarray:
        """The weights the prior mixes :data:`PRIOR_CANDIDATES` with: :meth:`weights` (``"bma"``), or all
        on the most probable one (``"select"``; the model on a tie)."""
        w = self.weights()
        if self.mode != "select":
            return w
        one = np.zeros_like(w)
        one[int(np.argmax(w))] = 1.0
        return one

    @staticmethod
    def candidates(fc: np.ndarray, open_fc: np.ndarray) -> list[np.ndarray]:
        """The candidate prior trajectories of :data:`PRIOR_CANDIDATES` (each (S+1, 2, R, C), field units):
        the loop's forecast ``fc``, the model alone over the same times ``open_fc`` and persistence of
        ``fc``'s first snapshot."""
        return [fc, np.asarray(open_fc, np.float64), np.repeat(fc[:1], fc.shape[0], axis=0)]

    def mix(self, fc: np.ndarray, open_fc: Callable[[], np.ndarray]) -> np.ndarray:
        """The estimate a model forecast ``fc`` ((S+1, 2, R, C)) stands for: ``fc`` itself, or the
        candidates' mixture under :meth:`mixing_weights` (float32); ``open_fc()`` gives the model alone over
        the same times (called only when it is needed)."""
        if self.mode == "off":
            return fc
        w = self.mixing_weights()
        if np.count_nonzero(w) == 1 and w[0] == 1.0:
            return fc
        cands = self.candidates(np.asarray(fc, np.float64), open_fc())
        return sum(float(wk) * ck for wk, ck in zip(w, cands) if wk).astype(np.float32)

    def observe(self, leg: int, loglik: np.ndarray) -> np.ndarray:
        """Leg ``leg``'s evidence: the innovation log likelihood (nats) of each of :data:`PRIOR_CANDIDATES`
        at its samples. Updates the weights (share, forgetting, evidence), records the leg and returns the
        mixing weights the leg's prior uses."""
        ll = np.asarray(loglik, np.float64)
        if self.share > 0:  # fixed share: every candidate keeps share / K of the weight
            w0 = self.weights()
            self.log_weights = np.log((1.0 - self.share) * w0 + self.share / w0.size)
        # forgetting: "select" discounts old evidence towards the start weights (a decision whose null is the
        # trusted model, which noise must not erode), "bma" towards the uniform (Raftery et al.'s averaging)
        back = self.log_prior if self.mode == "select" else 0.0
        self.log_weights = self.forgetting * self.log_weights + (1.0 - self.forgetting) * back + ll
        w = self.mixing_weights()
        self.history.append(
            {
                "leg": int(leg),
                "log_likelihood": {k: float(v) for k, v in zip(PRIOR_CANDIDATES, ll)},
                "weights": {k: float(v) for k, v in zip(PRIOR_CANDIDATES, w)},
                **(
                    {"posterior": dict(zip(PRIOR_CANDIDATES, map(float, self.weights())))}
                    if self.mode == "select"
                    else {}
                ),
            }
        )
        return w


def model_forecast(predictor, state, steps: int, land) -> np.ndarray:
    """(steps+1, 2, R, C) float32: ``state`` ((2, R, C) field units) then ``predictor``'s ``steps``
    predictions (``None``: the state held), land (``(R, C)`` bool) filled with 0 at the input, NaN in the output."""
    s = np.asarray(state, dtype=np.float32)
    if predictor is None:
        pred = np.repeat(s[None], steps, axis=0)
    else:
        pred = np.asarray(predictor.predict(np.where(land, np.float32(0), s), steps), dtype=np.float32)
    out = np.concatenate([s[None], pred], axis=0)
    out[:, :, land] = np.nan
    return out
