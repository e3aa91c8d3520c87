"""passt-mav evaluate: offline PASST campaign - trials x path lengths, RMSE over time and POD energy.

For every path length L (area covered per re-initialisation) and every trial
(seed ``seed + trial``, random water start cell), the field is estimated over
``--steps`` snapshots from the true state at ``--t0`` by:

* ``passt``        - the PASST loop: model forecast, one-step reward, planner, GP on
                     the residual vs the forecast, re-initialise, repeat;
* ``model``        - the model alone from the true initial state (no re-initialisation);
* ``lawnmower_gp`` / ``greedy_gp`` / ``random_gp`` - that planner's samples
                     reconstructed by a GP alone (constant prior mean), the estimate
                     held between legs (the paper's baselines); with
                     ``--baseline-prior forecast`` they instead run the full loop with
                     the model, so only the planner differs.

Reported: RMSE over time (mean +- std over trials), POD energy of the estimated
vs true series, and the ratio of each method's final-window RMSE to PASST's.
Written under --out: ``results.json`` and PNG figures; the directory is named at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import sys

from passt_mav.reconstruction.background import DEFAULT_BACKGROUND, background_steps_problem

HELP = "Offline PASST campaign: trials x path lengths, RMSE over time and POD energy"
EXAMPLES = """examples:
  passt-mav evaluate --data builtin:cylinder --model builtin:cylinder --out runs/eval_cyl
  passt-mav evaluate --data builtin:oscillating --model builtin:cylinder --trials 10 --path-lengths 50,100 --out runs/eval_osc
  passt-mav evaluate --data builtin:ocean --model dmd --reward vorticity --workers 2 --json --out runs/eval_ocean
  passt-mav evaluate --data builtin:cylinder --model builtin:cylinder --scheduler tcp://127.0.0.1:8786 --out runs/eval_dask
"""

METHODS = ("passt", "model", "lawnmower_gp", "greedy_gp", "random_gp")
ENGINES = ("lockstep", "serial")
DEFAULT_PATH_LENGTHS = "25,50,75,100,150,200"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, help="field: builtin:cylinder | builtin:oscillating | builtin:ocean | FILE.nc")
    p.add_argument("--model", required=True, help="predictor: builtin:cylinder | builtin:ocean | CHECKPOINT | a predictor name (fitted on --data)")
    p.add_argument("--trials", type=int, default=30, help="trials per path length (default 30)")
    p.add_argument("--path-lengths", default=DEFAULT_PATH_LENGTHS, help=f"comma-separated moves per leg (default {DEFAULT_PATH_LENGTHS})")
    p.add_argument("--planner", default="policy_gradient", help="PASST's planner (default policy_gradient)")
    p.add_argument("--reward", default="speed", help="reward map: speed | vorticity | std | speed_std | change (the predicted change over the leg) (default speed)")
    p.add_argument("--steps", type=int, default=300, help="snapshots estimated after the start (default 300, clipped to the data)")
    p.add_argument("--t0", type=int, default=0, help="start snapshot index (default 0)")
    p.add_argument("--steps-per-leg", type=int, default=10, help="snapshots one leg spans = re-initialisation interval (default 10)")
    p.add_argument("--noise", type=float, default=0.02, help="sensor noise std, field units (default 0.02)")
    p.add_argument("--sampling", choices=("end", "spread"), default="end", help="when a leg's cells are read: all at the leg's end (default; the paper's offline protocol, one snapshot per leg) or spread over the leg at constant speed")
    p.add_argument("--hyper", default="every_leg", help="GP hyper-parameter fits: every_leg | first_leg | state | auto (residual GPs every leg, sample-only GPs once on the initial state) (default every_leg)")
    p.add_argument("--baseline-prior", choices=("none", "forecast"), default="none", help="baselines: GP alone (none, default) or the full loop with the model (forecast)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"subset of {','.join(METHODS)}; also PLANNER_gp for any planner (e.g. information_gp) and METHOD@REWARD (e.g. passt@variance_reduction) to compare planners and rewards in one loop")
    p.add_argument("--window", type=int, default=50, help="final window (steps) for the ratio table (default 50)")
    p.add_argument("--snapshot-step", type=int, default=250, help="step of the 2-D snapshot figure (default 250, clipped)")
    p.add_argument("--seed", type=int, default=0, help="base seed (trial i uses seed + i)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (joblib; default 1)")
    p.add_argument("--scheduler", default=None, help="address of an existing Dask distributed scheduler (runs trials there)")
    p.add_argument("--engine", choices=ENGINES, default="serial", help="serial (default: one trial at a time) or lockstep (a path length's trials advance together, one batched predictor call per leg and one batched policy-gradient planning call; 2.4x the serial engine's trial-legs/s with the same GP options, benchmarks/bench_passt.py, 15 trials). Same numbers for predictors whose batched and single predictions agree bit for bit (DMD, persistence); with the KNODE, batched convolutions round differently and paths can diverge (shipped ocean model, L=50, 2 trials: PASST 0.2445 lockstep vs 0.2550 serial)")
    p.add_argument("--batch", type=int, default=None, help="lockstep: trials per batch = unit of work for --workers/--scheduler (default: all trials of a path length)")
    p.add_argument("--gp-solver", choices=("cholesky", "sklearn"), default="sklearn", help="GP posterior with the fitted kernel: sklearn's regressor (default) or a direct Cholesky solve (faster; equal to sklearn to 1e-6 per reconstruction, which a long campaign can amplify into different paths)")
    p.add_argument("--fast-predict", action="store_true", help="run a KNODE through its compiled prediction path (torch.compile with freezing: ~1.6x, fp32 rounding of the eager path, a few seconds of compiling per batch shape; what passt-mav paper uses)")
    p.add_argument("--background", type=int, default=DEFAULT_BACKGROUND, metavar="STEPS", help=f"residual GPs (PASST's; the baselines' with --baseline-prior forecast) add a model-based background covariance: the anomalies of STEPS snapshots of the model's roll-out from the initial state (ensemble optimal interpolation) (default {DEFAULT_BACKGROUND}; 0 = stationary kernels only)")
    p.add_argument("--prior-blend", choices=("off", "bma"), default="off", help="residual GPs' prior mean: the model's forecast (off, default) or bma: the model's forecast and persistence weighed leg by leg by how well each explains the leg's samples (Bayesian model averaging with a forgetting factor)")
    p.add_argument("--gp-bias", action="store_true", help="the residual GP may add a constant offset over the region (u, v), kept only where the samples' likelihood pays for it (GPReconstructor bias)")
    p.add_argument("--boats", type=int, default=1, help="N > 1: the fleet comparison instead of the campaign: "
                   "PASST with 1..N boats of L moves each vs 1 boat of N*L moves per leg interval (the same "
                   "budget), L = the first of --path-lengths; writes fleet.json and fleet_rmse.png")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--out", required=True, help="output directory")


# -- campaign (importable; numpy etc. imported inside) ---------------------------


def _rmse_series(est, truth):
    import numpy as np

    d = (est.astype(np.float64) - truth) ** 2
    return np.sqrt(np.nanmean(d.reshape(d.shape[0], -1), axis=1))


def _trial(field, predictor, cfg: dict, L: int, trial: int) -> dict:
    """One trial at path length L: every loop method's RMSE series (+ snapshots for trial 0)."""
    return _task(field, predictor, cfg, L, (trial,))[0]


def _task(field, predictor, cfg: dict, L: int, trials) -> list[dict]:
    """Trials ``trials`` at path length L, one result dict per trial (see :func:`_trial_body`).

    ``cfg["engine"] == "lockstep"``: the trials advance together, one predictor call
    per leg for all of them (:func:`passt_mav.passt.run_offline_lockstep`); "serial":
    one trial after another (the original path).

    Runs with one BLAS thread wherever it runs: a multi-threaded BLAS sums in a
    different order, and a last-bit difference can flip a planner's argmax, so the
    same seeds would give different numbers in the main process, a joblib worker
    and a Dask worker.
    """
    from threadpoolctl import threadpool_limits

    torch = sys.modules.get("torch")  # a torch predictor: its reductions too
    prev = torch.get_num_threads() if torch is not None else None
    try:
        if torch is not None:
            torch.set_num_threads(1)
        with threadpool_limits(1), _fast_path(predictor, cfg.get("fast_predict", False)), _heap_reuse():
            if cfg.get("engine", "serial") == "lockstep":
                return _lockstep_body(field, predictor, cfg, L, list(trials))
            return [_trial_body(field, predictor, cfg, L, i) for i in trials]
    finally:
        if torch is not None:
            torch.set_num_threads(prev)


@contextlib.contextmanager
def _heap_reuse():
    """Keep glibc's allocator reusing freed heap memory inside the block, where the
    environment froze its thresholds (a no-op elsewhere).

    A campaign allocates and frees arrays of 0.1-2 MB thousands of times per leg (roll-out
    tables, GP cross-covariances, model activations). Dask's nanny starts workers with
    ``MALLOC_TRIM_THRESHOLD_=65536``, which also freezes glibc's mmap threshold at 128 KiB:
    every such array is then a fresh mmap, page-faulted in and unmapped again. Measured on
    one lockstep batch (cylinder, L=200, 15 trials, PASST and random+GP): that environment
    made the model's predictions 25 % and the GP 80 % slower (7x the system time); in a
    Dask worker the batch took 61 s without this and 49 s with it, as in a plain process.
    Without such a variable glibc's dynamic threshold already reuses the heap, so nothing
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
    if sys.platform.startswith("linux") and ("MALLOC_TRIM_THRESHOLD_" in os.environ or "MALLOC_MMAP_THRESHOLD_" in os.environ):
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


#: GP hyper-parameter schedules of a campaign: passt_mav.passt.HYPER, or "auto" = each GP fitted
#: on what it models: a GP on the residual vs the forecast on every leg's residuals
#: ("every_leg": the model's error grows and changes shape over a campaign), a GP on the
#: samples alone once on the initial state ("state"). A residual GP whose kernel was fitted on
#: the whole field (variance and length scale of the flow, not of the model's error) spreads
#: every leg's noisy residuals far and wide: measured with the shipped KNODEs, 2 trials, PASST
#: final-window RMSE ocean L=100 0.52 with "state" vs 0.062 with "first_leg" (0.053
#: every_leg); cylinder L=50 0.44 vs 0.16 (0.10). With the background covariance (200
#: snapshots, factor fixed at 1), 6 trials, L=50: ocean 0.0832 first_leg vs 0.0564 every_leg;
#: without it 0.0810 vs 0.0693 (the model alone: 0.0756).
CAMPAIGN_HYPER = ("every_leg", "first_leg", "state", "auto")


def _hyper_for(hyper: str, residual: bool) -> str:
    """The :data:`passt_mav.passt.HYPER` schedule of one GP: ``auto`` resolved by what it models."""
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
        return (f"unknown method {m!r}; choose from {', '.join(METHODS)}, PLANNER_gp or PLANNER_loop with PLANNER one of "
                f"{', '.join(PLANNERS)}")
    if reward and (base == "model" or reward not in REWARDS):
        return f"method {m!r}: unknown reward {reward!r} (or a method that plans nothing); rewards: {', '.join(REWARDS)}"
    return None


def _method_kw(cfg: dict, m: str, predictor) -> tuple:
    """(predictor, run_offline options) of loop method ``m`` (its GP schedule included)."""
    h = cfg["hyper"]
    base, _, reward = m.partition("@")
    planner = cfg["planner"] if base == "passt" else base.rsplit("_", 1)[0]  # PLANNER_gp / PLANNER_loop
    if base == "passt" or base.endswith("_loop") or cfg["baseline_prior"] == "forecast":
        return predictor, dict(planner=planner, reward=reward or cfg["reward"], prior="forecast", hyper=_hyper_for(h, residual=True))
    return None, dict(planner=planner, reward=reward or "speed", prior="none", hyper=_hyper_for(h, residual=False))


def _summarise_trial(out: dict, m: str, r, truth, cfg: dict, trial: int) -> None:
    import numpy as np

    from passt_mav.fields.analysis import pod_energy

    out["rmse"][m] = _rmse_series(r.estimate, truth).tolist()
    out["pod"][m] = pod_energy(r.estimate, cfg["pod_modes"], cumulative=False).tolist()
    out["plan_ms"][m] = float(np.mean([leg["timings"]["plan"] for leg in r.legs]) * 1e3)
    out.setdefault("timings_s", {})[m] = {k: float(sum(leg["timings"].get(k, 0.0) for leg in r.legs)) for k in ("predict", "reward", "plan", "gp")}
    if cfg.get("keep_paths"):
        out.setdefault("paths", {})[m] = [leg["path"] for leg in r.legs]
    if trial == 0:
        k = min(cfg["snapshot_step"], cfg["steps"])
        out["snap"][m] = r.estimate[k].tolist()


def _lockstep_body(field, predictor, cfg: dict, L: int, trials: list[int]) -> list[dict]:
    from passt_mav.passt import run_offline_lockstep

    t0, T = cfg["t0"], cfg["steps"]
    truth = field.data[t0 : t0 + T + 1].astype("float64")
    starts = [_start_cell(field, cfg, L, i) for i in trials]
    seeds = [int(cfg["seed"]) + i for i in trials]
    outs = [{"L": L, "trial": i, "start": list(st), "rmse": {}, "pod": {}, "snap": {}, "plan_ms": {}} for i, st in zip(trials, starts)]
    common = dict(t0=t0, n_steps=T, path_length=L, steps_per_leg=cfg["steps_per_leg"], noise_std=cfg["noise"], sample_at=cfg.get("sampling", "end"), gp_kw=cfg.get("gp_kw"), kernel_cache=_KERNEL_CACHE, background=cfg.get("background", 0), prior_blend=cfg.get("prior_blend", "off"))
    for m in cfg["methods"]:
        if m == "model":
            continue
        pred, kw = _method_kw(cfg, m, predictor)
        res = run_offline_lockstep(field, pred, start_cells=starts, seeds=seeds, **kw, **common)
        for out, r, i in zip(outs, res, trials):
            _summarise_trial(out, m, r, truth, cfg, i)
    return outs


def _trial_body(field, predictor, cfg: dict, L: int, trial: int) -> dict:
    from passt_mav.passt import run_offline

    seed = int(cfg["seed"]) + trial
    start = _start_cell(field, cfg, L, trial)
    t0, T = cfg["t0"], cfg["steps"]
    truth = field.data[t0 : t0 + T + 1].astype("float64")
    common = dict(start_cell=start, t0=t0, n_steps=T, path_length=L, steps_per_leg=cfg["steps_per_leg"], noise_std=cfg["noise"], sample_at=cfg.get("sampling", "end"), gp_kw=cfg.get("gp_kw"), seed=seed, background=cfg.get("background", 0), prior_blend=cfg.get("prior_blend", "off"))
    out: dict = {"L": L, "trial": trial, "start": list(start), "rmse": {}, "pod": {}, "snap": {}, "plan_ms": {}}
    for m in cfg["methods"]:
        if m == "model":
            continue
        pred, kw = _method_kw(cfg, m, predictor)
        r = run_offline(field, pred, **kw, **common)
        _summarise_trial(out, m, r, truth, cfg, trial)
    return out


def run_campaign(field, predictor, *, path_lengths=(25, 50, 75, 100, 150, 200), trials: int = 30, planner: str = "policy_gradient", reward: str = "speed", steps: int = 300, t0: int = 0, steps_per_leg: int = 10, noise: float = 0.02, hyper: str = "every_leg", sampling: str = "end", baseline_prior: str = "none", methods=METHODS, window: int = 50, snapshot_step: int = 250, seed: int = 0, pod_modes: int = 6, workers: int = 1, scheduler=None, progress: bool = True, engine: str = "serial", batch: int | None = None, gp_solver: str = "sklearn", keep_trials: bool = False, fast_predict: bool = False, background: int = 0, prior_blend: str = "off", gp_bias: bool = False) -> dict:
    """Run the campaign; returns the results dict (JSON-able). ``scheduler``: a Dask
    address string or a ``distributed.Client``. Same seeds give the same numbers
    whichever way the trials are spread.

    engine: "serial" (default: one trial after another, the original path) or
    "lockstep" (the trials of one path length advance together in batches of ``batch``
    (default: all), one predictor call per leg for the batch). A unit of work sent to a
    worker is one batch. gp_solver: "sklearn" (default; a GaussianProcessRegressor per
    leg) or "cholesky" (direct posterior with the fitted kernel; the same reconstruction
    to ~1e-12). Lockstep gives the serial numbers exactly only for predictors whose
    batched and single predictions agree bit for bit (DMD, persistence; tested): a
    KNODE's batched convolutions round differently and a campaign's paths can then
    diverge (measured on the shipped ocean model), hence the serial default.
    keep_trials: also return the per-trial records (``_trials``, with every leg's path)
    for tests and debugging. fast_predict: run a KNODE through its compiled prediction
    path (:attr:`passt_mav.models.knode.KnodePredictor.fast_predict`, 1.6x, fp32
    rounding of the eager path) for the model-alone roll-out and every leg, in every
    worker; other predictors ignore it. background: snapshots of the model's roll-out
    whose anomaly covariance every residual GP (PASST's, and the baselines' with
    ``baseline_prior="forecast"``) adds to its stationary kernels
    (:func:`passt_mav.reconstruction.model_background`); 0 = none. prior_blend: "off" or
    "bma" (:class:`passt_mav.passt.PasstLoop`: every residual loop weighs the model's forecast
    against persistence leg by leg).
    """
    import numpy as np

    from passt_mav.errors import PlannerError
    from passt_mav.fields.analysis import pod_energy
    from passt_mav.passt import run_pure_model
    from passt_mav.planning import PLANNERS, REWARDS

    methods = list(methods)
    if not methods:
        raise PlannerError(f"no methods; choose from {', '.join(METHODS)}")
    for m in methods:
        if (problem := method_problem(m)) is not None:
            raise PlannerError(problem)
    if planner not in PLANNERS and planner != "pg":
        raise PlannerError(f"unknown planner {planner!r}; choose one of {', '.join(PLANNERS)}")
    if reward not in REWARDS:
        raise PlannerError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
    if predictor is None and {"passt", "model"} & {m.partition("@")[0] for m in methods}:
        from passt_mav.errors import ModelError

        raise ModelError("methods 'passt' and 'model' need a predictor")
    if trials < 1 or not path_lengths or min(path_lengths) < 1:
        raise PlannerError("need at least one trial and positive path lengths")
    if not (0 <= t0 < field.n_times - 1):
        raise PlannerError(f"--t0 {t0} must lie in [0, {field.n_times - 2}]")
    if engine not in ENGINES:
        raise PlannerError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
    if hyper not in CAMPAIGN_HYPER:
        raise PlannerError(f"unknown GP hyper-parameter schedule {hyper!r}; choose one of {', '.join(CAMPAIGN_HYPER)}")
    if batch is not None and int(batch) < 1:
        raise PlannerError("--batch must be >= 1")
    problem = background_steps_problem(background)
    if problem:
        raise PlannerError(f"--background: {problem}")
    from passt_mav.passt import PRIOR_BLENDS

    if prior_blend not in PRIOR_BLENDS:
        raise PlannerError(f"--prior-blend: unknown {prior_blend!r}; choose one of {', '.join(PRIOR_BLENDS)}")
    steps = int(min(steps, field.n_times - 1 - t0))
    cfg = dict(seed=seed, t0=t0, steps=steps, steps_per_leg=steps_per_leg, noise=noise, hyper=hyper, sampling=sampling, planner=planner, reward=reward, baseline_prior=baseline_prior, methods=methods, snapshot_step=snapshot_step, pod_modes=pod_modes, engine=engine, gp_kw={"solver": gp_solver, **({"bias": True} if gp_bias else {})}, keep_paths=bool(keep_trials), fast_predict=bool(fast_predict), background=int(background), prior_blend=prior_blend)
    truth = field.data[t0 : t0 + steps + 1].astype(np.float64)
    with _fast_path(predictor, fast_predict):
        pure = run_pure_model(field, predictor, t0=t0, n_steps=steps) if "model" in methods else None
    tasks = campaign_tasks(path_lengths, trials, engine, batch)
    results = _execute(field, predictor, cfg, tasks, workers=workers, scheduler=scheduler, progress=progress)
    results.sort(key=lambda r: (r["L"], r["trial"]))

    w = max(1, min(window, steps))
    summary: dict = {"config": dict(cfg, path_lengths=list(map(int, path_lengths)), trials=trials, window=w, n_times=field.n_times), "per_L": {}}
    summary["pod_truth"] = pod_energy(truth, pod_modes, cumulative=False).tolist()
    snaps = {"truth": truth[min(snapshot_step, steps)].tolist()}
    if pure is not None:
        pure_rmse = _rmse_series(pure, truth)
        summary["pod_model"] = pod_energy(pure, pod_modes, cumulative=False).tolist()
        snaps["model"] = pure[min(snapshot_step, steps)].tolist()
    for L in path_lengths:
        rs = [r for r in results if r["L"] == L]
        per: dict = {"rmse_mean": {}, "rmse_std": {}, "final_rmse": {}, "final_rmse_std": {}, "pod": {}, "plan_ms": {}}
        for m in methods:
            if m == "model":
                a = np.repeat(pure_rmse[None], len(rs), axis=0)
                per["pod"][m] = summary["pod_model"]
            else:
                a = np.array([r["rmse"][m] for r in rs])
                per["pod"][m] = np.mean([r["pod"][m] for r in rs], axis=0).tolist()
                per["plan_ms"][m] = float(np.mean([r["plan_ms"][m] for r in rs]))
            per["rmse_mean"][m] = a.mean(0).tolist()
            per["rmse_std"][m] = a.std(0).tolist()
            fin = a[:, -w:].mean(1)
            per["final_rmse"][m] = float(fin.mean())
            per["final_rmse_std"][m] = float(fin.std())
        if "passt" in methods:
            per["ratio_to_passt"] = {m: per["final_rmse"][m] / per["final_rmse"]["passt"] for m in methods}
        per["starts"] = [r["start"] for r in rs]
        summary["per_L"][str(L)] = per
        r0 = [r for r in rs if r["trial"] == 0][0]
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
    summary["trial_legs"] = len(results) * sum(1 for m in methods if m != "model") * -(-steps // steps_per_leg)
    if keep_trials:
        summary["_trials"] = results
    return summary


def _fleet_starts(field, seed: int, trial: int, L: int, n: int) -> list[tuple[int, int]]:
    """``n`` distinct water cells for a trial's boats; the first is the one-boat campaign's start."""
    import numpy as np

    first = _start_cell(field, {"seed": seed}, L, trial)
    rng = np.random.default_rng([seed + trial, L, 7])
    water = [tuple(int(x) for x in w) for w in np.argwhere(~field.land_mask) if tuple(int(x) for x in w) != first]
    pick = rng.choice(len(water), size=n - 1, replace=False) if n > 1 else []
    return [first] + [water[j] for j in pick]


def fleet_comparison(field, predictor, *, boats: int, path_length: int, trials: int = 10, planner: str = "policy_gradient", reward: str = "speed", steps: int = 300, t0: int = 0, steps_per_leg: int = 10, noise: float = 0.02, hyper: str = "every_leg", sampling: str = "end", window: int = 50, seed: int = 0, progress: bool = True, background: int = 0) -> dict:
    """PASST with 1..``boats`` boats of ``path_length`` moves each, and one boat of ``boats`` x
    ``path_length`` moves (the fleet's budget in one path), over ``trials`` seeded trials
    (:func:`passt_mav.passt.run_offline_fleet`). Returns per configuration the mean RMSE over
    time, the final-window mean and each trial's final-window value (field units).
    ``background``: as in :func:`run_campaign`."""
    import numpy as np

    from passt_mav.passt import run_offline_fleet

    configs = [(f"{n} boat{'s' if n > 1 else ''} x {path_length}", n, path_length) for n in range(1, boats + 1)]
    configs.append((f"1 boat x {boats * path_length}", 1, boats * path_length))
    T = int(min(steps, field.n_times - 1 - t0))
    truth = field.data[t0 : t0 + T + 1].astype("float64")
    out: dict = {"config": {"boats": boats, "path_length": path_length, "trials": trials, "steps": T, "t0": t0,
                            "steps_per_leg": steps_per_leg, "noise": noise, "window": window, "seed": seed,
                            "planner": planner, "reward": reward, "hyper": hyper, "sampling": sampling, "background": background},
                 "runs": {}}
    from threadpoolctl import threadpool_limits

    it = [(name, n, L, i) for name, n, L in configs for i in range(trials)]
    from passt_mav.progress import progress as _progress

    it = _progress(it, "fleet comparison", "trial", quiet=not progress)
    series: dict[str, list] = {}
    with threadpool_limits(1):  # the campaign's rule: one BLAS thread, the same numbers everywhere
        for name, n, L, i in it:
            r = run_offline_fleet(field, predictor, start_cells=_fleet_starts(field, seed, i, path_length, n), t0=t0,
                                  n_steps=T, planner=planner, reward=reward, path_length=L, steps_per_leg=steps_per_leg,
                                  noise_std=noise, hyper=_hyper_for(hyper, residual=True), sample_at=sampling, seed=seed + i, background=background)
            series.setdefault(name, []).append(_rmse_series(r.estimate, truth))
    for name, n, L in configs:
        arr = np.array(series[name])
        finals = arr[:, -window:].mean(axis=1)
        out["runs"][name] = {"boats": n, "path_length": L, "rmse_mean": arr.mean(axis=0).tolist(),
                             "final_rmse": float(finals.mean()), "final_rmse_trials": finals.tolist()}
    return out


def write_fleet_figure(result: dict, out_dir):
    """fleet_rmse.png: mean RMSE over time of each fleet configuration."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    for name, run in result["runs"].items():
        ax.plot(run["rmse_mean"], label=f"{name} (final {run['final_rmse']:.3f})",
                ls="--" if run["boats"] == 1 and run["path_length"] != result["config"]["path_length"] else "-")
    c = result["config"]
    ax.set_xlabel(f"steps after the start (snapshots; legs of {c['steps_per_leg']})")
    ax.set_ylabel("RMSE (field units)")
    ax.set_title(f"PASST with a fleet: mean over {c['trials']} trials", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    path = Path(out_dir) / "fleet_rmse.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def campaign_tasks(path_lengths, trials: int, engine: str = "lockstep", batch: int | None = None) -> list[tuple[int, tuple[int, ...]]]:
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
                futs = [client.submit(_task, f_fut, p_fut, cfg, L, tr, pure=False, priority=-i) for i, (L, tr) in enumerate(longest_first)]
                for fut in as_completed(futs):
                    rs = fut.result()
                    out.extend(rs)
                    bar.update(len(rs))
            finally:
                if client is not scheduler:
                    client.close()
        elif workers > 1:
            from joblib import Parallel, delayed

            for rs in Parallel(n_jobs=workers, return_as="generator_unordered")(delayed(_task)(field, predictor, cfg, L, tr) for L, tr in longest_first):
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


# -- figures -------------------------------------------------------------------


def write_figures(summary: dict, out_dir) -> list:
    """RMSE vs time per path length, POD energy bars, snapshots (truth / PASST / model)."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out_dir = Path(out_dir)
    files = []
    Ls = list(summary["per_L"])
    n = len(Ls)
    ncol = min(3, n)
    nrow = (n + ncol - 1) // ncol
    fig, axes = plt.subplots(nrow, ncol, figsize=(5 * ncol, 3.6 * nrow), squeeze=False, sharey=True)
    for ax, L in zip(axes.ravel(), Ls):
        per = summary["per_L"][L]
        for m, mu in per["rmse_mean"].items():
            mu = np.asarray(mu)
            sd = np.asarray(per["rmse_std"][m])
            t = np.arange(mu.size)
            ax.plot(t, mu, label=m, lw=1.4 if m == "passt" else 1.0)
            ax.fill_between(t, mu - sd, mu + sd, alpha=0.15)
        ax.set_title(f"L = {L} moves per leg")
        ax.set_xlabel("steps after start")
        ax.set_ylabel("RMSE")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    p = out_dir / "rmse_vs_time.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p)

    fig, axes = plt.subplots(1, n, figsize=(4.5 * n, 3.4), squeeze=False)
    for ax, L in zip(axes[0], Ls):
        pod = {"truth": summary["pod_truth"], **summary["per_L"][L]["pod"]}
        k = len(pod["truth"])
        width = 0.8 / len(pod)
        for j, (m, e) in enumerate(pod.items()):
            ax.bar(np.arange(k) + j * width, e, width, label=m)
        ax.set_xticks(np.arange(k) + 0.4 - width / 2, [str(i + 1) for i in range(k)])
        ax.set_xlabel("POD mode")
        ax.set_ylabel("energy fraction")
        ax.set_title(f"L = {L}")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    p = out_dir / "pod_energy.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p)

    snaps = summary.get("_snapshots", {})
    step = min(summary["config"]["snapshot_step"], summary["config"]["steps"])
    for L in Ls:
        panels = [("truth", snaps.get("truth")), ("PASST", snaps.get(f"passt@L{L}")), ("pure model", snaps.get("model"))]
        panels = [(t, np.asarray(a)) for t, a in panels if a is not None]
        if len(panels) < 2:
            continue
        spd = [np.hypot(a[0], a[1]) for _, a in panels]
        vmax = np.nanmax(spd[0])
        fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8), squeeze=False)
        for ax, (title, a), s in zip(axes[0], panels, spd):
            im = ax.imshow(s, origin="lower", vmin=0, vmax=vmax, cmap="viridis")
            R, C = s.shape
            q = max(1, R // 15)
            yy, xx = np.mgrid[0:R:q, 0:C:q]
            ax.quiver(xx, yy, a[0][::q, ::q], a[1][::q, ::q], color="w", scale=None, width=0.004)
            ax.set_title(f"{title}, t = {step}")
        fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="speed")
        p = out_dir / f"snapshots_L{L}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        files.append(p)
    return files


# -- CLI -----------------------------------------------------------------------


def _load_predictor(spec: str, field):
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


def _parse_lengths(s: str) -> list[int]:
    from passt_mav.errors import PlannerError

    try:
        out = [int(x) for x in s.split(",") if x.strip()]
    except ValueError:
        raise PlannerError(f"--path-lengths must be comma-separated integers, got {s!r}") from None
    if not out or min(out) < 1:
        raise PlannerError(f"--path-lengths must be positive integers, got {s!r}")
    return out


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from passt_mav.errors import PlannerError
    from passt_mav.fields.datasets import resolve_field

    lengths = _parse_lengths(args.path_lengths)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if args.workers < 1:
        raise PlannerError("--workers must be >= 1")
    if args.steps < 1 or args.steps_per_leg < 1:
        raise PlannerError("--steps and --steps-per-leg must be >= 1")
    field = resolve_field(args.data)
    predictor = _load_predictor(args.model, field)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.boats < 1:
        raise PlannerError("--boats must be >= 1")
    if args.boats > 1:
        return _run_fleet(args, field, predictor, lengths[0], out_dir)
    summary = run_campaign(field, predictor, path_lengths=lengths, trials=args.trials, planner=args.planner, reward=args.reward, steps=args.steps, t0=args.t0, steps_per_leg=args.steps_per_leg, noise=args.noise, hyper=args.hyper, sampling=args.sampling, baseline_prior=args.baseline_prior, methods=methods, window=args.window, snapshot_step=args.snapshot_step, seed=args.seed, workers=args.workers, scheduler=args.scheduler, engine=args.engine, batch=args.batch, gp_solver=args.gp_solver, fast_predict=args.fast_predict, background=args.background, prior_blend=args.prior_blend, gp_bias=args.gp_bias)
    summary["config"].update(data=args.data, model=args.model, command="passt-mav evaluate " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["evaluate"] else None)
    files = write_figures(summary, out_dir)
    snaps = summary.pop("_snapshots")
    (out_dir / "results.json").write_text(json.dumps(summary) + "\n")
    (out_dir / "snapshots.json").write_text(json.dumps(snaps) + "\n")
    table = {L: {"final_rmse": per["final_rmse"], "ratio_to_passt": per.get("ratio_to_passt")} for L, per in summary["per_L"].items()}
    if args.json:
        print(json.dumps({"out": str(out_dir), "window": summary["config"]["window"], "per_L": table}))
    else:
        ms = list(next(iter(table.values()))["final_rmse"])
        print(f"final-window RMSE (last {summary['config']['window']} steps), mean over {args.trials} trials; ratio = method / passt")
        print("L".rjust(6) + "".join(m.rjust(16) for m in ms))
        for L, row in table.items():
            cells = []
            for m in ms:
                r = row["ratio_to_passt"][m] if row["ratio_to_passt"] else float("nan")
                cells.append(f"{row['final_rmse'][m]:.4f} ({r:.2f})".rjust(16))
            print(str(L).rjust(6) + "".join(cells))
        print(f"figures: {', '.join(f.name for f in files)}")
    print(f"results written to {out_dir}", file=sys.stderr if args.json else sys.stdout)
    return 0


def _run_fleet(args, field, predictor, L: int, out_dir) -> int:
    import json

    res = fleet_comparison(field, predictor, boats=args.boats, path_length=L, trials=args.trials, planner=args.planner,
                           reward=args.reward, steps=args.steps, t0=args.t0, steps_per_leg=args.steps_per_leg,
                           noise=args.noise, hyper=args.hyper, sampling=args.sampling, window=args.window, seed=args.seed, background=args.background)
    res["config"].update(data=args.data, model=args.model)
    fig = write_fleet_figure(res, out_dir)
    (out_dir / "fleet.json").write_text(json.dumps(res) + "\n")
    if args.json:
        print(json.dumps({"out": str(out_dir), "final_rmse": {k: v["final_rmse"] for k, v in res["runs"].items()}}))
    else:
        print(f"final-window RMSE (last {args.window} steps), mean over {args.trials} trials")
        for name, run in res["runs"].items():
            print(f"  {name:>18}: {run['final_rmse']:.4f}")
        print(f"figure: {fig.name}")
    print(f"results written to {out_dir}", file=sys.stderr if args.json else sys.stdout)
    return 0
