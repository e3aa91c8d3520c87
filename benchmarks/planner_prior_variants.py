"""Two changes to the information planner's prior, measured in the same-loop protocol (issue 27, item 4).

    .venv/bin/python benchmarks/planner_prior_variants.py --variant ml --trials 30
    .venv/bin/python benchmarks/planner_prior_variants.py --variant forecast --trials 2

One campaign (the item-4 protocol: lockstep engine, Cholesky GP, ``bias`` on, the model's
200-snapshot background, sensor noise 0.02, samples read at each leg's end) flies three
methods over the same trials: the information planner as shipped, the information planner
with the variant's prior, and the random walk. Only the prior the planner scores paths on
differs; the reconstruction is the same GP in all three.

``--variant ml``: the planner's prior takes the kernels as the likelihood fitted them on the
last leg, before the evidence gate, with the white variance they hold above the sensor's as
the state nugget. Why try it: on the ocean default at L = 100 the gate switches the signal
kernel off (u and v both) on 60 % of the information planner's legs (trials 0-1), though the forecast's error at a
leg's end is correlated over 2-5 cells (its semivariogram at one cell is 0.5-0.6 of its
variance); the planner then sees only fresh cells, all worth the same nugget.

``--variant forecast``: the forecast-weighted reward of item 1. The variance removed is
counted over the next leg's forecast instead of the reconstruction alone: the Gram matrix
``W = F^T F`` of the prior's factor (``passt_mav.planning.information``) becomes the mean over
the leg's snapshots k = 0 .. S-1 of ``(J_k F)^T (J_k F)``, with ``J_k F`` each column of F pushed
k steps through the model from the leg's forecast end (``(M_k(x + eps f) - M_k(x)) / eps``:
``--eps 1`` is the ensemble of Bishop, Etherton & Majumdar 2001; 0.1 nearer the tangent
linear). The local part is taken to persist in place (exact for a model that moves it without
damping it). r + 1 roll-outs of S steps per trial and leg (about 5 s on this CPU for r = 140):
an experiment, not a planner for a boat.

Printed (JSON): the final-window RMSE (field units, mean of the last ``--window`` snapshots, mean
over trials) of the three methods and the ratios to the random walk.

Measured (2026-11-27, ocean default, L = 100; docs/research/2026-11-27-information-reward.md, "Two more planner priors"):
``--variant ml``: trials 0-5, 0.0310 against 0.0319 shipped; 30 trials 0.0319 against 0.0313
(random walk 0.0370); L = 50, 30 trials, 0.0415 against 0.0403; static wake, 30 trials, 0.0589 /
0.0497 against 0.0592 / 0.0495 (L = 50 / 100). ``--variant forecast``, trials 0-1: 0.0347
(eps 1) and 0.0354 (eps 0.1) against 0.0301 shipped and 0.0330 for the random walk.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _loop_patch import add_item4_arguments, item4_final_rmse, loop_patched  # noqa: E402

VARIANT_REWARD = "variance_reduction_variant"


def forecast_weighted(info, predictor, x_end, steps: int, land, eps: float):
    """A copy of ``info`` (an :class:`~passt_mav.planning.InformationModel`) whose objective counts the
    variance removed over ``steps`` snapshots of the forecast from ``x_end`` (2, R, C), see the module
    docstring. ``info`` must not have observed any cell yet (one boat: the planner conditions on its start)."""
    if info.observed.any():
        raise ValueError("forecast_weighted needs an unconditioned information model (one boat)")
    R, C = info.shape
    cols = info.F.T.reshape(-1, 2, R, C).astype(np.float32)
    base = np.where(land, 0.0, np.nan_to_num(x_end)).astype(np.float32)
    X = np.concatenate([base[None], base[None] + eps * cols])
    X[:, :, land] = 0.0
    W = info.F.T @ info.F
    if steps > 1:
        out = np.asarray(predictor.predict(X, steps - 1), dtype=np.float64)
        for k in range(steps - 1):
            JF = (out[1:, k] - out[0, k]) / eps
            JF[:, :, land] = 0.0
            JF = JF.reshape(len(cols), -1)
            W = W + JF @ JF.T
    W = W / steps
    m = copy.copy(info)
    m.W, m.M, m.P = W, W.copy(), np.eye(W.shape[0])
    m.trW = m.trPM = float(np.trace(W))
    m.prior_total = m.trW + float(info.d.sum())
    return m


@contextlib.contextmanager
def _variant_installed(variant: str, eps: float):
    """Within the block, loops whose reward is :data:`VARIANT_REWARD` plan on the variant's prior."""
    from passt_mav.loop import passt as P
    from passt_mav.reconstruction import gp as G

    orig_gate, orig_reward_map = G.GPReconstructor._evidence_gate, P.PasstLoop._reward_map

    def gate(self, gp, y, comp):
        pre = list(getattr(self, "_variant_ml", None) or [None, None])
        pre[comp] = gp.kernel_  # the fit before the evidence gate
        self._variant_ml = pre
        return orig_gate(self, gp, y, comp)

    def reward_map(self, fc, start, taken=None, avoid=None):
        if self.reward_name != VARIANT_REWARD:
            return orig_reward_map(self, fc, start, taken, avoid)
        gp = self.gp
        pre = getattr(gp, "_variant_ml", None)
        if variant != "ml" or pre is None:
            out = orig_reward_map(self, fc, start, taken, avoid)
        else:
            saved = gp.kernels_, gp.nugget_var_
            s2 = max(float(gp.noise_std) ** 2, 1e-10)
            gp.kernels_, gp.nugget_var_ = list(pre), [max(float(k.k2.noise_level) - s2, 0.0) for k in pre]
            try:
                out = orig_reward_map(self, fc, start, taken, avoid)
            finally:
                gp.kernels_, gp.nugget_var_ = saved
        if variant == "forecast":
            self.info_ = forecast_weighted(self.info_, self.predictor, fc[-1], fc.shape[0] - 1, self.land, eps)
        return out

    with loop_patched(
        VARIANT_REWARD,
        using_prior=True,
        replacements=[(G.GPReconstructor, "_evidence_gate", gate), (P.PasstLoop, "_reward_map", reward_map)],
    ):
        yield


def main(argv=None) -> int:
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.loop.campaign import load_predictor

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", choices=("ml", "forecast"), required=True)
    add_item4_arguments(ap)
    ap.add_argument(
        "--eps", type=float, default=1.0, help="--variant forecast: the perturbation's scale (1 = the prior's std)"
    )
    a = ap.parse_args(argv)
    if not a.eps > 0:
        ap.error(f"--eps must be > 0, got {a.eps}")
    field = resolve_field(a.data)
    predictor = load_predictor(a.model, field)
    methods = ["information_loop@variance_reduction", f"information_loop@{VARIANT_REWARD}", "random_loop"]
    with _variant_installed(a.variant, a.eps):
        fin = item4_final_rmse(
            field,
            predictor,
            methods=methods,
            path_length=a.path_length,
            trials=a.trials,
            seed=a.seed,
            noise=a.noise,
            window=a.window,
        )
    shipped, variant, rand = (fin[m] for m in methods)
    out = {
        "data": a.data, "model": a.model, "L": a.path_length, "trials": a.trials, "seed": a.seed,
        "variant": a.variant, "eps": a.eps if a.variant == "forecast" else None,
        "final_rmse": {"information": shipped, "information_variant": variant, "random_walk": rand},
        "information_over_random": shipped / rand, "variant_over_random": variant / rand,
    }  # fmt: skip
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
