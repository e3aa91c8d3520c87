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

from passt_mav.loop.threads import single_threaded

__all__ = ["fleet_rounds", "lawnmower_counterfactual", "same_loop_counterfactual", "same_loop_counterfactuals"]


@single_threaded
def lawnmower_counterfactual(
    field, legs: list[dict], *, path_length: int, start_cell, noise_std: float = 0.02, seed: int = 0, gp_seed: int = 0
) -> list[float | None]:
    """RMSE (field units) of a lawnmower+GP survey at the end of each of ``legs``.

    ``legs``: the run's leg records (``t_start``, ``t_end`` in field time units, in
    order); ``path_length``: moves per leg; ``start_cell``: ``(row, col)`` of the first
    leg; ``noise_std``: sensor noise (field units). ``None`` where a leg has no end time
    or the truth is not defined there (outside the field's time span).
    """
    from passt_mav.loop.passt import FieldSampler, PasstLoop

    land = field.land_mask
    loop = PasstLoop(
        None,
        field.grid,
        planner="lawnmower",
        path_length=int(path_length),
        prior="none",
        land=land,
        gp_kw={"seed": gp_seed},
        seed=seed,
    )
    sampler = FieldSampler(field, noise_std=noise_std, seed=seed + 7919, steps_per_leg=1, sample_at="spread")
    state = np.zeros((2,) + field.grid.shape, np.float32)  # no knowledge before the first samples
    state[:, land] = np.nan
    return _fly_legs(loop, sampler, field, legs, state, float(field.times[0]), start_cell)


def _fly_legs(loop, sampler, field, legs: list[dict], state, t_state: float, start_cell) -> list[float | None]:
    """Fly ``legs`` (their field-time spans) offline with ``loop`` from ``state`` at ``t_state``, one
    boat from ``start_cell``: :func:`_fly_rounds` with one boat."""
    return _fly_rounds(loop, sampler, field, _leg_spans(legs), state, t_state, [start_cell])


def _leg_spans(legs: list[dict]) -> list[tuple[float | None, float | None]]:
    """(t_start, t_end) of each leg record (field time; None where not recorded)."""
    return [(x.get("t_start"), x.get("t_end")) for x in legs]


def _fly_rounds(loop, sampler, field, spans, state, t_state: float, starts) -> list[float | None]:
    """Fly leg intervals ``spans`` ((t_start, t_end) in field time, s) offline with ``loop`` from
    ``state`` at ``t_state``, one boat per cell of ``starts``: per interval, forecast to its start
    (a loop without a model holds the state), plan boat 0, then each other boat under the fleet's
    keep-out rule (:func:`passt_mav.loop.engine.plan_after`), sample the truth along every path,
    one GP update with all the samples. The RMSE vs the truth at each interval's end (None where
    it has no times or lies outside the field)."""
    from passt_mav.loop.engine import plan_after
    from passt_mav.loop.measurement import rmse, truth_at
    from passt_mav.loop.passt import Samples

    starts = [tuple(int(x) for x in c) for c in starts]
    out: list[float | None] = []
    t_lo, t_hi = float(field.times[0]), float(field.times[-1])
    for t0, t1 in spans:
        if t0 is None or t1 is None or not (t_lo <= t0 < t1 <= t_hi):
            out.append(None)
            continue
        k = max(0, int(round((float(t0) - t_state) / field.dt)))
        if k and loop.predictor is not None:
            state = loop.forecast(state, k)[-1]
        steps = max(1, int(round((t1 - t0) / field.dt)))
        plans = [loop.plan_leg(state, starts[0], float(t0), field.dt, steps=steps)]
        for n in range(1, len(starts)):
            plans.append(plan_after(loop, starts[n], float(t0), field.dt, steps, plans, f"boat {n}"))
        sampler.steps_per_leg = (t1 - t0) / field.dt
        parts = [sampler.sample_path(p.path, float(t0)) for p in plans]
        samples = Samples.concat(parts)
        state = loop.update(plans[0], samples)
        t_state = float(t0) + steps * field.dt
        out.append(rmse(state, truth_at(field, float(t1))))
        starts = [tuple(int(x) for x in p.path[-1]) for p in plans]
    return out


def fleet_rounds(legs: list[dict]) -> list[tuple[float | None, float | None]]:
    """A fleet run's legs as synchronous leg intervals, for an offline counterfactual: interval j
    runs from the earliest start of the boats' j-th legs to the latest end of them (field time, s;
    ``boat`` names a leg's boat), and starts no earlier than interval j-1 ended (live, the boats'
    legs drift apart; offline they leave together and move in step). ``(None, None)`` where no
    boat's j-th leg has both times."""
    per: dict[int, list[dict]] = {}
    for leg in legs:
        per.setdefault(int(leg.get("boat", 0)), []).append(leg)
    out: list[tuple[float | None, float | None]] = []
    t_prev = None
    for j in range(max((len(v) for v in per.values()), default=0)):
        nth = [
            v[j]
            for v in per.values()
            if len(v) > j and v[j].get("t_start") is not None and v[j].get("t_end") is not None
        ]
        if not nth:
            out.append((None, None))
            continue
        t0 = min(float(x["t_start"]) for x in nth)
        t1 = max(float(x["t_end"]) for x in nth)
        t0 = t0 if t_prev is None else max(t0, t_prev)
        out.append((t0, t1) if t1 > t0 else (None, None))
        t_prev = t1
    return out


def same_loop_counterfactual(
    config, field, predictor, legs: list[dict], *, planner: str = "random", start_cell=None, start_cells=None
) -> list[float | None]:
    """RMSE (field units) at the end of each of ``legs`` of the run's OWN loop with another planner.

    The same model (``predictor``), the same GP (the mission's options, its background and
    seeds: :func:`passt_mav.loop.legstep.build_loop`), the same legs (field-time spans, moves per
    leg, first start cell), only the path differs: ``planner`` (default the random walk, the
    baseline an adaptive planner must beat). Starts from the truth at the mission's ``t0`` as
    the run does, forecasts each state to the next leg's start as the run does between legs,
    and samples the true field along the path at the times a constant-speed boat passes each
    cell, with the mission's sensor noise and seed. Offline arithmetic, like
    :func:`lawnmower_counterfactual`: link, turns and thinning do not enter.

    A fleet (``start_cells``: each boat's first start cell (row, col)): the boats fly
    synchronous leg intervals (:func:`fleet_rounds`), boat 0 planned first and the others in
    turn under the keep-out rule, every boat's samples in one GP update per interval, as the
    offline fleet engine does (:mod:`passt_mav.loop.engine`); one RMSE per interval. The live
    fleet's legs are asynchronous (each boat plans from the newest shared state), so this is the
    same model + GP loop over the same time span, not the run's exact schedule.
    """
    return same_loop_counterfactuals(
        config,
        field,
        predictor,
        legs,
        planner=planner,
        seeds=[config.seeds.planner],
        start_cell=start_cell,
        start_cells=start_cells,
    )[0]


@single_threaded
def same_loop_counterfactuals(
    config, field, predictor, legs: list[dict], *, seeds, planner: str = "random", start_cell=None, start_cells=None
) -> list[list[float | None]]:
    """:func:`same_loop_counterfactual` once per planner seed in ``seeds`` (the mission's
    ``seeds.planner`` replaced; sensor noise and GP seeds stay the run's): one random walk is one
    draw from a wide distribution, so a run is set beside several. The model background (a roll-out
    from the same initial state, the same for every seed) is computed once and shared."""
    from passt_mav.loop.legstep import build_loop
    from passt_mav.loop.passt import FieldSampler

    land = field.land_mask
    t_state = float(field.times[config.t0])
    if start_cells is not None:  # a fleet: its legs as synchronous intervals, all boats' samples in one update
        spans, starts = fleet_rounds(legs), start_cells
    else:
        spans = _leg_spans(legs)
        starts = [start_cell or config.start_cell or (field.grid.rows // 2, field.grid.cols // 2)]
    out, first = [], None
    for seed in seeds:
        cfg = config.model_copy(
            update={
                "planner": config.planner.model_copy(update={"name": planner, "options": {}}),
                "seeds": config.seeds.model_copy(update={"planner": int(seed)}),
            }
        )
        loop = build_loop(cfg, predictor, field.grid, land=land)
        if first is not None and not first._background_pending:
            loop.set_background(first.gp.background)
        first = first or loop
        sampler = FieldSampler(
            field,
            noise_std=config.sensors.noise_std,
            seed=config.seeds.sensor + 7919,
            steps_per_leg=1,
            sample_at="spread",
        )
        state = field.state_at(config.t0)  # gaps that come and go: FlowField.state_at
        state[:, land] = np.nan
        out.append(_fly_rounds(loop, sampler, field, spans, state, t_state, starts))
    return out
