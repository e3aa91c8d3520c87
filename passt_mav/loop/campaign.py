"""The offline PASST campaign: trials x path lengths on ground truth, RMSE over time and POD energy.

The library behind ``passt-mav evaluate`` and ``passt-mav paper`` (thin CLI layers on top) and the
benchmarks. For every path length L (area covered per re-initialisation) and every trial (seed
``seed + trial``, random water start cell), the field is estimated over ``steps`` snapshots from the
true state at ``t0`` by:

* ``passt``        - the PASST loop: model forecast, one-step reward, planner, GP on
                     the residual vs the forecast, re-initialise, repeat;
* ``model``        - the model alone from the true initial state (no re-initialisation);
* ``lawnmower_gp`` / ``greedy_gp`` / ``random_gp`` - that planner's samples
                     reconstructed by a GP alone (constant prior mean), the estimate
                     held between legs (the paper's baselines); with
                     ``baseline_prior="forecast"`` they instead run the full loop with
                     the model, so only the planner differs.

Every loop runs on the offline engine (:func:`passt_mav.loop.engine.run_trials`); :data:`ENGINES` names
how a unit of work drives it (one trial at a time, or a batch of trials in lockstep). Reported: RMSE
over time (mean +- std over trials, field units), POD energy of the estimated vs true series, and the
ratio of each method's final-window RMSE to PASST's. :func:`fleet_comparison`: the same loop with
1..N boats (``passt-mav evaluate --boats N``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from collections.abc import Sequence

from passt_mav.loop.presets import DEFAULT, Preset
from passt_mav.reconstruction.background import background_steps_problem
from passt_mav.reconstruction.gp import MAX_FIT_POINTS

__all__ = [
    "METHODS",
    "ENGINES",
    "CAMPAIGN_HYPER",
    "CampaignOptions",
    "run_campaign",
    "fleet_comparison",
    "fleet_starts",
    "campaign_tasks",
    "method_problem",
    "load_predictor",
]

METHODS = ("passt", "model", "lawnmower_gp", "greedy_gp", "random_gp")


def _rmse_series(est, truth):
    import numpy as np

    d = (est.astype(np.float64) - truth) ** 2
    return np.sqrt(np.nanmean(d.reshape(d.shape[0], -1), axis=1))


def _task(field, predictor, cfg: dict, L: int, trials) -> list[dict]:
    """Trials ``trials`` at path length L, one result dict per trial (RMSE series, POD energy, timings
    per loop method), through the engine body :data:`ENGINES` names (``cfg["engine"]``).

    Runs with one BLAS thread wherever it runs: a multi-threaded BLAS sums in a
    different order, and a last-bit difference can flip a planner's argmax, so the
    same seeds would give different numbers in the main process, a joblib worker
    and a Dask worker.
    """
    from passt_mav.loop.threads import one_thread

    with one_thread(), _fast_path(predictor, cfg.get("fast_predict", False)), _heap_reuse():
        return ENGINES[cfg.get("engine", "serial")](field, predictor, cfg, L, list(trials))


@contextlib.contextmanager
def _heap_reuse():
    """Keep glibc's allocator reusing freed heap memory inside the block, where the
    environment froze its thresholds (a no-op elsewhere).

    A campaign allocates and frees arrays of 0.1-2 MB thousands of times per leg (roll-out
    tables, GP cross-covariances, model activations). Dask's nanny starts workers with
    ``MALLOC_TRIM_THRESHOLD_=65536``, which also freezes glibc's mmap threshold at 128 KiB:
    every such array is then a fresh mmap, page-faulted in and unmapped again, which slows
    the model's predictions and the GP several-fold in system time. Without such a variable glibc's dynamic threshold already reuses the heap, so nothing
    is changed. Here the mmap threshold goes to 64 MiB and the trim threshold to 256 MiB
    for the task; afterwards both go back to what the environment asked for (mmap 128 KiB
    unless ``MALLOC_MMAP_THRESHOLD_`` says otherwise) and ``malloc_trim`` returns the freed
    memory, as Dask wants. glibc's ``mallopt`` is called through ctypes: no library
    exposes it.
    """
    import ctypes
    import ctypes.util
    import os

    def env_int(name: str, default: int) -> int:
        try:
            return int(os.environ.get(name, default))
        except ValueError:
            return default

    libc = None
    frozen = "MALLOC_TRIM_THRESHOLD_" in os.environ or "MALLOC_MMAP_THRESHOLD_" in os.environ
    if sys.platform.startswith("linux") and frozen:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            libc.mallopt  # noqa: B018 - glibc only (musl has no mallopt)
        except (OSError, AttributeError):
            libc = None
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
    if libc is not None:
        libc.mallopt(M_MMAP_THRESHOLD, 64 << 20)
        libc.mallopt(M_TRIM_THRESHOLD, 256 << 20)
    try:
        yield
    finally:
        if libc is not None:
            libc.mallopt(M_MMAP_THRESHOLD, env_int("MALLOC_MMAP_THRESHOLD_", 128 << 10))
            libc.mallopt(M_TRIM_THRESHOLD, env_int("MALLOC_TRIM_THRESHOLD_", 128 << 10))
            libc.malloc_trim(0)


@contextlib.contextmanager
def _fast_path(predictor, on: bool):
    """Predict through the model's compiled fast path (``fast_predict``) inside the block, if it has one."""
    if predictor is None or not hasattr(predictor, "fast_predict"):
        yield
        return
    prev = predictor.fast_predict
    predictor.fast_predict = bool(on)
    try:
        yield
    finally:
        predictor.fast_predict = prev


#: GP kernels fitted on a campaign's initial state, per process (hyper="state": one fit
#: per configuration, shared by every trial and method with the same GP options)
_KERNEL_CACHE: dict = {}


def _start_cell(field, cfg: dict, L: int, trial: int) -> tuple[int, int]:
    import numpy as np

    rng = np.random.default_rng([int(cfg["seed"]) + trial, L])
    water = np.argwhere(~field.land_mask)
    return tuple(int(x) for x in water[rng.integers(len(water))])


#: GP hyper-parameter schedules of a campaign: passt_mav.loop.passt.HYPER, or "auto" = each GP fitted
#: on what it models: a GP on the residual vs the forecast on every leg's residuals
#: ("every_leg": the model's error grows and changes shape over a campaign), a GP on the
#: samples alone once on the initial state ("state"). A residual GP whose kernel was fitted on
#: the whole field (variance and length scale of the flow, not of the model's error) spreads
#: every leg's noisy residuals far and wide.
CAMPAIGN_HYPER = ("every_leg", "first_leg", "state", "auto")


def _hyper_for(hyper: str, residual: bool) -> str:
    """The :data:`passt_mav.loop.passt.HYPER` schedule of one GP: ``auto`` resolved by what it models."""
    if hyper != "auto":
        return hyper
    return "every_leg" if residual else "state"


def method_problem(m: str) -> str | None:
    """Why ``m`` is not a campaign method, or ``None``. A method is one of :data:`METHODS`, or
    ``PLANNER_gp`` for any planner of :data:`passt_mav.planning.PLANNERS` (e.g.
    ``information_gp``: prior as ``--baseline-prior`` says), or ``PLANNER_loop`` (always PASST's
    own loop: the model's forecast as the GP's prior, only the path differs), optionally with
    ``@REWARD`` (e.g. ``passt@speed``, ``greedy_loop@speed``): several planners and rewards in
    one campaign."""
    from passt_mav.planning import PLANNERS, REWARDS

    base, _, reward = m.partition("@")
    known = base in METHODS or any(base.endswith(sfx) and base[: -len(sfx)] in PLANNERS for sfx in ("_gp", "_loop"))
    if not known:
        return (
            f"unknown method {m!r}; choose from {', '.join(METHODS)}, PLANNER_gp or PLANNER_loop with PLANNER "
            f"one of {', '.join(PLANNERS)}"
        )
    if reward and (base == "model" or reward not in REWARDS):
        return (
            f"method {m!r}: unknown reward {reward!r} (or a method that plans nothing); rewards: {', '.join(REWARDS)}"
        )
    return None


def _method_kw(cfg: dict, m: str, predictor) -> tuple:
    """(predictor, run_offline options) of loop method ``m`` (its GP schedule included)."""
    h = cfg["hyper"]
    base, _, reward = m.partition("@")
    planner = cfg["planner"] if base == "passt" else base.rsplit("_", 1)[0]  # PLANNER_gp / PLANNER_loop
    if base == "passt" or base.endswith("_loop") or cfg["baseline_prior"] == "forecast":
        return predictor, dict(
            planner=planner, reward=reward or cfg["reward"], prior="forecast", hyper=_hyper_for(h, residual=True)
        )
    return None, dict(planner=planner, reward=reward or "speed", prior="none", hyper=_hyper_for(h, residual=False))


def _drifter_geometry(field) -> tuple | None:
    """(snapshot interval in seconds, (north-south, east-west) cell size in metres) of ``field`` for the
    drifter skill (:func:`passt_mav.models.drifters.drifter_separation`), or None where a distance per day
    means nothing: a field not in m/s (the cylinder: non-dimensional speed and time), or with unevenly
    spaced snapshots."""
    from passt_mav.errors import FieldError
    from passt_mav.units import MPS, speed_unit

    if speed_unit(None, field.units).label != MPS:
        return None
    try:
        return float(field.dt), tuple(float(x) for x in field.grid.cell_size_m)
    except FieldError:
        return None


def _drifters(estimate, truth, geom) -> dict | None:
    """The drifter separation of ``estimate`` against ``truth`` (each (T+1, 2, R, C), m/s) over the whole
    evaluated horizon, or None without a geometry (:func:`_drifter_geometry`)."""
    from passt_mav.models.drifters import drifter_separation

    return None if geom is None else drifter_separation(estimate, truth, geom[0], geom[1])


def _summarise_trial(out: dict, m: str, r, truth, cfg: dict, trial: int, geom=None) -> None:
    import numpy as np

    from passt_mav.fields.analysis import pod_energy

    out["rmse"][m] = _rmse_series(r.estimate, truth).tolist()
    drift = _drifters(r.estimate, truth, geom)
    if drift is not None:  # virtual drifters through the estimates vs through the truth (km, km/day)
        out.setdefault("drifters", {})[m] = drift
    out["pod"][m] = pod_energy(r.estimate, cfg["pod_modes"], cumulative=False).tolist()
    out["plan_ms"][m] = float(np.mean([leg["timings"]["plan"] for leg in r.legs]) * 1e3)
    out.setdefault("timings_s", {})[m] = {
        k: float(sum(leg["timings"].get(k, 0.0) for leg in r.legs)) for k in ("predict", "reward", "plan", "gp")
    }
    if cfg.get("keep_paths"):
        out.setdefault("paths", {})[m] = [leg["path"] for leg in r.legs]
    cals = [leg["calibration"] for leg in r.legs if leg.get("calibration")]
    if cals:  # the leg-end estimates' std against the truth (engine's calibration)
        out.setdefault("calibration", {})[m] = {k: [c[k] for c in cals] for k in ("step", "coverage95", "nlpd")}
    recs = [leg["model_update"] for leg in r.legs if leg.get("model_update") is not None]
    if recs:  # learning at sea: legs tried (at least one gradient step), kept, steps and seconds in all
        out.setdefault("model_update", {})[m] = _update_counts(recs)
    if trial == 0:
        k = min(cfg["snapshot_step"], cfg["steps"])
        out["snap"][m] = r.estimate[k].tolist()


def _update_counts(recs: list[dict]) -> dict:
    """The online model update's per-leg records summed: ``tried`` (legs with a gradient step), ``kept``,
    ``steps``, ``seconds``."""
    return {
        "tried": sum(1 for x in recs if x["steps"] > 0),
        "kept": sum(1 for x in recs if x["kept"]),
        "steps": int(sum(x["steps"] for x in recs)),
        "seconds": float(sum(x["seconds"] for x in recs)),
    }


def _loop_options(cfg: dict, m: str, predictor, L: int) -> tuple:
    """(predictor, :class:`~passt_mav.loop.passt.LoopOptions`) of loop method ``m`` at path length ``L``."""
    from passt_mav.loop.online import ModelUpdate
    from passt_mav.loop.passt import LoopOptions

    pred, kw = _method_kw(cfg, m, predictor)
    mu = cfg.get("model_update")
    return pred, LoopOptions(
        path_length=L,
        steps_per_leg=cfg["steps_per_leg"],
        gp_kw=cfg.get("gp_kw"),
        background=cfg.get("background", DEFAULT.background),
        prior_blend=cfg.get("prior_blend", DEFAULT.prior_blend),
        share=cfg.get("prior_share", DEFAULT.prior_share),
        forgetting=cfg.get("prior_forgetting", DEFAULT.forgetting),
        memory=cfg.get("memory", DEFAULT.memory),
        guard=cfg.get("guard", DEFAULT.guard),
        model_update=None if mu is None else ModelUpdate(**mu),
        **kw,
    )


def _trial_setup(field, cfg: dict, L: int, trials) -> tuple:
    """(truth (T+1, 2, R, C) float64, start cells, seeds, empty result dicts, engine keywords) of ``trials``."""
    t0, T = cfg["t0"], cfg["steps"]
    truth = field.data[t0 : t0 + T + 1].astype("float64")
    starts = [_start_cell(field, cfg, L, i) for i in trials]
    seeds = [int(cfg["seed"]) + i for i in trials]
    outs = [
        {"L": L, "trial": i, "start": list(st), "rmse": {}, "pod": {}, "snap": {}, "plan_ms": {}}
        for i, st in zip(trials, starts)
    ]
    run = dict(
        t0=t0,
        n_steps=T,
        noise_std=cfg["noise"],
        sample_at=cfg.get("sampling", "end"),
        calibration=bool(cfg.get("calibration", False)),
    )
    return truth, starts, seeds, outs, run


def _lockstep_body(field, predictor, cfg: dict, L: int, trials: list[int]) -> list[dict]:
    """The trials together: per loop method one batched run of the engine (one predictor call and one
    planning call per leg for the batch)."""
    from passt_mav.loop.engine import run_trials

    truth, starts, seeds, outs, run = _trial_setup(field, cfg, L, trials)
    for m in cfg["methods"]:
        if m == "model":
            continue
        pred, opts = _loop_options(cfg, m, predictor, L)
        res = run_trials(
            field,
            pred,
            opts,
            starts=[[st] for st in starts],
            seeds=seeds,
            batched=True,
            kernel_cache=_KERNEL_CACHE,
            **run,
        )
        for out, r, i in zip(outs, res, trials):
            _summarise_trial(out, m, r, truth, cfg, i, _drifter_geometry(field))
    return outs


def _serial_body(field, predictor, cfg: dict, L: int, trials: list[int]) -> list[dict]:
    """One trial after another, each method's loop on its own."""
    from passt_mav.loop.engine import run_trials

    truth, starts, seeds, outs, run = _trial_setup(field, cfg, L, trials)
    for out, st, sd, i in zip(outs, starts, seeds, trials):
        for m in cfg["methods"]:
            if m == "model":
                continue
            pred, opts = _loop_options(cfg, m, predictor, L)
            (r,) = run_trials(field, pred, opts, starts=[[st]], seeds=[sd], **run)
            _summarise_trial(out, m, r, truth, cfg, i, _drifter_geometry(field))
    return outs


#: how a unit of work (a path length's trials) drives the engine, by ``engine=`` name: "serial" one
#: trial at a time; "lockstep" the trials together, one batched predictor and planning call per leg
#: (the same numbers for a predictor whose batched and single predictions agree bit for bit)
ENGINES = {"lockstep": _lockstep_body, "serial": _serial_body}


@dataclasses.dataclass
class CampaignOptions:
    """The options of :func:`run_campaign` (its keyword arguments), checked together before any work.

    scheduler: a Dask address string or a ``distributed.Client``. engine: a name in :data:`ENGINES`:
    "serial" (default: one trial after another) or "lockstep" (the trials of one path length advance
    together in batches of ``batch`` (default: all), one predictor call per leg for the batch). A unit
    of work sent to a worker is one batch. gp_solver: "sklearn" (default; a GaussianProcessRegressor
    per leg) or "cholesky" (direct posterior with the fitted kernel; the same reconstruction to
    ~1e-12). Lockstep gives the serial numbers exactly only for predictors whose batched and single
    predictions agree bit for bit (DMD, persistence; tested): a KNODE's batched convolutions round
    differently and a campaign's paths can then diverge (measured on the shipped ocean model), hence
    the serial default. keep_trials: also return the per-trial records (``_trials``, with every leg's
    path) for tests and debugging. fast_predict: run a KNODE through its compiled prediction path
    (:attr:`passt_mav.models.knode.KnodePredictor.fast_predict`, 1.6x, fp32 rounding of the eager
    path) for the model-alone roll-out and every leg, in every worker; other predictors ignore it.
    background: snapshots of the model's roll-out whose anomaly covariance every residual GP
    (PASST's, and the baselines' with ``baseline_prior="forecast"``) adds to its stationary kernels
    (:func:`passt_mav.reconstruction.model_background`); 0 = none. prior_blend: "off", "bma" or "select"
    (:class:`passt_mav.loop.passt.PasstLoop`: every residual loop weighs the model's forecast against
    persistence leg by leg). gp_bias / gp_nugget: the residual GPs' ``bias`` and ``nugget``
    (:class:`passt_mav.reconstruction.GPReconstructor`). prior_share: the blend's fixed share
    (``PasstLoop(share=...)``); prior_forgetting its forgetting factor (``PasstLoop(forgetting=...)``). memory: "off" or "fitted", the information
    prior's per-cell memory of past samples (:class:`passt_mav.loop.memory.CellMemory`; loops with a
    reward that uses the prior). gp_fit_points: the residual GPs' ``max_fit_points`` (samples a leg's
    hyper-parameter fit sees at most, >= 3). model_update: :class:`passt_mav.loop.online.ModelUpdate`
    (learning at sea in every loop with the model; ``None`` = off; serial engine only). calibration: every
    loop computes each leg's posterior std and the results carry, per method and leg-end step, the
    estimate's ``coverage95`` and ``nlpd`` against the truth (:mod:`passt_mav.models.calibration`; the std's
    solve costs GP time; off: no such keys). ``methods`` is kept as a list.
    """

    path_lengths: tuple = (25, 50, 75, 100, 150, 200)
    trials: int = 30
    planner: str = DEFAULT.planner
    reward: str = DEFAULT.reward
    steps: int = 300
    t0: int = 0
    steps_per_leg: int = 10
    noise: float = 0.02
    hyper: str = "every_leg"
    sampling: str = "end"
    baseline_prior: str = "none"
    methods: Sequence[str] = METHODS
    window: int = 50
    snapshot_step: int = 250
    seed: int = 0
    pod_modes: int = 6
    workers: int = 1
    scheduler: object = None
    progress: bool = True
    engine: str = "serial"
    batch: int | None = None
    gp_solver: str = "sklearn"
    keep_trials: bool = False
    fast_predict: bool = False
    background: int = DEFAULT.background
    prior_blend: str = DEFAULT.prior_blend
    gp_bias: bool = DEFAULT.bias
    gp_nugget: str = DEFAULT.nugget
    memory: str = DEFAULT.memory
    gp_fit_points: int = MAX_FIT_POINTS
    prior_share: float = DEFAULT.prior_share
    prior_forgetting: float = DEFAULT.forgetting
    guard: str = DEFAULT.guard
    model_update: object = None
    calibration: bool = True

    def __post_init__(self) -> None:
        self.methods = list(self.methods)


def run_campaign(field, predictor, **options) -> dict:
    """Run the campaign; returns the results dict (JSON-able; RMSE in field units, steps in snapshots).
    ``options``: the fields of :class:`CampaignOptions`. Same seeds give the same numbers whichever
    way the trials are spread.
    """
    import numpy as np

    from passt_mav.loop.passt import run_pure_model

    o = CampaignOptions(**options)
    _check_campaign(field, predictor, o)
    cfg = _campaign_cfg(o, steps=int(min(o.steps, field.n_times - 1 - o.t0)))
    t0, steps = o.t0, cfg["steps"]
    truth = field.data[t0 : t0 + steps + 1].astype(np.float64)
    with _fast_path(predictor, o.fast_predict):
        pure = run_pure_model(field, predictor, t0=t0, n_steps=steps) if "model" in o.methods else None
    tasks = campaign_tasks(o.path_lengths, o.trials, o.engine, o.batch)
    results = _execute(field, predictor, cfg, tasks, workers=o.workers, scheduler=o.scheduler, progress=o.progress)
    results.sort(key=lambda r: (r["L"], r["trial"]))
    summary = _summarise(
        cfg, results, truth, pure, path_lengths=o.path_lengths, trials=o.trials, window=o.window, n_times=field.n_times
    )
    _drifter_summary(summary, results, truth, pure, _drifter_geometry(field))
    if o.keep_trials:
        summary["_trials"] = results
    return summary


#: the options of :class:`CampaignOptions` a unit of work receives as given, in the order the summary's
#: config lists them (``steps`` is replaced by the clipped value)
_TASK_OPTIONS = (
    "seed",
    "t0",
    "steps",
    "steps_per_leg",
    "noise",
    "hyper",
    "sampling",
    "planner",
    "reward",
    "baseline_prior",
    "methods",
    "snapshot_step",
    "pod_modes",
    "engine",
)


def _campaign_cfg(o: CampaignOptions, steps: int) -> dict:
    """The configuration every unit of work receives (and the summary reports), ``steps`` (snapshots)
    already clipped to the field."""
    cfg = {k: getattr(o, k) for k in _TASK_OPTIONS}
    cfg.update(
        steps=steps,
        gp_kw={
            "solver": o.gp_solver,
            "bias": bool(o.gp_bias),
            "nugget": o.gp_nugget,
            **({"max_fit_points": int(o.gp_fit_points)} if int(o.gp_fit_points) != MAX_FIT_POINTS else {}),
        },
        keep_paths=bool(o.keep_trials),
        fast_predict=bool(o.fast_predict),
        background=int(o.background),
        prior_blend=o.prior_blend,
        memory=o.memory,
        prior_share=float(o.prior_share),
        prior_forgetting=float(o.prior_forgetting),
        guard=o.guard,
        model_update=None if o.model_update is None else o.model_update.record(),
        calibration=bool(o.calibration),
    )
    return cfg


def fit_points_problem(n) -> str | None:
    """One line naming a bad ``--gp-fit-points`` (samples a hyper-parameter fit sees: an integer >= 3), or None."""
    import numbers

    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 3:
        return f"--gp-fit-points must be an integer >= 3, got {n!r}"
    return None


def blend_options_problem(share, forgetting) -> str | None:
    """One line naming the prior blend's setting outside [0, 1] (``--prior-share``, ``--prior-forgetting``),
    or None: the campaign's check, and ``passt-mav evaluate``'s before it loads a field."""
    for opt, v in (("--prior-share", share), ("--prior-forgetting", forgetting)):
        if not 0.0 <= float(v) <= 1.0:
            return f"{opt} must lie in [0, 1], got {v!r}"
    return None


def _check_campaign(field, predictor, o: CampaignOptions) -> None:
    """Every option of :func:`run_campaign` checked once, before any work; raises the error naming it."""
    from passt_mav.errors import ModelError, PlannerError
    from passt_mav.loop.online import model_update_problem
    from passt_mav.loop.passt import MEMORIES, PRIOR_BLENDS
    from passt_mav.planning import PLANNERS, REWARDS

    if not o.methods:
        raise PlannerError(f"no methods; choose from {', '.join(METHODS)}")
    for m in o.methods:
        if (problem := method_problem(m)) is not None:
            raise PlannerError(problem)
    if o.planner not in PLANNERS and o.planner != "pg":
        raise PlannerError(f"unknown planner {o.planner!r}; choose one of {', '.join(PLANNERS)}")
    if o.reward not in REWARDS:
        raise PlannerError(f"unknown reward {o.reward!r}; choose one of {', '.join(REWARDS)}")
    if predictor is None and {"passt", "model"} & {m.partition("@")[0] for m in o.methods}:
        raise ModelError("methods 'passt' and 'model' need a predictor")
    if o.trials < 1 or not o.path_lengths or min(o.path_lengths) < 1:
        raise PlannerError("need at least one trial and positive path lengths")
    if not (0 <= o.t0 < field.n_times - 1):
        raise PlannerError(f"--t0 {o.t0} must lie in [0, {field.n_times - 2}]")
    if o.engine not in ENGINES:
        raise PlannerError(f"unknown engine {o.engine!r}; choose one of {', '.join(ENGINES)}")
    if o.hyper not in CAMPAIGN_HYPER:
        raise PlannerError(
            f"unknown GP hyper-parameter schedule {o.hyper!r}; choose one of {', '.join(CAMPAIGN_HYPER)}"
        )
    if o.batch is not None and int(o.batch) < 1:
        raise PlannerError("--batch must be >= 1")
    problem = background_steps_problem(o.background)
    if problem:
        raise PlannerError(f"--background: {problem}")
    if o.prior_blend not in PRIOR_BLENDS:
        raise PlannerError(f"--prior-blend: unknown {o.prior_blend!r}; choose one of {', '.join(PRIOR_BLENDS)}")
    problem = blend_options_problem(o.prior_share, o.prior_forgetting)
    if problem:
        raise PlannerError(problem)
    if o.memory not in MEMORIES:
        raise PlannerError(f"--memory: unknown {o.memory!r}; choose one of {', '.join(MEMORIES)}")
    problem = fit_points_problem(o.gp_fit_points)
    if problem:
        raise PlannerError(problem)
    problem = model_update_problem(o.model_update)
    if problem:
        raise PlannerError(problem)
    if o.model_update is not None and o.model_update.online == "on" and o.engine != "serial":
        raise PlannerError("--model-update on gives each trial its own model: use --engine serial")


def _summarise(
    cfg: dict, results: list[dict], truth, pure, *, path_lengths, trials: int, window: int, n_times: int
) -> dict:
    """The campaign's results dict from the per-trial records (sorted by (L, trial)): per path length
    the mean / std RMSE over time, final-window RMSE, POD energy, planning time; snapshots; timings."""
    from passt_mav.fields.analysis import pod_energy

    steps, pod_modes, methods = cfg["steps"], cfg["pod_modes"], cfg["methods"]
    w = max(1, min(window, steps))
    summary: dict = {
        "config": dict(cfg, path_lengths=list(map(int, path_lengths)), trials=trials, window=w, n_times=n_times),
        "per_L": {},
    }
    summary["pod_truth"] = pod_energy(truth, pod_modes, cumulative=False).tolist()
    snaps = {"truth": truth[min(cfg["snapshot_step"], steps)].tolist()}
    pure_rmse = None
    if pure is not None:
        pure_rmse = _rmse_series(pure, truth)
        summary["pod_model"] = pod_energy(pure, pod_modes, cumulative=False).tolist()
        snaps["model"] = pure[min(cfg["snapshot_step"], steps)].tolist()
    summary["baselines"] = _trivial_maps(truth, pure)
    for L in path_lengths:
        rs = [r for r in results if r["L"] == L]
        summary["per_L"][str(L)] = _per_length(rs, methods, pure_rmse, summary.get("pod_model"), w)
        summary["per_L"][str(L)]["beats_trivial"] = _beats_trivial(summary["per_L"][str(L)], summary["baselines"], w)
        r0 = next(r for r in rs if r["trial"] == 0)
        snaps.update({f"{m}@L{L}": r0["snap"][m] for m in r0["snap"]})
    summary["_snapshots"] = snaps
    # compute seconds per component summed over every trial-leg (predict: a batch's time / B)
    tim: dict = {}
    for r in results:
        for m, d in r.get("timings_s", {}).items():
            for k, v in d.items():
                tim.setdefault(m, {}).setdefault(k, 0.0)
                tim[m][k] += v
    summary["timings_s"] = tim
    summary["trial_legs"] = len(results) * sum(1 for m in methods if m != "model") * -(-steps // cfg["steps_per_leg"])
    return summary


def _drifter_summary(summary: dict, results: list[dict], truth, pure, geom) -> None:
    """Per path length ``drifter_sep_km`` and ``drifter_km_per_day``: per method the mean over its trials of
    the virtual drifters' separation after the whole horizon (:func:`_drifters`), with "model" (the model
    alone) and "persistence" (the first true snapshot held fixed: the usual reference) beside the loops;
    ``drifter_horizon_h`` (hours) and ``drifter_n`` (drifters). Nothing without a geometry."""
    import numpy as np

    if geom is None:
        return
    refs = {"persistence": _drifters(np.broadcast_to(truth[:1], truth.shape), truth, geom)}
    if pure is not None:
        refs["model"] = _drifters(pure, truth, geom)
    for L, per in summary["per_L"].items():
        rs = [r for r in results if str(r["L"]) == L]
        runs = {m: [r["drifters"][m] for r in rs if m in r.get("drifters", {})] for m in summary["config"]["methods"]}
        runs.update({k: [v] for k, v in refs.items() if v is not None})
        runs = {m: d for m, d in runs.items() if d}
        if not runs:
            continue
        per["drifter_sep_km"] = {m: float(np.mean([d["sep_km"] for d in ds])) for m, ds in runs.items()}
        per["drifter_km_per_day"] = {m: float(np.mean([d["km_per_day"] for d in ds])) for m, ds in runs.items()}
        first = next(iter(runs.values()))[0]
        per["drifter_horizon_h"], per["drifter_n"] = first["horizon_h"], first["n"]


def _per_length(rs: list[dict], methods, pure_rmse, pod_model, w: int) -> dict:
    """One path length's summary from its trials' records ``rs`` (final window ``w`` steps)."""
    import numpy as np

    per: dict = {"rmse_mean": {}, "rmse_std": {}, "final_rmse": {}, "final_rmse_std": {}, "pod": {}, "plan_ms": {}}
    for m in methods:
        if m == "model":
            a = np.repeat(pure_rmse[None], len(rs), axis=0)
            per["pod"][m] = pod_model
        else:
            a = np.array([r["rmse"][m] for r in rs])
            per["pod"][m] = np.mean([r["pod"][m] for r in rs], axis=0).tolist()
            per["plan_ms"][m] = float(np.mean([r["plan_ms"][m] for r in rs]))
        per["rmse_mean"][m] = a.mean(0).tolist()
        per["rmse_std"][m] = a.std(0).tolist()
        fin = a[:, -w:].mean(1)
        per["final_rmse"][m] = float(fin.mean())
        per["final_rmse_std"][m] = float(fin.std())
        _calibration_means(per, m, rs)
        counts = [r["model_update"][m] for r in rs if m in r.get("model_update", {})]
        if counts:  # learning at sea, summed over the trials
            per.setdefault("model_update", {})[m] = {k: sum(c[k] for c in counts) for k in counts[0]}
    if "passt" in methods:
        ref = per["final_rmse"]["passt"]  # 0 where PASST's map is exact (a steady field, a persistence model)
        per["ratio_to_passt"] = {m: per["final_rmse"][m] / ref if ref > 0 else float("nan") for m in methods}
    per["starts"] = [r["start"] for r in rs]
    return per


def _calibration_means(per: dict, m: str, rs: list[dict]) -> None:
    """Method ``m``'s calibration over its trials ``rs``, into ``per``: ``calibration_steps`` (leg-end steps),
    ``coverage95_mean`` and ``nlpd_mean`` (mean over the trials that scored each step; None where none did)."""
    import numpy as np

    recs = [r["calibration"][m] for r in rs if m in r.get("calibration", {})]
    if not recs:
        return
    steps = sorted({s for c in recs for s in c["step"]})
    per.setdefault("calibration_steps", {})[m] = steps
    for key in ("coverage95", "nlpd"):
        cols = []
        for st in steps:
            vals = [c[key][c["step"].index(st)] for c in recs if st in c["step"]]
            vals = [float(v) for v in vals if v is not None and np.isfinite(v)]
            cols.append(float(np.mean(vals)) if vals else None)
        per.setdefault(f"{key}_mean", {})[m] = cols


def _trivial_maps(truth, pure) -> dict:
    """RMSE over time (field units) of the trivial maps against ``truth`` (T+1, 2, R, C): ``rmse_zero`` (no
    current) and, with the model alone ``pure``, ``rmse_forecast_mean`` (its time mean over the campaign)."""
    import numpy as np

    out = {"rmse_zero": _rmse_series(np.where(np.isfinite(truth), 0.0, np.nan), truth).tolist()}
    if pure is not None:
        fm = np.nanmean(np.asarray(pure, np.float64), axis=0)
        out["rmse_forecast_mean"] = _rmse_series(np.broadcast_to(fm, truth.shape), truth).tolist()
    return out


def _beats_trivial(per: dict, baselines: dict, w: int) -> dict:
    """Per method: whether its final-window RMSE is below every trivial map's over the same window."""
    import numpy as np

    fin = {k.removeprefix("rmse_"): float(np.mean(v[-w:])) for k, v in baselines.items()}
    return {m: all(per["final_rmse"][m] < x for x in fin.values()) for m in per["final_rmse"]}


def fleet_starts(field, seed: int, trial: int, L: int, n: int) -> list[tuple[int, int]]:
    """``n`` distinct water cells for a trial's boats; the first is the one-boat campaign's start."""
    import numpy as np

    first = _start_cell(field, {"seed": seed}, L, trial)
    rng = np.random.default_rng([seed + trial, L, 7])
    water = [tuple(int(x) for x in w) for w in np.argwhere(~field.land_mask) if tuple(int(x) for x in w) != first]
    pick = rng.choice(len(water), size=n - 1, replace=False) if n > 1 else []
    return [first] + [water[j] for j in pick]


def fleet_comparison(
    field,
    predictor,
    *,
    boats: int,
    path_length: int,
    trials: int = 10,
    planner: str | None = None,
    reward: str | None = None,
    steps: int = 300,
    t0: int = 0,
    steps_per_leg: int = 10,
    noise: float = 0.02,
    hyper: str = "every_leg",
    sampling: str = "end",
    window: int = 50,
    seed: int = 0,
    progress: bool = True,
    background: int | None = None,
    preset: Preset = DEFAULT,
) -> dict:
    """PASST with 1..``boats`` boats of ``path_length`` moves each, and one boat of ``boats`` x
    ``path_length`` moves (the fleet's budget in one path), over ``trials`` seeded trials
    (:func:`passt_mav.loop.engine.run_trials`, one trial of N boats per run). Returns per configuration
    the mean RMSE over time, the final-window mean and each trial's final-window value (field units).
    ``preset``: the loop's configuration (:mod:`passt_mav.loop.presets`); ``planner``, ``reward`` and
    ``background`` (as in :func:`run_campaign`) replace its own where given."""
    configs = [(f"{n} boat{'s' if n > 1 else ''} x {path_length}", n, path_length) for n in range(1, boats + 1)]
    configs.append((f"1 boat x {boats * path_length}", 1, boats * path_length))
    T = int(min(steps, field.n_times - 1 - t0))
    config = {
        "boats": boats,
        "path_length": path_length,
        "trials": trials,
        "steps": T,
        "t0": t0,
        "steps_per_leg": steps_per_leg,
        "noise": noise,
        "window": window,
        "seed": seed,
        "hyper": hyper,
        "sampling": sampling,
        **preset.as_dict(),
        **{k: v for k, v in dict(planner=planner, reward=reward, background=background).items() if v is not None},
    }
    series = _fleet_series(field, predictor, configs, config, progress=progress)
    return {"config": config, "runs": _fleet_runs(configs, series, window)}


def _fleet_series(field, predictor, configs: list[tuple], config: dict, *, progress: bool) -> dict[str, list]:
    """Per fleet configuration (name, boats, moves per boat) its trials' RMSE-over-time series (field
    units, ``config["steps"] + 1`` snapshots each), one engine run of all its boats per trial."""
    from threadpoolctl import threadpool_limits

    from passt_mav.loop.engine import run_trials
    from passt_mav.loop.passt import LoopOptions
    from passt_mav.progress import progress as _progress

    t0, T, seed = config["t0"], config["steps"], config["seed"]
    truth = field.data[t0 : t0 + T + 1].astype("float64")
    preset = Preset(**{k: config[k] for k in Preset.__dataclass_fields__})
    base = LoopOptions(
        **preset.loop_kwargs(),
        gp_kw=preset.gp_kwargs(),
        steps_per_leg=config["steps_per_leg"],
        hyper=_hyper_for(config["hyper"], residual=True),
    )
    it = _progress(
        [(name, n, L, i) for name, n, L in configs for i in range(config["trials"])],
        "fleet comparison",
        "trial",
        quiet=not progress,
    )
    series: dict[str, list] = {}
    with threadpool_limits(1):  # the campaign's rule: one BLAS thread, the same numbers everywhere
        for name, n, L, i in it:
            (r,) = run_trials(
                field,
                predictor,
                LoopOptions.of(base, path_length=L),
                starts=[fleet_starts(field, seed, i, config["path_length"], n)],
                seeds=[seed + i],
                t0=t0,
                n_steps=T,
                noise_std=config["noise"],
                sample_at=config["sampling"],
            )
            series.setdefault(name, []).append(_rmse_series(r.estimate, truth))
    return series


def _fleet_runs(configs: list[tuple], series: dict[str, list], window: int) -> dict:
    """Per fleet configuration: its mean RMSE over time and the final-window (``window`` steps) RMSE,
    mean and per trial (field units)."""
    import numpy as np

    runs = {}
    for name, n, L in configs:
        arr = np.array(series[name])
        finals = arr[:, -window:].mean(axis=1)
        runs[name] = {
            "boats": n,
            "path_length": L,
            "rmse_mean": arr.mean(axis=0).tolist(),
            "final_rmse": float(finals.mean()),
            "final_rmse_trials": finals.tolist(),
        }
    return runs


def campaign_tasks(
    path_lengths, trials: int, engine: str = "lockstep", batch: int | None = None
) -> list[tuple[int, tuple[int, ...]]]:
    """Units of work: (L, trial indices). Serial engine: one trial each; lockstep: batches."""
    if engine == "serial":
        return [(int(L), (i,)) for L in path_lengths for i in range(trials)]
    b = int(batch) if batch else trials
    return [(int(L), tuple(range(a, min(a + b, trials)))) for L in path_lengths for a in range(0, trials, b)]


def _execute(field, predictor, cfg, tasks, *, workers, scheduler, progress) -> list[dict]:
    from passt_mav.progress import progress as _progress

    # a bar with ETA on a terminal, a plain line every 10 % (or 30 s) in a log
    bar = _progress(sum(len(tr) for _, tr in tasks), "evaluate", "trial", quiet=not progress)
    out = []
    # longest first (a task's time grows with its path length): parallel workers then
    # finish together instead of one of them running the longest task alone at the end;
    # the results are sorted by (L, trial) afterwards, so the order changes no number
    longest_first = sorted(tasks, key=lambda task: -int(task[0]))
    try:
        if scheduler is not None:
            from distributed import Client, as_completed

            client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
            try:
                f_fut = client.scatter(field, broadcast=True)
                p_fut = client.scatter(predictor, broadcast=True)
                futs = [
                    client.submit(_task, f_fut, p_fut, cfg, L, tr, pure=False, priority=-i)
                    for i, (L, tr) in enumerate(longest_first)
                ]
                for fut in as_completed(futs):
                    rs = fut.result()
                    out.extend(rs)
                    bar.update(len(rs))
            finally:
                if client is not scheduler:
                    client.close()
        elif workers > 1:
            from joblib import Parallel, delayed

            jobs = (delayed(_task)(field, predictor, cfg, L, tr) for L, tr in longest_first)
            for rs in Parallel(n_jobs=workers, return_as="generator_unordered")(jobs):
                out.extend(rs)
                bar.update(len(rs))
        else:
            for L, tr in tasks:
                rs = _task(field, predictor, cfg, L, tr)
                out.extend(rs)
                bar.update(len(rs))
    finally:
        bar.close()
    return out


def load_predictor(spec: str, field):
    """The predictor ``spec`` names: a name in ``PREDICTORS`` (fitted on ``field``), ``builtin:*`` or a
    checkpoint (loaded; its validation skill printed on stderr)."""
    from passt_mav.errors import ModelError

    try:
        from passt_mav.models.base import PREDICTORS, load_predictor, make_predictor
    except ImportError as exc:  # the predictors package is not installed in this build
        raise ModelError(f"predictors are not available ({exc})") from None
    if spec in PREDICTORS:
        return make_predictor(spec).fit(field)
    p = load_predictor(spec)
    from passt_mav.models.evaluate import echo_skill

    # the skill line goes to stderr so that --json output stays one JSON document
    echo_skill(spec, getattr(p, "metadata_", None), lambda m: print(m, file=sys.stderr))
    return p
