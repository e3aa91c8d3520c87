"""What a lawnmower survey would have given over the same legs: the counterfactual of a live run.

A PASST run only tells its user how the adaptive legs did. The natural question at sea
is "would a plain survey have done as well?". For a run whose field is known (the
simulator replays it), this module re-flies the run's leg schedule offline with the
lawnmower planner: the same number of legs, the same moves per leg, the same start
cell and the same field-time span per leg (from the run's leg records), samples read
from the true field along the lawnmower path at the times a constant-speed boat would
pass each cell (``FieldSampler(sample_at="spread")``), with the mission's sensor noise
and seed, reconstructed by the GP (prior "none": the GP-only baseline of ``passt-mav
evaluate``'s ``lawnmower_gp``). The estimate is held between legs, as that baseline
does. Returns the RMSE at each leg end against the truth, to set beside the run's
``rmse_passt`` and ``rmse_model``.

It is offline arithmetic on the truth field, not a flight: link, turns and thinning do
not enter (the live legs had them). That is stated wherever its figure is shown.
"""

from __future__ import annotations

import numpy as np

__all__ = ["lawnmower_counterfactual"]


def lawnmower_counterfactual(field, legs: list[dict], *, path_length: int, start_cell, noise_std: float = 0.02, seed: int = 0, gp_seed: int = 0) -> list[float | None]:
    """RMSE (field units) of a lawnmower+GP survey at the end of each of ``legs``.

    ``legs``: the run's leg records (``t_start``, ``t_end`` in field time units, in
    order); ``path_length``: moves per leg; ``start_cell``: ``(row, col)`` of the first
    leg; ``noise_std``: sensor noise (field units). ``None`` where a leg has no end time
    or the truth is not defined there (outside the field's time span).
    """
    from passt_mav.controller import rmse
    from passt_mav.passt import FieldSampler, PasstLoop
    from passt_mav.analysis.report import truth_at

    land = field.land_mask
    loop = PasstLoop(None, field.grid, planner="lawnmower", path_length=int(path_length), prior="none", land=land, gp_kw={"seed": gp_seed}, seed=seed)
    sampler = FieldSampler(field, noise_std=noise_std, seed=seed + 7919, steps_per_leg=1, sample_at="spread")
    state = np.zeros((2,) + field.grid.shape, np.float32)  # no knowledge before the first samples
    state[:, land] = np.nan
    start = tuple(int(x) for x in start_cell)
    out: list[float | None] = []
    t_lo, t_hi = float(field.times[0]), float(field.times[-1])
    for leg in legs:
        t0, t1 = leg.get("t_start"), leg.get("t_end")
        if t0 is None or t1 is None or not (t_lo <= t0 < t1 <= t_hi):
            out.append(None)
            continue
        steps = max(1, int(round((t1 - t0) / field.dt)))
        plan = loop.plan_leg(state, start, float(t0), field.dt, steps=steps)
        sampler.steps_per_leg = (t1 - t0) / field.dt
        samples = sampler.sample_path(plan.path, float(t0))
        state = loop.update(plan, samples)
        out.append(rmse(state, truth_at(field, float(t1))))
        start = tuple(int(x) for x in plan.path[-1])
    return out
