"""The offline PASST engine: B trials x N boats, advanced leg interval by leg interval, on ground truth.

One step (:class:`OfflineStep`) serves every offline run: one trial of one boat
(:func:`run_offline`), one trial of a fleet (:func:`run_offline_fleet`) and a batch of
one-boat trials in lockstep (:func:`run_offline_lockstep`, one batched predictor call and
one batched planning call per leg). :func:`run_trials` is the one entry point they share.
Each leg interval, per trial: the forecast from the trial's state, boat 0's plan, the other
boats planned in turn under the fleet's keep-out rule, every boat's path sampled by
:class:`~passt_mav.loop.passt.FieldSampler`, one GP update of the trial's state
(:meth:`PasstLoop.update <passt_mav.loop.passt.PasstLoop.update>`, the same call the live
:class:`~passt_mav.loop.legstep.LegStep` makes).

The keep-out rule (:func:`keep_out`, :func:`plan_keeping_out`) is the live fleet's too
(:class:`passt_mav.loop.legstep.FleetStep`): a boat first plans outside every cell the other
boats' paths hold this leg; boxed in, it plans with those cells' reward zeroed and only keeps
out of the cells another boat is at when it gets there (within one move's duration; a boat
whose path has ended holds its last cell), repaired over at most :data:`KEEP_OUT_ROUNDS` plans.
Offline the boats leave together and move in step, so times are counted in moves
(:func:`same_step_clashes`); live they come from the boats' speeds and start times.

Time: steps are the predictor's snapshots (``field.dt`` apart); ``t0`` a snapshot index.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from passt_mav.errors import PlannerError
from passt_mav.loop.passt import FieldSampler, LegPlan, LoopOptions, OfflineResult, Samples, _background_or_none

__all__ = [
    "KEEP_OUT_ROUNDS",
    "OfflineStep",
    "keep_out",
    "plan_after",
    "plan_keeping_out",
    "same_step_clashes",
    "run_trials",
    "run_offline",
    "run_offline_fleet",
    "run_offline_lockstep",
]

#: plans a boat may make to repair clashes with the other boats before giving up (PlannerError)
KEEP_OUT_ROUNDS = 20


# -- the fleet's keep-out rule -------------------------------------------------------------------
def keep_out(path, times, others, shape) -> np.ndarray:
    """(R, C) bool: the cells of ``path`` ((L+1, 2) int (row, col)) after its start that another
    boat is at when this one gets there.

    ``times``: (L+1,) when this boat reaches each cell; ``others``: ``(path, times, tol)`` of each
    other boat, ``tol`` how close in time two boats count as meeting (one move's duration of the
    slower). Another boat is at a cell within ``tol`` of its reaching it, and at its last cell
    from then on (it waits there). Times in any one unit: field time live, moves offline.
    """
    out = np.zeros(shape, bool)
    path = np.asarray(path, int)
    mine = np.asarray(times, float)
    for o_path, o_times, tol in others:
        o_path, o_times = np.asarray(o_path, int), np.asarray(o_times, float)
        for j in range(1, len(path)):
            same = (o_path == path[j]).all(axis=1)
            if (same & (np.abs(o_times - mine[j]) < tol)).any() or (same[-1] and mine[j] >= o_times[-1]):
                out[path[j, 0], path[j, 1]] = True
    return out


def same_step_clashes(path, others, shape) -> np.ndarray:
    """:func:`keep_out` for boats that leave together and move in step (offline): times in moves,
    one move's tolerance, so a cell clashes when another boat enters it at the same move index or
    stands on it after its path ended. ``others``: the other boats' paths ((L+1, 2) int)."""
    moves = [(o, np.arange(len(o)), 1.0) for o in others]
    return keep_out(path, np.arange(len(path)), moves, shape)


def plan_keeping_out(plan: Callable, taken: np.ndarray, conflicts: Callable, what: str):
    """One boat's plan under the fleet's keep-out rule (module docstring).

    ``plan(taken=, avoid=)``: the boat's planner call ((R, C) bool masks, see
    :meth:`passt_mav.loop.passt.PasstLoop.plan_leg`); ``taken``: the cells the other boats' paths hold,
    the boat's own start cell already cleared; ``conflicts(planned)``: (R, C) bool of
    :func:`keep_out`. Raises :class:`PlannerError` naming ``what`` when no path keeps clear.
    """
    try:  # first choice: none of the cells the others hold this leg
        planned = plan(taken=None, avoid=taken)
    except PlannerError:  # boxed in by their paths: collect nothing twice, cross them at other times only
        planned = None
    avoid = np.zeros_like(taken)
    for _ in range(KEEP_OUT_ROUNDS):  # each round forbids the cells the last plan clashed on
        clash = None if planned is None else conflicts(planned)
        if clash is not None and not clash.any():
            return planned
        if clash is not None:
            avoid |= clash
        planned = plan(taken=taken, avoid=avoid)
    if conflicts(planned).any():
        raise PlannerError(f"{what} finds no path that keeps out of the other boats' way")
    return planned


def plan_after(loop, start, t_start: float, dt: float, steps: int, earlier: list[LegPlan], what: str) -> LegPlan:
    """A boat's leg planned by ``loop`` from ``start`` after the boats of ``earlier`` (their plans this
    leg interval, the first one's forecast shared), under the keep-out rule with offline timing
    (boats leave together, move in step: :func:`same_step_clashes`). ``t_start``/``dt``: field time
    (s); ``steps``: snapshots the leg spans; ``what`` names the boat in the error."""
    start = tuple(int(x) for x in start)
    shape = loop.grid.shape
    taken = np.zeros(shape, bool)
    for p in earlier:
        taken[p.path[:, 0], p.path[:, 1]] = True
    taken[start] = False

    def plan(taken=None, avoid=None):
        return loop.plan_leg(
            None, start, t_start, dt, steps=steps, forecast=earlier[0].forecast, taken=taken, avoid=avoid
        )

    return plan_keeping_out(plan, taken, lambda q: same_step_clashes(q.path, [p.path for p in earlier], shape), what)


# -- batched forecast and planning ------------------------------------------------------------------
def _batch_forecast(predictor, states: np.ndarray, steps: int, land: np.ndarray) -> np.ndarray:
    """(B, steps+1, 2, R, C) float32: each state then its ``steps`` predictions, NaN on land.

    One predictor call for the whole batch when the predictor takes ``(B, 2, R, C)``
    (every :class:`passt_mav.models.base.Predictor` does); otherwise one call per state.
    Per row the same arithmetic as :meth:`PasstLoop.forecast`.
    """
    s = np.asarray(states, dtype=np.float32)
    B = s.shape[0]
    if predictor is None:
        pred = np.repeat(s[:, None], steps, axis=1)
    else:
        x = np.where(land, np.float32(0), s)
        pred = None
        if getattr(predictor, "_predict_batch", None) is not None:
            pred = np.asarray(predictor.predict(x, steps), dtype=np.float32)
        if pred is None or pred.shape != (B, steps) + s.shape[1:]:
            pred = np.stack([np.asarray(predictor.predict(x[b], steps), dtype=np.float32) for b in range(B)])
    out = np.concatenate([s[:, None], pred], axis=1)
    out[:, :, :, land] = np.nan
    return out


def _plan_batch(loops: list, starts, t_start: float, dt: float, S: int, fcs) -> list[LegPlan]:
    """``[loops[b].plan_leg(..., forecast=fcs[b]) for b]`` with the planning batched when it can be.

    Loops whose planners are all of one class with the same options and have a
    ``plan_many`` (policy gradient, greedy) plan in one call of it (same paths as one call
    each; the ``plan`` timing is the batch's time / B); any other planner plans loop by
    loop.
    """
    p0 = loops[0].planner
    same = hasattr(p0, "plan_many") and all(
        type(lp.planner) is type(p0) and vars(lp.planner) == vars(p0) and lp.path_length == loops[0].path_length
        for lp in loops
    )
    if not same or len(loops) == 1:
        return [lp.plan_leg(None, st, t_start, dt, steps=S, forecast=fc) for lp, st, fc in zip(loops, starts, fcs)]
    B = len(loops)
    tr = time.perf_counter()
    qm = [lp._reward_map(fc, st) for lp, st, fc in zip(loops, starts, fcs)]
    t_rew = (time.perf_counter() - tr) / B
    tp = time.perf_counter()
    paths = p0.plan_many(
        [q for q, _ in qm], starts, loops[0].path_length, [lp._plan_seed() for lp in loops], [m for _, m in qm]
    )
    t_plan = (time.perf_counter() - tp) / B
    return [
        LegPlan(
            path=path,
            reward=q,
            forecast=fc,
            t_start=float(t_start),
            dt=float(dt),
            steps=S,
            timings={"predict": 0.0, "reward": t_rew, "plan": t_plan},
        )
        for path, (q, _), fc in zip(paths, qm, fcs)
    ]


# -- the step -----------------------------------------------------------------------------------------
class OfflineStep:
    """B trials of N boats each on one ground-truth field, advanced one leg interval per :meth:`advance`.

    Args:
        field: the truth (:class:`~passt_mav.fields.field.FlowField`); predictor: the model or ``None``
            (the GP-only "hold" loops).
        options: the loops' :class:`~passt_mav.loop.passt.LoopOptions`.
        starts: per trial, its boats' start cells ((row, col), distinct within a trial).
        seeds: per trial: planner seeds ``seed + leg``, sensor noise from ``seed + 7919``.
        t0: start snapshot index; noise_std: sensor noise (field units); sample_at: see
            :class:`~passt_mav.loop.passt.FieldSampler`; initial_state: (2, R, C), default the truth at t0.
        batched: the trials' forecasts in one predictor call and their boat-0 plans in one planning
            call per leg (lockstep), else one call per trial.
        calibration: compute every leg's posterior std and record, in the leg's record, the estimate
            scored against the truth (``calibration``: :meth:`_calibration`); the std's solve costs GP time.
    """

    def __init__(
        self,
        field,
        predictor,
        options: LoopOptions,
        *,
        starts,
        seeds,
        t0: int = 0,
        noise_std: float = 0.0,
        sample_at: str = "end",
        initial_state=None,
        batched: bool = False,
        calibration: bool = False,
    ):
        self.field, self.predictor, self.options, self.t0, self.batched = field, predictor, options, int(t0), batched
        self.calibration = bool(calibration)
        self.land = field.land_mask
        self.starts = [[tuple(int(x) for x in c) for c in cells] for cells in starts]
        for cells in self.starts:
            if len(set(cells)) != len(cells):  # two boats on one cell from the start
                raise PlannerError(f"fleet start cells must differ, got {cells}")
        self.loops = [options.loop(predictor, field.grid, land=self.land, seed=int(sd)) for sd in seeds]
        for lp in self.loops:  # calibration: every leg's posterior std, scored against the truth
            lp.keep_std = lp.keep_std or self.calibration
        if batched and self.loops[0].online is not None:  # one batched predictor call needs one predictor
            raise PlannerError("an online model update gives each trial its own model: use the serial engine")
        self.samplers = [
            FieldSampler(
                field,
                noise_std=noise_std,
                seed=int(sd) + 7919,
                steps_per_leg=options.steps_per_leg,
                sample_at=sample_at,
            )
            for sd in seeds
        ]
        state0 = np.array(field.state_at(t0) if initial_state is None else initial_state, dtype=np.float32)
        state0[:, self.land] = np.nan
        self.state0 = state0
        self.states = np.repeat(state0[None], len(self.loops), axis=0)

    def share_setup(self, n_steps: int, cache: dict) -> None:
        """What every trial shares, computed once (and once per ``cache`` dict across calls): the GP
        kernel fitted on the initial state (``hyper="state"``; key = GP options + state bytes) and the
        model background's modes (key = predictor object, length, state) and the model alone from the initial
        state (the guard's and the prior blend's open loop; key = predictor object, state)."""
        loops, state0, opts = self.loops, self.state0, self.options
        if opts.hyper == "state":  # a loop would fit on its first leg's forecast[0] = this state
            key = (repr(sorted((opts.gp_kw or {}).items())), opts.prior, state0.tobytes())
            if key not in cache:
                loops[0].gp.fit_field(state0)
                cache[key] = (loops[0].gp.kernels_, loops[0].gp.cell_m_, loops[0].gp.n_inputs_)
            for lp in loops:
                lp.gp.kernels_, lp.gp.cell_m_, lp.gp.n_inputs_ = cache[key]
        if loops[0].background_steps and n_steps >= opts.steps_per_leg:
            bkey = ("background", id(self.predictor), loops[0].background_steps, state0.tobytes())
            if bkey not in cache or cache[bkey][0] is not self.predictor:
                modes = _background_or_none(self.predictor, state0, loops[0].background_steps, self.land)
                cache[bkey] = (self.predictor, modes)
            for lp in loops:
                lp.set_background(cache[bkey][1])
        if self.predictor is not None and (loops[0].guard == "on" or loops[0].prior_blend != "off"):
            okey = ("open_loop", id(self.predictor), state0.tobytes())
            if okey not in cache or cache[okey][0] is not self.predictor or len(cache[okey][1]) <= n_steps:
                cache[okey] = (self.predictor, loops[0].model_alone(state0, max(int(n_steps), 1)))
            t0 = float(self.field.times[self.t0])
            for lp in loops:
                lp.set_open_loop(cache[okey][1], t0, float(self.field.dt))

    def _forecasts(self, S: int) -> tuple[list[np.ndarray], list[float]]:
        """Each trial's (S+1, 2, R, C) forecast from its state, and the seconds each cost."""
        if self.batched:
            tp = time.perf_counter()
            fcs = _batch_forecast(self.predictor, self.states, max(S, 1), self.land)
            return list(fcs), [(time.perf_counter() - tp) / len(self.loops)] * len(self.loops)
        fcs, secs = [], []
        for lp, st in zip(self.loops, self.states):
            tp = time.perf_counter()
            fcs.append(lp.forecast(st, max(S, 1)))
            secs.append(time.perf_counter() - tp)
        return fcs, secs

    def _plan_boat(self, b: int, n: int, t_start: float, S: int, earlier: list[LegPlan]) -> LegPlan:
        """Boat ``n`` (> 0) of trial ``b`` planned after the boats before it, under the keep-out rule."""
        return plan_after(self.loops[b], self.starts[b][n], t_start, self.field.dt, S, earlier, f"boat {n}")

    def advance(self, k: int, S: int) -> list[tuple[dict, np.ndarray]]:
        """The leg interval of ``S`` snapshots from step ``k``: per trial (the leg's record, the estimate
        at steps k+1..k+S (S, 2, R, C) float32); ``states`` then hold the trials' states at k+S."""
        from passt_mav.planning import path_reward

        t_start, dt = self.field.times[self.t0] + k * self.field.dt, self.field.dt
        fcs, secs = self._forecasts(S)
        starts0 = [cells[0] for cells in self.starts]
        if self.batched:
            firsts = _plan_batch(self.loops, starts0, t_start, dt, S, fcs)
        else:
            firsts = [
                lp.plan_leg(None, st, t_start, dt, steps=S, forecast=fc) for lp, st, fc in zip(self.loops, starts0, fcs)
            ]
        out = []
        for b, lp in enumerate(self.loops):
            firsts[b].timings["predict"] = secs[b]
            plans = [firsts[b]]
            for n in range(1, len(self.starts[b])):
                try:
                    plans.append(self._plan_boat(b, n, t_start, S, plans))
                except PlannerError as exc:
                    raise PlannerError(f"leg at step {k}: {exc}") from None
            parts = [self.samplers[b].sample_path(p.path, p.t_start) for p in plans]
            samples = Samples.concat(parts)
            if lp.online is not None:  # before the estimate between legs is taken from the leg's forecast
                lp.online.consider(lp, plans[0], samples)
            # before the update moves the blend's weights
            est = np.array(lp.blend(plans[0].forecast, plans[0].t_start, plans[0].dt)[1 : S + 1])
            self.states[b] = lp.update(plans[0], samples) if S == self.options.steps_per_leg else est[S - 1]
            est[S - 1] = self.states[b]
            out.append(
                (
                    {
                        "step": k,
                        "path": plans[0].path.tolist(),
                        "paths": [p.path.tolist() for p in plans],
                        "timings": {
                            key: float(sum(p.timings.get(key, 0.0) for p in plans))
                            for key in ("predict", "reward", "plan", "gp")
                        },
                        "reward_collected": float(sum(path_reward(p.reward, p.path) for p in plans)),
                        "n_samples": len(samples),
                        **({} if lp.online is None else {"model_update": lp.online.record_}),
                        **self._calibration(lp, k + S, S),
                    },
                    est,
                )
            )
            self.starts[b] = [tuple(int(x) for x in p.path[-1]) for p in plans]
        return out

    def _calibration(self, lp, step: int, S: int) -> dict:
        """``{"calibration": ...}``: the leg's estimate (the state at ``step``) and its posterior std scored
        against the truth there (:func:`passt_mav.models.calibration.calibration`: ``coverage95``, ``nlpd``,
        ``z_rms``, ``n``, ``reliability``), with ``step``; empty without ``calibration`` or a std (a leg
        cut short by the run's end keeps its forecast)."""
        if not self.calibration or lp.std is None or S != self.options.steps_per_leg:
            return {}
        from passt_mav.models.calibration import calibration

        idx = self.t0 + int(step)
        if idx >= self.field.n_times:
            return {}
        cal = calibration(self.states[self.loops.index(lp)], lp.std, self.field.data[idx])
        return {} if cal is None else {"calibration": {"step": int(step), **cal}}


# -- the one entry point ----------------------------------------------------------------------------
def run_trials(
    field,
    predictor,
    options: LoopOptions,
    *,
    starts,
    seeds,
    t0: int = 0,
    n_steps: int,
    noise_std: float = 0.0,
    sample_at: str = "end",
    initial_state=None,
    batched: bool = False,
    kernel_cache: dict | None = None,
    calibration: bool = False,
) -> list[OfflineResult]:
    """PASST offline on ground truth ``field`` from snapshot ``t0`` for ``n_steps`` steps (clipped to the
    data): one :class:`~passt_mav.loop.passt.OfflineResult` per trial (``starts[b]``: its boats' start cells,
    ``seeds[b]``); arguments as :class:`OfflineStep`. Batched, what the trials share is computed once
    (:meth:`OfflineStep.share_setup`, once per ``kernel_cache`` dict across calls). Deterministic given
    the seeds."""
    if not (0 <= t0 < field.n_times - 1):
        raise PlannerError(f"start snapshot t0={t0} must lie in [0, {field.n_times - 2}]")
    if len(starts) != len(seeds) or not len(seeds):
        raise PlannerError("the offline engine needs one seed per trial's start cells (at least one trial)")
    n_steps = int(min(n_steps, field.n_times - 1 - t0))
    step = OfflineStep(
        field,
        predictor,
        options,
        starts=starts,
        seeds=seeds,
        t0=t0,
        noise_std=noise_std,
        sample_at=sample_at,
        initial_state=initial_state,
        batched=batched,
        calibration=calibration,
    )
    if batched:
        step.share_setup(n_steps, kernel_cache if kernel_cache is not None else {})
    est = np.empty((len(seeds), n_steps + 1, 2) + field.grid.shape, np.float32)
    est[:, 0] = step.state0
    legs: list[list[dict]] = [[] for _ in seeds]
    k = 0
    while k < n_steps:
        S = min(options.steps_per_leg, n_steps - k)
        for b, (rec, leg_est) in enumerate(step.advance(k, S)):
            est[b, k + 1 : k + S + 1] = leg_est
            legs[b].append(rec)
        k += S
    return [OfflineResult(estimate=est[b], legs=legs[b]) for b in range(len(seeds))]


def run_offline(
    field,
    predictor,
    *,
    start_cell,
    t0: int = 0,
    n_steps: int,
    seed: int = 0,
    noise_std: float = 0.0,
    sample_at: str = "end",
    initial_state=None,
    options: LoopOptions | None = None,
    **loop_kw,
) -> OfflineResult:
    """One boat, one trial (:func:`run_trials`). The loop's options: ``options`` with any
    :class:`~passt_mav.loop.passt.LoopOptions` field given as a keyword (``planner=``, ``path_length=``, ...).
    ``predictor=None`` runs the GP-only ("hold") variant."""
    return run_offline_fleet(
        field,
        predictor,
        start_cells=[start_cell],
        t0=t0,
        n_steps=n_steps,
        seed=seed,
        noise_std=noise_std,
        sample_at=sample_at,
        initial_state=initial_state,
        options=options,
        **loop_kw,
    )


def run_offline_fleet(
    field,
    predictor,
    *,
    start_cells,
    t0: int = 0,
    n_steps: int,
    seed: int = 0,
    noise_std: float = 0.0,
    sample_at: str = "end",
    initial_state=None,
    options: LoopOptions | None = None,
    **loop_kw,
) -> OfflineResult:
    """:func:`run_offline` for a fleet: ``len(start_cells)`` boats, synchronous legs, one state.

    Each leg interval: one forecast and one reward map; the boats plan in turn under the keep-out
    rule (module docstring); every boat's samples go to one GP update. With one start cell this is
    :func:`run_offline`. Leg records hold ``paths`` (one per boat) and ``path`` (boat 0's).
    """
    (res,) = run_trials(
        field,
        predictor,
        LoopOptions.of(options, **loop_kw),
        starts=[start_cells],
        seeds=[seed],
        t0=t0,
        n_steps=n_steps,
        noise_std=noise_std,
        sample_at=sample_at,
        initial_state=initial_state,
    )
    return res


def run_offline_lockstep(
    field,
    predictor,
    *,
    start_cells,
    seeds,
    t0: int = 0,
    n_steps: int,
    noise_std: float = 0.0,
    sample_at: str = "end",
    initial_state=None,
    kernel_cache: dict | None = None,
    options: LoopOptions | None = None,
    **loop_kw,
) -> list[OfflineResult]:
    """:func:`run_offline` for B one-boat trials at once (``start_cells[b]``, ``seeds[b]``), in lockstep.

    Each leg runs the predictor ONCE for the whole batch and plans the batch in one call where the
    planner can; every trial then samples and reconstructs as in :func:`run_offline` (same seeds,
    same order of random draws): equal to it up to the predictor's batch-vs-single rounding (exactly
    equal for a predictor whose rows do not interact; tested). ``hyper="state"`` kernels and the
    background's modes are computed once for all trials (:meth:`OfflineStep.share_setup`). Leg
    timings: ``predict`` is the batch's time divided by B.
    """
    if len(start_cells) != len(seeds) or not len(seeds):
        raise PlannerError("run_offline_lockstep needs one seed per start cell (at least one)")
    return run_trials(
        field,
        predictor,
        LoopOptions.of(options, **loop_kw),
        starts=[[c] for c in start_cells],
        seeds=seeds,
        t0=t0,
        n_steps=n_steps,
        noise_std=noise_std,
        sample_at=sample_at,
        initial_state=initial_state,
        batched=True,
        kernel_cache=kernel_cache,
    )
