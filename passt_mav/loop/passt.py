"""The PASST loop (Predictive-model based Adaptive Sampling of a Spatio-Temporal process).

ONE implementation, driven offline by :class:`FieldSampler` (ground truth, through the
offline engine :mod:`passt_mav.loop.engine`) and on a vehicle by :class:`passt_mav.loop.legstep.LegStep`
(the controller flies the leg, the step turns its logged samples into :class:`Samples`)::

    state U(t_k) --predict S steps--> forecast --one-step reward--> plan L moves
         ^                                                             |
         +-- GP(samples - forecast) + forecast(t_k+S) <-- sample along the path

Time. The loop counts time in snapshot steps of the predictor (``dt`` field-time
units apart). A leg of ``L`` moves spans ``steps_per_leg`` snapshots: for the
offline evaluation this is given directly; for a vehicle it follows from the
speed, ``L * cell_size / speed`` (see :func:`steps_for_leg`), or, in a current, from the time
the boat needs for the planned path with the crab angle held against it
(:mod:`passt_mav.planning.transit`, :func:`steps_for_duration`). Between
re-initialisations the estimate at each step is the model's prediction from the
last reconstructed state; the leg's samples are compared with that forecast at
their own position AND time (the GP fits the residual), and the reconstruction
becomes the state at the leg's end, from which the next leg is planned. With
``background`` > 0 the residual GP's prior covariance also holds the anomaly covariance
of the model's own roll-out from the first leg's initial state
(:func:`passt_mav.reconstruction.model_background`), so a leg's samples correct the
model's drift across the region, not only near the track.

Land cells (NaN in the state) are filled with 0 only at the predictor's input
(predictors reject NaN) and set back to NaN in every output, so nothing
downstream sees a land value.

Step-by-step API for a controller: :class:`PasstLoop` ``.plan_leg(state, start,
t_start)`` -> :class:`LegPlan`, fly / sample, ``.update(leg, samples)`` -> new state. The loop's
options are one frozen :class:`LoopOptions`. Offline: :func:`passt_mav.loop.engine.run_offline`
(and its fleet and lockstep forms). Everything random is seeded.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np

from passt_mav.errors import PlannerError, ReconstructionError
from passt_mav.loop.blend import (  # noqa: F401 - the blend's names re-exported
    PRIOR_BLENDS,
    PRIOR_CANDIDATES,
    PRIOR_START_WEIGHTS,
    PriorBlend,
    model_forecast,
)
from passt_mav.loop.guard import GUARDS, OpenLoop, guard_record, relax_to_open_loop
from passt_mav.loop.online import ModelUpdate, OnlineUpdate
from passt_mav.loop.presets import DEFAULT

__all__ = [
    "Samples",
    "Sampler",
    "FieldSampler",
    "LegPlan",
    "LoopOptions",
    "PasstLoop",
    "OfflineResult",
    "run_pure_model",
    "model_forecast",
    "steps_for_leg",
    "steps_for_duration",
    "HYPER",
    "SAMPLE_AT",
]

#: FieldSampler sampling times: along the leg at constant speed, or all at the leg's end
SAMPLE_AT = ("spread", "end")

#: when the GP hyper-parameters are fitted: once on the first leg's samples (residuals),
#: once on the campaign's initial state, or on every leg (slower, adapts to a growing error)
HYPER = ("first_leg", "state", "every_leg")


@dataclass
class Samples:
    """Current samples of one leg (arrays of equal length ``n``).

    t: field time (same units as ``FlowField.times``); r, c: fractional cells
    (row north, col east; integer = cell centre); u, v: east/north velocity.
    """

    t: np.ndarray
    r: np.ndarray
    c: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def __post_init__(self) -> None:
        arrs = [np.asarray(a, dtype=np.float64).reshape(-1) for a in (self.t, self.r, self.c, self.u, self.v)]
        if len({a.size for a in arrs}) != 1:
            raise ReconstructionError("samples: t, r, c, u, v must have the same length")
        self.t, self.r, self.c, self.u, self.v = arrs

    def __len__(self) -> int:
        return int(self.t.size)

    @classmethod
    def from_latlon(cls, grid, t, lat, lon, u, v) -> Samples:
        """Samples at geographic positions (degrees), e.g. from a vehicle's GPS."""
        r, c = grid.latlon_to_fcell(np.asarray(lat, float), np.asarray(lon, float))
        return cls(t, r, c, u, v)

    @classmethod
    def concat(cls, parts) -> Samples:
        """One set of the samples of ``parts`` (a fleet's boats in one leg interval), in order."""
        return cls(*(np.concatenate([getattr(x, f) for x in parts]) for f in ("t", "r", "c", "u", "v")))

    def xy(self, grid) -> np.ndarray:
        """(n, 2) local east/north metres of the samples (the grid's frame)."""
        x, y = grid.latlon_to_xy(*grid.fcell_to_latlon(self.r, self.c))
        return np.column_stack([np.asarray(x, float).reshape(-1), np.asarray(y, float).reshape(-1)])

    @property
    def uv(self) -> np.ndarray:
        return np.column_stack([self.u, self.v])


@runtime_checkable
class Sampler(Protocol):
    """Where samples come from: the ground-truth field offline, a vehicle live."""

    def leg_duration(self, n_moves: int) -> float:
        """Field time (FlowField.times units) the robot needs for ``n_moves`` moves."""

    def sample_path(self, path_cells: np.ndarray, t_start: float) -> Samples:
        """Traverse ``path_cells`` ((L+1, 2) int) starting at field time ``t_start``."""


def steps_for_leg(n_moves: int, cell_size_m: float, speed_m_s: float, dt_s: float) -> int:
    """Snapshots spanned by a leg in still water: ``round(n_moves * cell_size / speed / dt)``, at least 1."""
    if speed_m_s <= 0 or dt_s <= 0:
        raise PlannerError("vehicle speed and snapshot interval must be positive")
    return steps_for_duration(n_moves * cell_size_m / speed_m_s, dt_s)


def steps_for_duration(duration_s: float, dt_s: float) -> int:
    """Snapshots spanned by a leg of ``duration_s`` seconds (e.g. a path's time in the current,
    :func:`passt_mav.planning.transit.leg_timing`): ``round(duration / dt)``, at least 1 (a leg the
    boat cannot finish, an infinite duration, spans as many as 10**6)."""
    if dt_s <= 0:
        raise PlannerError("snapshot interval must be positive")
    x = float(duration_s) / float(dt_s)
    return max(1, int(round(min(x, 1e6))) if np.isfinite(x) else 10**6)


class FieldSampler:
    """Offline sampler: reads a ground-truth :class:`FlowField` along the path.

    One sample per path cell (the start included). With ``sample_at="spread"`` each
    is read at the time the robot passes it, assuming constant speed over the leg:
    cell ``i`` of ``L`` moves at ``t_start + i / L * leg_duration``. Values are the field bilinearly
    interpolated (space and time) plus Gaussian noise of std ``noise_std`` (field
    units), from a generator seeded with ``seed``.

    ``sample_at="end"`` (default) reads every cell at the leg's end time: the idealised
    leg of the paper's offline evaluation (a robot fast compared with the flow), in
    which the reconstruction is of one snapshot. With ``"spread"`` a residual seen
    early in the leg may have moved by the leg's end: in the cylinder wake (flow ~1
    cell per snapshot) 10 snapshots per leg made reconstructions worse than the
    forecast, where 1 snapshot per leg made them better (measured with a DMD model).

    Leg duration: ``steps_per_leg * field.dt`` if given, else
    ``n_moves * mean_cell_size / speed`` (speed in m/s; for the non-dimensional
    cylinder, cell size in metres and speed in inflow units). With ``speed`` (and no
    ``steps_per_leg``) and ``current_aware`` (default), ``"spread"`` samples a cell at the time
    the boat reaches it in the true current, its crab angle held against it
    (:func:`passt_mav.planning.transit.leg_timing` on the field's snapshots from ``t_start``).
    """

    def __init__(
        self,
        field,
        *,
        noise_std: float = 0.0,
        seed: int = 0,
        steps_per_leg: int | None = None,
        speed: float | None = None,
        sample_at: str = "end",
        current_aware: bool = True,
    ):
        if steps_per_leg is None and speed is None:
            raise PlannerError("FieldSampler needs steps_per_leg or speed")
        if sample_at not in SAMPLE_AT:
            raise PlannerError(f"unknown sampling time {sample_at!r}; choose one of {', '.join(SAMPLE_AT)}")
        self.sample_at = sample_at
        self.field = field
        self.noise_std = float(noise_std)
        self.seed = seed
        self.steps_per_leg = steps_per_leg
        self.speed = speed
        self.current_aware = bool(current_aware)
        self._rng = np.random.default_rng(seed)

    def leg_duration(self, n_moves: int) -> float:
        if self.steps_per_leg is not None:
            return float(self.steps_per_leg) * self.field.dt
        return float(n_moves) * self.field.grid.mean_cell_size_m / float(self.speed)

    def arrival_times(self, path, t_start: float) -> np.ndarray:
        """(L+1,) field time from ``t_start`` at which a boat at ``speed`` (field velocity units, as
        the cell size and the field's times) reaches each cell of ``path`` in the true current."""
        from passt_mav.planning.transit import leg_timing

        f = self.field
        k0 = int(np.clip(np.searchsorted(f.times, t_start, side="right") - 1, 0, f.n_times - 1))
        snaps = np.asarray(f.data[k0:], np.float64)
        lag = float(t_start) - float(f.times[k0])  # the leg begins this long after snapshot k0
        tm = leg_timing(path, snaps, f.grid.cell_size_m, float(self.speed), snapshot_s=float(f.dt), start_s=lag)
        return np.minimum(tm.arrival - lag, 1e12)

    def sample_path(self, path_cells, t_start: float) -> Samples:
        p = np.asarray(path_cells, dtype=np.float64)
        L = max(len(p) - 1, 1)
        if self.sample_at == "end":  # the idealised leg: one snapshot, read along the whole path
            t = np.full(len(p), float(t_start) + self.leg_duration(L))
        elif self.steps_per_leg is None and self.current_aware and len(p) > 1:
            t = float(t_start) + self.arrival_times(np.asarray(path_cells, np.int64), float(t_start))
        else:
            t = float(t_start) + np.arange(len(p)) / L * self.leg_duration(L)
        t = np.minimum(t, self.field.times[-1])  # a leg running past the data samples its last snapshot
        uv = self.field.interp(t, p[:, 0], p[:, 1])
        if self.noise_std > 0:
            uv = uv + self._rng.normal(0.0, self.noise_std, uv.shape)
        return Samples(t, p[:, 0], p[:, 1], uv[:, 0], uv[:, 1])


@dataclass
class LegPlan:
    """One planned leg.

    path: (L+1, 2) int cells; reward: (R, C) map it was planned on; forecast:
    (S+1, 2, R, C) model trajectory from the leg's initial state (index 0 = that
    state) over the leg's ``steps`` snapshots; t_start: field time of index 0;
    dt: field time per step; timings: seconds for predict / reward / plan.
    """

    path: np.ndarray
    reward: np.ndarray
    forecast: np.ndarray
    t_start: float
    dt: float
    steps: int
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def planning_time(self) -> float:
        return self.timings.get("reward", 0.0) + self.timings.get("plan", 0.0)


@dataclass(frozen=True)
class LoopOptions:
    """Every option of a :class:`PasstLoop` but its predictor, grid, land mask and seed: built once
    (from a mission file, a campaign's configuration or keywords) and handed to each loop.

    planner / planner_kw: a name in ``passt_mav.planning.PLANNERS`` and its options; reward: a name
    in ``passt_mav.planning.REWARDS``; path_length: moves per leg ``L``; steps_per_leg: snapshots
    a leg spans ``S``; prior: "forecast" | "none"; gp_kw: :class:`GPReconstructor` options;
    hyper: :data:`HYPER`; background: roll-out snapshots of the model background (0 = none);
    prior_blend / forgetting / share / memory / guard / model_update / vehicle_speed: see :class:`PasstLoop`.
    Validated by the loop that takes them.
    """

    planner: str = DEFAULT.planner
    planner_kw: dict | None = None
    reward: str = DEFAULT.reward
    path_length: int = 50
    steps_per_leg: int = 10
    prior: str = DEFAULT.prior
    gp_kw: dict | None = None
    hyper: str = "every_leg"
    background: int = DEFAULT.background
    prior_blend: str = DEFAULT.prior_blend
    forgetting: float = DEFAULT.forgetting
    share: float = DEFAULT.prior_share
    memory: str = DEFAULT.memory
    guard: str = DEFAULT.guard
    model_update: ModelUpdate | None = None
    vehicle_speed: float | None = None
    transit_kw: dict | None = None

    @classmethod
    def of(cls, options: LoopOptions | None = None, **changes) -> LoopOptions:
        """``options`` (default: the defaults) with ``changes``; an unknown name raises ``TypeError``."""
        return replace(options or cls(), **changes)

    def as_kwargs(self) -> dict[str, Any]:
        """The options as :class:`PasstLoop` keywords."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def loop(self, predictor, grid, *, land=None, seed: int = 0) -> PasstLoop:
        """A fresh :class:`PasstLoop` with these options."""
        return PasstLoop(predictor, grid, land=land, seed=seed, **self.as_kwargs())


def _check_loop_options(
    reward, hyper, path_length, steps_per_leg, background, prior_blend, forgetting, memory="off", share=0.0, guard="on"
) -> None:
    """Raise :class:`PlannerError` / :class:`ReconstructionError` (one line naming the problem) for
    an unknown reward, GP schedule or prior blend, a non-positive path length or leg span, a bad
    background roll-out length, a forgetting factor or share outside [0, 1], an unknown planner memory or guard."""
    from passt_mav.planning import REWARDS
    from passt_mav.reconstruction.background import background_steps_problem

    if reward not in REWARDS:
        raise PlannerError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
    if hyper not in HYPER:
        raise ReconstructionError(f"unknown GP hyper-parameter schedule {hyper!r}; choose one of {', '.join(HYPER)}")
    if int(path_length) < 1 or int(steps_per_leg) < 1:
        raise PlannerError("path_length and steps_per_leg must be positive integers")
    problem = background_steps_problem(background)
    if problem:
        raise ReconstructionError(problem)
    if prior_blend not in PRIOR_BLENDS:
        raise ReconstructionError(f"unknown prior blend {prior_blend!r}; choose one of {', '.join(PRIOR_BLENDS)}")
    if not 0.0 <= float(forgetting) <= 1.0:
        raise ReconstructionError(f"forgetting factor must lie in [0, 1], got {forgetting!r}")
    if not 0.0 <= float(share) <= 1.0:
        raise ReconstructionError(f"prior share must lie in [0, 1], got {share!r}")
    if memory not in MEMORIES:
        raise PlannerError(f"unknown planner memory {memory!r}; choose one of {', '.join(MEMORIES)}")
    if guard not in GUARDS:
        raise ReconstructionError(f"unknown guard {guard!r}; choose one of {', '.join(GUARDS)}")


class PasstLoop:
    """The PASST algorithm, leg by leg.

    Defaults: :data:`passt_mav.loop.presets.DEFAULT` (the mission schema's; the paper's configuration is
    :data:`~passt_mav.loop.presets.PAPER`: ``PasstLoop(..., **PAPER.loop_kwargs(), gp_kw=PAPER.gp_kwargs())``).

    Args:
        predictor: object with ``predict(state (2,R,C), steps) -> (steps,2,R,C)``, or
            ``None`` for "hold" (the estimate stays the last reconstruction: the
            GP-only baselines).
        grid: the field's region grid (metres frame for the GP, cell size for rewards).
        planner / planner_kw: a name in ``passt_mav.planning.PLANNERS`` and its options.
        reward: a name in ``passt_mav.planning.REWARDS``.
        path_length: moves per leg ``L``; steps_per_leg: snapshots a leg spans ``S``.
        prior: GP prior, "forecast" or "none".
        gp_kw: options of :class:`GPReconstructor` (besides ``grid_xy`` / ``prior``).
        hyper: when to fit the GP hyper-parameters, see :data:`HYPER`.
        land: (R, C) bool, True = land (never traversable, NaN in estimates).
        seed: planner seeds are ``seed + leg index``.
        background: snapshots of the predictor's roll-out, from the first leg's initial
            state, whose anomaly covariance the residual GP adds to its stationary kernels
            (:func:`passt_mav.reconstruction.model_background`); 0 = none. Only
            with a predictor and ``prior="forecast"``. A caller may set ``gp.background``
            itself beforehand (the lockstep engine computes it once for all trials).
        prior_blend: "off" (the forecast restarted from the last estimate is the GP's prior mean),
            "bma" or "select": a prior that knows when it is wrong (:mod:`passt_mav.loop.blend`). Each
            leg's samples score the whole-field forecasts that could have been its background (the model
            restarted, the model alone from the first leg's initial state, persistence) by the innovation
            likelihood of their residuals under the GP's stationary kernels and sensor noise as they stand
            before this leg's fit (:meth:`GPReconstructor.innovation_loglik` with ``modes=False``: one
            covariance for all, so the smaller and smoother residual wins); "bma" mixes them by their
            weights, "select" takes the most probable alone. The weights are updated with the leg's own
            samples before its reconstruction, the same mixture carries the estimate between legs
            (:meth:`blend`), and each leg's record is in ``blend_history_``.
        forgetting: the blend's forgetting factor in [0, 1] (memory of about 1 / (1 - forgetting) legs).
        share: the blend's "fixed share" of the prior weights in [0, 1] (0 = off; with a share the blend
            starts on the model alone).
        guard: "on" (default) or "off": before a leg's samples enter the estimate, the loop's
            forecast (restarted from the last estimate) and the model alone are scored at them
            (RMSE and innovation likelihood, :func:`passt_mav.loop.guard.guard_record`; no truth
            read); when the loop's forecast fits them worse on two legs running, or by more than
            10 % on one, the leg's background is the model alone (``guard_history_``; the record's
            ``fallback``). Only with a predictor and ``prior="forecast"``.
        memory: "off" or "fitted": the information reward's prior remembers, cell by cell, the
            local error variance that past legs' samples removed, with a persistence per leg
            fitted by the innovations' likelihood (:class:`passt_mav.loop.memory.CellMemory`;
            0 = off until cells sampled twice show it). Only with a reward that uses the prior.
        model_update: :class:`passt_mav.loop.online.ModelUpdate` (``None`` or ``online="off"``: off): learning
            at sea, each leg's update of the predictor kept only when the leg's samples find it more probable
            (:mod:`passt_mav.loop.online`; ``online`` holds the updater, ``initial_predictor`` the model alone).
        vehicle_speed: the boat's speed through the water in the field's velocity units (m/s divided by
            ``field.velocity_scale``), or None. Given, the planner is offered only the moves the boat can
            make in the leg's forecast current, its crab angle held against it (ground speed at least
            :data:`~passt_mav.planning.transit.FEASIBLE_MARGIN` x the speed in every snapshot of the
            forecast; :func:`passt_mav.planning.transit.feasible_moves`).
        transit_kw: how the boat holds ``vehicle_speed`` (:func:`passt_mav.planning.transit.ground_speed`'s
            ``hold`` and ``max_water_speed``, the latter in the field's velocity units); None: through the water.
    """

    def __init__(
        self,
        predictor,
        grid,
        *,
        planner: str = DEFAULT.planner,
        planner_kw: dict | None = None,
        reward: str = DEFAULT.reward,
        path_length: int = 50,
        steps_per_leg: int = 10,
        prior: str = DEFAULT.prior,
        gp_kw: dict | None = None,
        hyper: str = "every_leg",
        land=None,
        seed: int = 0,
        background: int = DEFAULT.background,
        prior_blend: str = DEFAULT.prior_blend,
        forgetting: float = DEFAULT.forgetting,
        share: float = DEFAULT.prior_share,
        memory: str = DEFAULT.memory,
        guard: str = DEFAULT.guard,
        model_update: ModelUpdate | None = None,
        vehicle_speed: float | None = None,
        transit_kw: dict | None = None,
    ):
        from passt_mav.planning import make_planner
        from passt_mav.planning.rewards import REWARDS_USING_PRIOR, REWARDS_USING_STD
        from passt_mav.reconstruction import GPReconstructor

        _check_loop_options(
            reward, hyper, path_length, steps_per_leg, background, prior_blend, forgetting, memory, share, guard
        )
        if vehicle_speed is not None and not float(vehicle_speed) > 0:
            raise PlannerError(f"vehicle speed must be positive, got {vehicle_speed!r}")
        self.vehicle_speed = None if vehicle_speed is None else float(vehicle_speed)
        self.transit_kw = dict(transit_kw or {})
        self.hyper = hyper
        self.predictor = self.initial_predictor = predictor  # an online update replaces the first alone
        self.online = OnlineUpdate.of(model_update, predictor)
        self.grid = grid
        self.planner_name = planner
        self.planner = make_planner(planner, **(planner_kw or {}))
        self.reward_name = reward
        self.path_length = int(path_length)
        self.steps_per_leg = int(steps_per_leg)
        self.land = np.zeros(grid.shape, bool) if land is None else np.asarray(land, bool)
        self.seed = int(seed)
        self.gp = GPReconstructor(grid_xy=grid.centres_xy(), prior=prior, **{**DEFAULT.gp_kwargs(), **(gp_kw or {})})
        self.background_steps = int(background) if predictor is not None and prior == "forecast" else 0
        self._background_pending = bool(self.background_steps)
        # GP posterior std of the last reconstruction; computed only for a reward that
        # uses it (the variance is most of a leg's GP time with the cholesky solver)
        self.std: np.ndarray | None = None
        #: the information model the last reward map was built on (variance_reduction), else None
        self.info_ = None
        self._needs_std = reward in REWARDS_USING_STD
        #: compute the GP std every leg even when the reward does not read it (set by
        #: legstep.build_loop: a vehicle's run records it in legs/NNN/estimate.nc)
        self.keep_std = False
        self.leg_index = 0
        self._cell = grid.cell_size_m
        #: the candidate priors' weights (:class:`passt_mav.loop.blend.PriorBlend`)
        self.blend_ = PriorBlend(
            prior_blend if predictor is not None and prior == "forecast" else "off", forgetting, share
        )
        #: per-cell memory of the local error past samples removed (``memory="fitted"``), else None
        self.memory = None
        if memory == "fitted" and reward in REWARDS_USING_PRIOR:
            from passt_mav.loop.memory import CellMemory

            self.memory = CellMemory(grid.shape[0] * grid.shape[1])
        self._memory_diag = None  # (modes, local, noise) variances (2, N) of the last unscaled prior
        self.guard = guard if predictor is not None and prior == "forecast" else "off"
        #: the model alone from the first leg's initial state (:class:`passt_mav.loop.guard.OpenLoop`)
        self.open_loop_: OpenLoop | None = None
        #: one :func:`passt_mav.loop.guard.guard_record` per leg (``guard="on"``)
        self.guard_history_: list[dict] = []
        #: field time of the last reconstruction (None before the first): where a restarted forecast's
        #: correction starts to fade (:func:`passt_mav.loop.guard.relax_to_open_loop`)
        self.t_recon_: float | None = None
        self.relaxed_ = False  # whether the last leg's background had that correction faded

    def forecast(self, state: np.ndarray, steps: int) -> np.ndarray:
        """(steps+1, 2, R, C) float32: ``state`` then the model's ``steps`` predictions."""
        return model_forecast(self.predictor, state, steps, self.land)

    def anchor_open_loop(self, state, t_start: float, dt: float) -> None:
        """Start the model alone (:class:`passt_mav.loop.guard.OpenLoop`) from ``state`` ((2, R, C),
        field units) at field time ``t_start``, ``dt`` field time per snapshot, unless started
        already: the first leg's initial state, which :meth:`plan_leg` and :meth:`update` pass."""
        if self.open_loop_ is None and self.predictor is not None:
            self.open_loop_ = OpenLoop(self.model_alone, state, t_start, dt)

    def set_open_loop(self, trajectory, t0: float, dt: float) -> None:
        """Use ``trajectory`` ((n, 2, R, C): the model alone from the first state at field time
        ``t0``, one snapshot every ``dt``) instead of rolling it out again (the lockstep engine
        computes it once for all trials)."""
        if self.predictor is not None:
            self.open_loop_ = OpenLoop(self.model_alone, trajectory[0], t0, dt, trajectory=trajectory)

    def model_alone(self, state, steps: int) -> np.ndarray:
        """:meth:`forecast` by the predictor the loop was built with (an online update changes the loop's own)."""
        return model_forecast(self.initial_predictor, state, steps, self.land)

    def open_loop_forecast(self, t_start: float, dt: float, n: int) -> np.ndarray:
        """(n, 2, R, C) float64: the model alone at field times ``t_start + i * dt`` (NaN on land)."""
        out = self.open_loop_.at(t_start, dt, n)
        out[:, :, self.land] = np.nan
        return out

    def plan_leg(
        self,
        state,
        start,
        t_start: float,
        dt: float = 1.0,
        *,
        steps: int | None = None,
        forecast=None,
        taken=None,
        avoid=None,
    ) -> LegPlan:
        """Predict the leg, build the one-step reward map, plan ``path_length`` moves from ``start``.

        ``forecast``: a ready (S+1, 2, R, C) forecast from ``state`` (the lockstep engine
        predicts a whole batch of trials at once); the predictor is then not called.
        ``taken`` / ``avoid``: (R, C) bool, for a fleet's joint planning: cells other boats
        sample during this leg (their reward is zeroed, so two boats do not collect the
        same cells) and cells never to enter (another boat is there at the same time).
        The start cell is always allowed.
        """
        S = self.steps_per_leg if steps is None else int(steps)
        tm: dict[str, float] = {}
        t0 = time.perf_counter()
        fc = self.forecast(state, max(S, 1)) if forecast is None else forecast
        tm["predict"] = time.perf_counter() - t0
        self.anchor_open_loop(fc[0], t_start, dt)
        t0 = time.perf_counter()
        q, mask = self._reward_map(fc, start, taken, avoid)
        tm["reward"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        extra = {"info": self.info_} if getattr(self.planner, "uses_information", False) else {}
        path = self.planner.plan(q, start, self.path_length, seed=self._plan_seed(), mask=mask, **extra)
        tm["plan"] = time.perf_counter() - t0
        return LegPlan(path=path, reward=q, forecast=fc, t_start=float(t_start), dt=float(dt), steps=S, timings=tm)

    def _plan_seed(self) -> int:
        return self.seed + self.leg_index

    def _reward_map(self, fc, start, taken=None, avoid=None) -> tuple[np.ndarray, np.ndarray]:
        """(reward (R, C), traversable mask) of a leg from its forecast (see :meth:`plan_leg`)."""
        from passt_mav.planning import compute_reward
        from passt_mav.planning.rewards import REWARDS_USING_PRIOR, REWARDS_USING_STATE

        std = self.std if self.std is not None else np.ones((2,) + self.grid.shape, np.float32)
        self.info_ = None
        if self.reward_name in REWARDS_USING_PRIOR:
            # the prior of the reconstruction that will follow this leg; another boat's cells
            # of this leg count as sampled already
            self.info_ = self.information_model(fc[0])
            if taken is not None and np.any(taken):
                self.info_ = self.info_.conditioned(np.argwhere(np.asarray(taken, bool)))
        if self.reward_name in REWARDS_USING_STATE:
            # the change over the whole leg, from its initial state to the snapshot the
            # leg's samples reconstruct
            q = compute_reward(self.reward_name, fc[-1], cell_size_m=self._cell, std=std, state=fc[0])
        else:
            q = compute_reward(self.reward_name, fc[1], cell_size_m=self._cell, std=std, info=self.info_)
        mask = ~self.land & np.isfinite(fc[1]).all(axis=0)
        if taken is not None:
            q = np.where(np.asarray(taken, bool), np.zeros_like(q), q)
        if avoid is not None:
            mask = mask & ~np.asarray(avoid, bool)
            mask[tuple(start)] = True
        if self.vehicle_speed is not None:  # the moves the boat can make in the forecast current: (R, C, 8)
            from passt_mav.planning.transit import feasible_moves

            mask = feasible_moves(fc, self._cell, self.vehicle_speed, traversable=mask, **self.transit_kw)
        return q, mask

    def information_model(self, state):
        """:class:`passt_mav.planning.InformationModel` of the prior the next reconstruction uses
        (:meth:`passt_mav.reconstruction.GPReconstructor.prior_factors`: background modes with the
        factor last fitted, the kernels last fitted, the sensor noise). ``state``: the leg's
        initial state, from which the background is taken on the first leg (as :meth:`update`
        would). Built once per leg and GP state (a fleet's boats share it)."""
        from passt_mav.planning import InformationModel

        self.ensure_background(state)
        key = (
            self.leg_index,
            id(getattr(self.gp, "kernels_", None)),
            self.gp.background_factor() if self.gp.background is not None else None,
        )
        if getattr(self, "_info_key", None) != key:
            if self.memory is None:
                F, d, noise = self.gp.prior_factors(self.land)
            else:
                F, d, noise = self._remembered_prior()
            self._info_cache, self._info_key = InformationModel(F, d, noise, self.grid.shape), key
        return self._info_cache

    def _remembered_prior(self):
        """The prior factors with each cell's local part (kernel columns and diagonal) scaled by the
        memory's fractions (:class:`passt_mav.loop.memory.CellMemory`); the modes stay whole. Keeps
        the unscaled variances per cell for the memory's update after the leg."""
        F, d, noise, m = self.gp.prior_factors(self.land, with_mode_count=True)
        N = F.shape[0] // 2
        modes = np.sum(F[:, :m] ** 2, axis=1)
        local = np.sum(F[:, m:] ** 2, axis=1) + d
        self._memory_diag = (modes.reshape(2, N), local.reshape(2, N), np.asarray(noise, float).reshape(2, N))
        s2 = np.tile(self.memory.fractions(), 2)
        F = np.concatenate([F[:, :m], F[:, m:] * np.sqrt(s2)[:, None]], axis=1)
        return F, d * s2, noise

    def prepare(self, state) -> None:
        """What the first leg's planning needs from its initial ``state`` alone, computed ahead: the
        background roll-out and, for a reward that uses the reconstruction's prior, that prior's
        factors (:meth:`information_model`, cached for the leg)."""
        from passt_mav.planning.rewards import REWARDS_USING_PRIOR

        self.ensure_background(state)
        if self.reward_name in REWARDS_USING_PRIOR:
            self.information_model(state)

    def set_background(self, modes) -> None:
        """Use ``modes`` (another loop's background from the same predictor and initial state, or
        None) instead of rolling the model out again."""
        self.gp.background, self._background_pending = modes, False

    def ensure_background(self, state) -> None:
        """The background modes from ``state`` (the first leg's initial state, (2, R, C) in the
        field's units), once: a ``background``-snapshot roll-out of the predictor (seconds on a CPU).
        A live mission calls it before it waits for the vehicle, so that the first leg's planning
        does not keep a boat waiting while the current moves on (:meth:`prepare`)."""
        if self._background_pending:
            self._background_pending = False
            if self.gp.background is None:
                self.gp.background = _background_or_none(self.predictor, state, self.background_steps, self.land)

    def update(self, leg: LegPlan, samples: Samples) -> np.ndarray:
        """Reconstruct the state at the leg's end (``t_start + steps * dt``) from its samples.

        Returns (2, R, C) float32 (NaN on land); ``self.std`` holds the GP std when the
        reward uses it (else it may be ``None``: the cholesky solver skips it).
        """
        from passt_mav.fields.field import FlowField

        t0 = time.perf_counter()
        if self.online is not None:  # learning at sea, decided before the samples enter (may replace the forecast)
            self.online.consider(self, leg, samples)
        fc = leg.forecast
        traj = FlowField(
            np.where(np.isfinite(fc), fc, np.nan), self.grid, leg.t_start + leg.dt * np.arange(fc.shape[0])
        )
        # forecast at each sample's own position and time (time clipped to the leg)
        ts = np.clip(samples.t, traj.times[0], traj.times[-1])
        f_at = traj.interp(ts, samples.r, samples.c)
        xy = samples.xy(self.grid)
        t_end = leg.t_start + leg.dt * leg.steps
        st = samples.t if self.hyper != "state" else None  # a field fit is spatial only
        self.ensure_background(fc[0])  # once, from the first leg's initial state
        self.anchor_open_loop(fc[0], leg.t_start, leg.dt)
        open_fc = open_at = guard = None
        if self.guard == "on" or self.prior_blend != "off":
            open_fc = self.open_loop_forecast(leg.t_start, leg.dt, fc.shape[0])
            open_at = FlowField(open_fc, self.grid, traj.times).interp(ts, samples.r, samples.c)
            self.relaxed_ = False  # (gp_summary's correction_faded)
            if self.t_recon_ is not None and getattr(self.gp, "n_inputs_", 2) == 3:
                # the last reconstruction's correction, carried by the model since, faded as the GP's own time
                # kernel says a residual fades (guard.relax_to_open_loop): taken when this leg's samples find it
                # more probable than the correction as the model carried it
                rfc = relax_to_open_loop(fc, open_fc, traj.times, self.t_recon_, self.gp.kernels_).astype(np.float32)
                rtraj = FlowField(np.where(np.isfinite(rfc), rfc, np.nan), self.grid, traj.times)
                r_at = rtraj.interp(ts, samples.r, samples.c)
                score = self.loglik_at(samples, xy, st)
                if score(samples.uv - r_at) > score(samples.uv - f_at):
                    fc, traj, f_at, self.relaxed_ = rfc, rtraj, r_at, True
        if self.guard == "on":
            guard = guard_record(
                self.leg_index, samples.uv, f_at, open_at, self.loglik_at(samples, xy, st), self.guard_history_
            )
            self.guard_history_.append(guard)
        if self.prior_blend != "off":
            fc, f_at = self._weigh_priors(fc, traj, ts, samples, xy, st, open_fc, open_at)
        if guard is not None and guard["fallback"]:  # the forecast alone is the leg's background
            fc, f_at = open_fc.astype(np.float32), open_at
        if self.hyper == "every_leg" or not hasattr(self.gp, "kernels_"):
            if self.hyper == "state":
                self.gp.fit_field(fc[0])
            else:
                self.gp.fit(xy, samples.uv, forecast_at_samples=f_at, samples_t=st)
        if getattr(self.gp, "n_inputs_", 2) == 2:
            st = None
        mean, std = self.gp.reconstruct(
            xy,
            samples.uv,
            forecast=fc[-1],
            forecast_at_samples=f_at,
            mask=~self.land,
            samples_t=st,
            t=t_end,
            with_std=self._needs_std or self.keep_std,
        )
        leg.timings["gp"] = time.perf_counter() - t0
        self.std = std
        if self.memory is not None:
            self._remember(samples, f_at)
        if self.online is not None:
            self.online.remember(mean, t_end)
        self.leg_index += 1
        self.t_recon_ = float(t_end)
        return mean

    def _remember(self, samples: Samples, f_at: np.ndarray) -> None:
        """The memory's update from a leg's samples (mean innovation per sampled cell) under the prior
        the leg was planned on (:meth:`_remembered_prior`; none yet: nothing to score, the fractions
        only relax)."""
        if self._memory_diag is None or len(samples) == 0:
            self.memory.relax()
            return
        R, C = self.grid.shape
        r = np.clip(np.round(samples.r).astype(int), 0, R - 1)
        c = np.clip(np.round(samples.c).astype(int), 0, C - 1)
        inn = samples.uv - np.asarray(f_at, float).reshape(samples.uv.shape)
        ok = np.isfinite(inn).all(axis=1)
        flat = (r * C + c)[ok]
        cells, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
        mean_inn = np.zeros((cells.size, 2))
        np.add.at(mean_inn, inv, inn[ok])
        mean_inn /= counts[:, None]
        self.memory.observe(cells, counts, mean_inn, *self._memory_diag)

    def gp_summary(self) -> dict:
        """What the last reconstruction assumed, for a run's leg record: the sensor noise the GP
        used (``noise_std``, m/s per component u, v: fitted by marginal likelihood, never below
        the sensor's ``noise_std``; the white variance fitted above it that the GP holds as the
        field's grid-scale error, ``nugget_std``, is not in it), whether the samples showed a signal beyond that noise
        (``signal_kept``; otherwise the forecast was left alone there), the background factor,
        with the GP's ``bias`` the offset and forecast-anomaly variances (``offset_var``,
        ``anomaly_var``; 0 = not kept) and the share of the region the samples saw (``bias_coverage``,
        the modes' gate), the prior weights (``prior_blend="bma"``) and the online model update's record of
        the leg (``model_update``: :class:`passt_mav.loop.online.OnlineUpdate`)."""
        gp = self.gp
        out: dict = {"sensor_noise_std": float(gp.noise_std)}
        ks = getattr(gp, "kernels_", None)
        if ks is not None:
            nug = gp.nugget_vars()
            # the white std the GP fitted, and its part that is the field's grid-scale error (the
            # state nugget: a sample corrects its own cell by it), m/s per component u, v
            out["noise_std"] = [float(np.sqrt(max(k.k2.noise_level - v, 0.0))) for k, v in zip(ks, nug)]
            out["nugget_std"] = [float(np.sqrt(v)) for v in nug]
        tsf = getattr(gp, "time_scale_factor_", None)
        if tsf is not None and getattr(gp, "n_inputs_", 2) == 3:
            # the kept / fitted time length scale per component (forward validation; 1 = the likelihood's)
            out["time_scale_factor"] = [float(f) for f in tsf]
        if gp.max_time_scale is not None and getattr(gp, "n_inputs_", 2) == 3:
            # the longest time length scale allowed (field time units: the field's decorrelation time)
            out["max_time_scale"] = float(gp.max_time_scale)
        if self.t_recon_ is not None:
            # whether this leg's background was the last estimate's correction faded towards the model alone
            out["correction_faded"] = bool(getattr(self, "relaxed_", False))
        ev = getattr(gp, "evidence_", None)
        if ev is not None:
            out["signal_kept"] = [None if e is None else bool(e[0] >= e[1]) for e in ev]
        if gp.background is not None:
            out["background_factor"] = gp.background_factor()
        chk = getattr(gp, "std_check_", None)
        if chk is not None:  # the std's own check (GPReconstructor.forward_std_factor): the factor it was widened by
            out["std_inflation"] = float(gp.std_inflation_)
            out["std_check"] = {k: v if isinstance(v, int) else round(float(v), 4) for k, v in chk.items()}
        if gp.background is not None and getattr(gp, "std_calibration", "off") == "forward":
            # the share of the background's variance kept in the map's std (estimated by the check above)
            out["unresolved_share"] = round(gp.share_in_use(), 4)
        if getattr(gp, "bias", False):
            out["offset_var"] = float(getattr(gp, "bias_var_", 0.0))  # (field units)^2, 0 = no offset kept
            out["anomaly_var"] = float(getattr(gp, "scale_var_", 0.0))  # factor variance on the forecast anomaly
            cov = getattr(gp, "bias_coverage_", None)  # share of the region the samples see (the modes' gate)
            out["bias_coverage"] = None if cov is None else round(float(cov), 3)
        if self.blend_history_:
            out["prior_weights"] = dict(self.blend_history_[-1]["weights"])
            # the evidence behind them: this leg's innovation log likelihood of each candidate (nats)
            out["prior_loglik"] = {k: round(v, 3) for k, v in self.blend_history_[-1]["log_likelihood"].items()}
        if self.memory is not None:
            out["memory"] = self.memory.record()
        if self.guard_history_:
            out["guard"] = dict(self.guard_history_[-1])
        upd = None if self.online is None else self.online.record_
        if upd is not None and upd["leg"] == self.leg_index - 1:  # (none for a leg that never reached update)
            out["model_update"] = dict(upd)  # kept / seconds / steps / scores (nats) of the last leg
        return out

    def loglik_at(self, samples: Samples, xy: np.ndarray, st):
        """``residual (n, 2) -> nats``: the innovation log likelihood at ``samples`` under the GP's
        stationary kernels and noise as they stand (0 with fewer than 2 finite rows)."""

        def loglik(residual) -> float:
            r = np.asarray(residual, float)
            ok = np.isfinite(samples.uv).all(axis=1) & np.isfinite(r).all(axis=1)
            if ok.sum() < 2:
                return 0.0
            sub_t = None if st is None else np.asarray(st)[ok]
            return float(self.gp.innovation_loglik(xy[ok], r[ok], samples_t=sub_t, modes=False))

        return loglik

    # -- the prior blend (passt_mav.loop.blend), as the loop's own attributes ------------------------------
    @property
    def prior_blend(self) -> str:
        """``"off"``, ``"bma"`` or ``"select"`` (:class:`~passt_mav.loop.blend.PriorBlend`)."""
        return self.blend_.mode

    @property
    def forgetting(self) -> float:
        return self.blend_.forgetting

    @property
    def share(self) -> float:
        return self.blend_.share

    @property
    def log_weights_(self) -> np.ndarray:
        """Log weights of :data:`~passt_mav.loop.blend.PRIOR_CANDIDATES`."""
        return self.blend_.log_weights

    @property
    def blend_history_(self) -> list[dict]:
        """One record per leg the blend weighed (:meth:`PriorBlend.observe`)."""
        return self.blend_.history

    def weights(self) -> np.ndarray:
        """Current weights of :data:`~passt_mav.loop.blend.PRIOR_CANDIDATES` (sum 1)."""
        return self.blend_.weights()

    def mixing_weights(self) -> np.ndarray:
        """The weights the prior mixes the candidates with (:meth:`PriorBlend.mixing_weights`)."""
        return self.blend_.mixing_weights()

    def blend(self, fc: np.ndarray, t_start: float = 0.0, dt: float = 1.0) -> np.ndarray:
        """The estimate a model forecast ``fc`` ((S+1, 2, R, C) from field time ``t_start``, ``dt``
        apart) stands for: ``fc`` itself, or with ``prior_blend`` "bma" / "select" the candidates'
        mixture under :meth:`mixing_weights` (float32)."""
        return self.blend_.mix(fc, lambda: self.open_loop_forecast(t_start, dt, fc.shape[0]))

    def _weigh_priors(self, fc, traj, ts, samples, xy, st, open_fc, open_at):
        """Score the candidate priors on this leg's samples (innovation log likelihood under the GP's
        stationary kernels, nats), update the weights, return the mixture trajectory and its values at the
        samples (see ``prior_blend``)."""
        from passt_mav.fields.field import FlowField

        cands = PriorBlend.candidates(np.asarray(fc, np.float64), open_fc)
        ats = [traj.interp(ts, samples.r, samples.c), open_at]
        for c in cands[2:]:
            ats.append(FlowField(c, self.grid, traj.times).interp(ts, samples.r, samples.c))
        ok = np.isfinite(samples.uv).all(axis=1) & np.logical_and.reduce([np.isfinite(a).all(axis=1) for a in ats])
        sub_t = None if st is None else np.asarray(st)[ok]
        ll = np.array(
            [
                self.gp.innovation_loglik(xy[ok], samples.uv[ok] - a[ok], samples_t=sub_t, modes=False)
                if ok.sum() >= 2
                else 0.0
                for a in ats
            ]
        )
        w = self.blend_.observe(self.leg_index, ll)
        mix = sum(float(wk) * c for wk, c in zip(w, cands) if wk).astype(np.float32)
        f_at = sum(float(wk) * a for wk, a in zip(w, ats) if wk)
        return mix, f_at


#: the information prior's per-cell memory of past samples (:class:`passt_mav.loop.memory.CellMemory`)
MEMORIES = ("off", "fitted")


def _background_or_none(predictor, state, steps: int, land):
    """:func:`passt_mav.reconstruction.model_background`, or ``None`` with a one-line warning when
    the model's roll-out is not finite: the loop then goes on with the stationary kernels (a
    mission must not stop because the model diverges from its initial state)."""
    import warnings

    from passt_mav.reconstruction import model_background

    try:
        return model_background(predictor, state, steps, land=land)
    except ReconstructionError as exc:
        warnings.warn(
            f"no background covariance: {exc}; the GP uses its stationary kernels only", RuntimeWarning, stacklevel=2
        )
        return None


@dataclass
class OfflineResult:
    """Estimate time series of one offline run.

    estimate: (T+1, 2, R, C) float32, index k = step k after the start (0 = the
    initial state); legs: per-leg records (path, start step, timings, reward
    collected, samples).
    """

    estimate: np.ndarray
    legs: list[dict[str, Any]]


def run_pure_model(field, predictor, *, t0: int = 0, n_steps: int) -> np.ndarray:
    """The model alone from the true state at ``t0``: (T+1, 2, R, C), index 0 = truth."""
    n_steps = int(min(n_steps, field.n_times - 1 - t0))
    land = field.land_mask
    s = field.state_at(t0)  # gaps that come and go: FlowField.state_at
    pred = np.asarray(predictor.predict(np.where(land, np.float32(0), s), n_steps), dtype=np.float32)
    out = np.concatenate([s[None], pred], axis=0)
    out[:, :, land] = np.nan
    return out
