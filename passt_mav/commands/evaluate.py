"""passt-mav evaluate: offline PASST campaign - trials x path lengths, RMSE over time and POD energy.

The CLI over :mod:`passt_mav.loop.campaign` (the methods, engines and protocol are described there):
arguments, figures, and the summary printed. Written under --out: ``results.json`` and PNG
figures (``fleet.json`` and ``fleet_rmse.png`` with ``--boats N``); the directory is named at the end.
"""

from __future__ import annotations

import argparse
import sys

from passt_mav.loop.campaign import ENGINES, METHODS
from passt_mav.loop.presets import DEFAULT, PRESETS
from passt_mav.reconstruction.gp import MAX_FIT_POINTS
from passt_mav.units import speed_unit

HELP = "Offline PASST campaign: trials x path lengths, RMSE over time and POD energy"
EXAMPLES = """examples:
  passt-mav evaluate --data builtin:cylinder --model builtin:cylinder --out runs/eval_cyl
  passt-mav evaluate --data builtin:oscillating --model builtin:cylinder --trials 10 --path-lengths 50,100 --out runs/eval_osc
  passt-mav evaluate --data builtin:ocean --model dmd --reward vorticity --workers 2 --json --out runs/eval_ocean
  passt-mav evaluate --data builtin:cylinder --model builtin:cylinder --scheduler tcp://127.0.0.1:8786 --out runs/eval_dask
"""

DEFAULT_PATH_LENGTHS = "25,50,75,100,150,200"

#: ``--model-update`` options: (``ModelUpdate`` field, option, type, default, metavar, help)
_UPDATE_OPTIONS = (
    ("budget_s", "--model-update-budget", float, 5.0, "SECONDS", "seconds of gradient steps per leg (default 5)"),
    (
        "max_steps",
        "--model-update-steps",
        int,
        None,
        "N",
        (
            "at most N gradient steps per leg, so that the numbers do not depend on the machine's speed (give a "
            "budget large enough for them; default: the budget alone)"
        ),
    ),
    ("lr", "--model-update-lr", float, 1e-4, "LR", "Adam's learning rate (default 1e-4)"),
    (
        "horizon",
        "--model-update-horizon",
        int,
        1,
        "H",
        "later states each state's roll-out is compared with (default 1)",
    ),
    ("window", "--model-update-window", int, 10, "W", "the most recent reconstructed states trained on (default 10)"),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data", required=True, help="field: builtin:cylinder | builtin:oscillating | builtin:ocean | FILE.nc"
    )
    p.add_argument(
        "--model",
        required=True,
        help="predictor: builtin:cylinder | builtin:ocean | CHECKPOINT | a predictor name (fitted on --data)",
    )
    p.add_argument("--trials", type=int, default=30, help="trials per path length (default 30)")
    p.add_argument(
        "--path-lengths",
        default=DEFAULT_PATH_LENGTHS,
        help=f"comma-separated moves per leg (default {DEFAULT_PATH_LENGTHS})",
    )
    p.add_argument(
        "--preset",
        choices=tuple(PRESETS),
        default="default",
        help="the loop's configuration the options below start from: default (what a mission flies unless its file "
        "says otherwise: the mission schema's defaults) or paper (the paper's: no prior blend, share or GP bias); "
        "an option given explicitly replaces the preset's (default: default)",
    )
    p.add_argument("--planner", default=None, help=f"PASST's planner (default: the preset's, {DEFAULT.planner})")
    p.add_argument(
        "--reward",
        default=None,
        help=f"reward map: speed | vorticity | std | speed_std | change (the predicted change over the leg) (default: the preset's, {DEFAULT.reward})",
    )
    p.add_argument(
        "--steps", type=int, default=300, help="snapshots estimated after the start (default 300, clipped to the data)"
    )
    p.add_argument("--t0", type=int, default=0, help="start snapshot index (default 0)")
    p.add_argument(
        "--steps-per-leg",
        type=int,
        default=10,
        help="snapshots one leg spans = re-initialisation interval (default 10)",
    )
    p.add_argument("--noise", type=float, default=0.02, help="sensor noise std, field units (default 0.02)")
    p.add_argument(
        "--sampling",
        choices=("end", "spread"),
        default="end",
        help="when a leg's cells are read: all at the leg's end (default; the paper's offline protocol, one snapshot per leg) or spread over the leg at constant speed",
    )
    p.add_argument(
        "--hyper",
        default="every_leg",
        help="GP hyper-parameter fits: every_leg | first_leg | state | auto (residual GPs every leg, sample-only GPs once on the initial state) (default every_leg)",
    )
    p.add_argument(
        "--baseline-prior",
        choices=("none", "forecast"),
        default="none",
        help="baselines: GP alone (none, default) or the full loop with the model (forecast)",
    )
    p.add_argument(
        "--methods",
        default=",".join(METHODS),
        help=f"subset of {','.join(METHODS)}; also PLANNER_gp for any planner (e.g. information_gp) and METHOD@REWARD (e.g. passt@variance_reduction) to compare planners and rewards in one loop",
    )
    p.add_argument("--window", type=int, default=50, help="final window (steps) for the ratio table (default 50)")
    p.add_argument(
        "--snapshot-step", type=int, default=250, help="step of the 2-D snapshot figure (default 250, clipped)"
    )
    p.add_argument("--seed", type=int, default=0, help="base seed (trial i uses seed + i)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (joblib; default 1)")
    p.add_argument(
        "--scheduler", default=None, help="address of an existing Dask distributed scheduler (runs trials there)"
    )
    p.add_argument(
        "--engine",
        choices=tuple(ENGINES),
        default="serial",
        help="serial (default: one trial at a time) or lockstep (a path length's trials advance together, one batched predictor call per leg and one batched policy-gradient planning call: faster per trial-leg, benchmarks/bench_passt.py). Same numbers for predictors whose batched and single predictions agree bit for bit (DMD, persistence); with the KNODE, batched convolutions round differently and paths can diverge",
    )
    p.add_argument(
        "--batch",
        type=int,
        default=None,
        help="lockstep: trials per batch = unit of work for --workers/--scheduler (default: all trials of a path length)",
    )
    p.add_argument(
        "--gp-solver",
        choices=("cholesky", "sklearn"),
        default="sklearn",
        help="GP posterior with the fitted kernel: sklearn's regressor (default) or a direct Cholesky solve (faster; equal to sklearn to 1e-6 per reconstruction, which a long campaign can amplify into different paths)",
    )
    p.add_argument(
        "--fast-predict",
        action="store_true",
        help="run a KNODE through its compiled prediction path (torch.compile with freezing: ~1.6x, fp32 rounding of the eager path, a few seconds of compiling per batch shape; what passt-mav paper uses)",
    )
    p.add_argument(
        "--background",
        type=int,
        default=None,
        metavar="STEPS",
        help=f"residual GPs (PASST's; the baselines' with --baseline-prior forecast) add a model-based background covariance: the anomalies of STEPS snapshots of the model's roll-out from the initial state (ensemble optimal interpolation) (default: the preset's, {DEFAULT.background}; 0 = stationary kernels only)",
    )
    p.add_argument(
        "--prior-blend",
        choices=("off", "bma", "select"),
        default=None,
        help=f"residual GPs' prior mean: off (the model's forecast restarted from the last estimate), bma (that forecast, the model alone from the first state and persistence weighed leg by leg by how well each explains the leg's samples: Bayesian model averaging with a forgetting factor) or select (the most probable of the three alone, leg by leg) (default: the preset's, {DEFAULT.prior_blend}; paper: off)",
    )
    p.add_argument(
        "--prior-share",
        type=float,
        default=None,
        metavar="BETA",
        help=f"with --prior-blend: fixed share of the prior weights (each candidate keeps at least BETA/3 before every leg's update, so one leg where a good model misses is won back in a few nats; 0 = off) (default: the preset's, {DEFAULT.prior_share:g}; paper: 0)",
    )
    p.add_argument(
        "--prior-forgetting",
        type=float,
        default=None,
        metavar="F",
        help=f"with --prior-blend: forgetting factor of the prior weights per leg (log weights <- F x log weights + the leg's log likelihood, which flattens the weights towards the uniform; select forgets towards the start weights; 1 = none) (default: the preset's, {DEFAULT.forgetting:g})",
    )
    p.add_argument(
        "--gp-bias",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the residual GP may shift the forecast by a constant offset over the region (u, v) and rescale its anomaly, kept only where the samples' likelihood pays for it (GPReconstructor bias) (default: the preset's, on; paper: off)",
    )
    p.add_argument(
        "--gp-nugget",
        choices=("state", "noise"),
        default=None,
        help=f"the white variance the residual GP fits above the sensor's: the field's grid-scale error, which a sample corrects in its own cell (state), or measurement noise (noise) (default: the preset's, {DEFAULT.nugget})",
    )
    p.add_argument(
        "--gp-fit-points",
        type=int,
        default=MAX_FIT_POINTS,
        metavar="N",
        help="at most N of a leg's samples (evenly spread along the track) enter the residual GP's hyper-parameter fit; the reconstruction uses all (GPReconstructor max_fit_points; default %(default)s)",
    )
    p.add_argument(
        "--memory",
        choices=("off", "fitted"),
        default=None,
        help=f"the information reward's prior remembers, cell by cell, the local error past legs' samples removed, with a persistence per leg fitted by the innovations' likelihood (fitted), or starts every leg from the stationary prior (off) (default: the preset's, {DEFAULT.memory})",
    )
    p.add_argument(
        "--model-update",
        choices=("off", "on"),
        default="off",
        help="learning at sea (a KNODE's weights; DMD and persistence stay as they are): between legs a copy of the model is fine-tuned on the trial's reconstructed states so far and kept only when the next leg's samples find it more probable than the current model (innovation log likelihood); each trial learns its own model (serial engine only) (default off)",
    )
    for _, flag, typ, default, metavar, text in _UPDATE_OPTIONS:
        p.add_argument(flag, type=typ, default=default, metavar=metavar, help=f"with --model-update on: {text}")
    p.add_argument(
        "--boats",
        type=int,
        default=1,
        help="N > 1: the fleet comparison instead of the campaign: "
        "PASST with 1..N boats of L moves each vs 1 boat of N*L moves per leg interval (the same "
        "budget), L = the first of --path-lengths; writes fleet.json and fleet_rmse.png",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--out", required=True, help="output directory")


def write_fleet_figure(result: dict, out_dir):
    """fleet_rmse.png: mean RMSE over time of each fleet configuration."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    for name, run in result["runs"].items():
        ax.plot(
            run["rmse_mean"],
            label=f"{name} (final {run['final_rmse']:.3f})",
            ls="--" if run["boats"] == 1 and run["path_length"] != result["config"]["path_length"] else "-",
        )
    c = result["config"]
    ax.set_xlabel(f"steps after the start (snapshots; legs of {c['steps_per_leg']})")
    ax.set_ylabel(f"RMSE ({c.get('rmse_unit', 'field units')})")
    ax.set_title(f"PASST with a fleet: mean over {c['trials']} trials", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    path = Path(out_dir) / "fleet_rmse.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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
        ax.set_ylabel(f"RMSE ({summary['config'].get('rmse_unit', 'field units')})")
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
        panels = [
            ("truth", snaps.get("truth")),
            ("PASST", snaps.get(f"passt@L{L}")),
            ("pure model", snaps.get("model")),
        ]
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


def parse_lengths(s: str) -> list[int]:
    """``--path-lengths`` (comma-separated moves per leg) as positive integers; :class:`PlannerError` otherwise."""
    from passt_mav.errors import PlannerError

    try:
        out = [int(x) for x in s.split(",") if x.strip()]
    except ValueError:
        raise PlannerError(f"--path-lengths must be comma-separated integers, got {s!r}") from None
    if not out or min(out) < 1:
        raise PlannerError(f"--path-lengths must be positive integers, got {s!r}")
    from passt_mav.mission.config import MAX_PATH_LENGTH  # a mission's own bound on planner.path_length

    if max(out) > MAX_PATH_LENGTH:
        raise PlannerError(f"--path-lengths must be at most {MAX_PATH_LENGTH} moves, got {max(out)}")
    return out


#: (argument, preset setting) of the options a preset fills (an argument given explicitly wins)
PRESET_ARGS = (
    ("planner", "planner"),
    ("reward", "reward"),
    ("memory", "memory"),
    ("background", "background"),
    ("prior_blend", "prior_blend"),
    ("prior_forgetting", "forgetting"),
    ("prior_share", "prior_share"),
    ("gp_bias", "bias"),
    ("gp_nugget", "nugget"),
)


def resolve_preset(args: argparse.Namespace) -> None:
    """Fill each of :data:`PRESET_ARGS` left unset (None) on the command line from ``args.preset``
    (:data:`passt_mav.loop.presets.PRESETS`)."""
    preset = PRESETS[args.preset]
    for arg, key in PRESET_ARGS:
        if getattr(args, arg, None) is None:
            setattr(args, arg, getattr(preset, key))


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from passt_mav.errors import PlannerError
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.loop.campaign import blend_options_problem, fit_points_problem, load_predictor
    from passt_mav.loop.online import model_update_problem

    lengths = parse_lengths(args.path_lengths)
    resolve_preset(args)
    if args.workers < 1:
        raise PlannerError("--workers must be >= 1")
    if args.steps < 1 or args.steps_per_leg < 1:
        raise PlannerError("--steps and --steps-per-leg must be >= 1")
    problem = blend_options_problem(args.prior_share, args.prior_forgetting) or fit_points_problem(args.gp_fit_points)
    args.model_update_options = _model_update(args)
    problem = problem or model_update_problem(args.model_update_options)
    if not problem and args.model_update == "on" and args.engine != "serial":
        problem = "--model-update on gives each trial its own model: use --engine serial"
    if problem:  # before the field loads and the run directory is made
        for key, opt, *_ in _UPDATE_OPTIONS:  # the option's name as the command line spells it
            problem = problem.replace(f"model_update.{key} ", f"{opt} ")
        raise PlannerError(problem)
    field = resolve_field(args.data, series=True)
    predictor = load_predictor(args.model, field)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.boats < 1:
        raise PlannerError("--boats must be >= 1")
    if args.boats > 1:
        return _run_fleet(args, field, predictor, lengths[0], out_dir)
    summary = _campaign(args, field, predictor, lengths)
    # the RMSEs are in the field's units: m/s for a field in m/s, else said (passt_mav.units)
    summary["config"]["rmse_unit"] = speed_unit(None, field.units).label
    files = write_figures(summary, out_dir)
    snaps = summary.pop("_snapshots")
    (out_dir / "results.json").write_text(json.dumps(summary) + "\n")
    (out_dir / "snapshots.json").write_text(json.dumps(snaps) + "\n")
    table = {
        L: {"final_rmse": per["final_rmse"], "ratio_to_passt": per.get("ratio_to_passt")}
        for L, per in summary["per_L"].items()
    }
    if args.json:
        print(json.dumps({"out": str(out_dir), "window": summary["config"]["window"], "per_L": table}))
    else:
        _print_table(table, window=summary["config"]["window"], trials=args.trials, unit=summary["config"]["rmse_unit"])
        for line in _drifter_lines(summary):  # virtual drifters through each map vs through the truth
            print(line)
        print(f"figures: {', '.join(f.name for f in files)}")
    for line in _trivial_lines(summary):  # the maps that do not beat no current / the forecast's time mean
        print(line, file=sys.stderr if args.json else sys.stdout)
    print(f"results written to {out_dir}", file=sys.stderr if args.json else sys.stdout)
    return 0


def _model_update(args: argparse.Namespace):
    """The :class:`passt_mav.loop.online.ModelUpdate` of ``--model-update*`` (``None`` when off)."""
    from passt_mav.loop.online import ModelUpdate

    if args.model_update == "off":
        return None
    return ModelUpdate(
        online="on", **{key: getattr(args, opt[2:].replace("-", "_")) for key, opt, *_ in _UPDATE_OPTIONS}
    )


def _campaign(args: argparse.Namespace, field, predictor, lengths: list[int]) -> dict:
    """The campaign the command line asks for (:func:`passt_mav.loop.campaign.run_campaign`), its summary's
    config completed with the data, model and command."""
    from passt_mav.loop.campaign import run_campaign

    summary = run_campaign(
        field,
        predictor,
        path_lengths=lengths,
        trials=args.trials,
        planner=args.planner,
        reward=args.reward,
        steps=args.steps,
        t0=args.t0,
        steps_per_leg=args.steps_per_leg,
        noise=args.noise,
        hyper=args.hyper,
        sampling=args.sampling,
        baseline_prior=args.baseline_prior,
        methods=[m.strip() for m in args.methods.split(",") if m.strip()],
        window=args.window,
        snapshot_step=args.snapshot_step,
        seed=args.seed,
        workers=args.workers,
        scheduler=args.scheduler,
        engine=args.engine,
        batch=args.batch,
        gp_solver=args.gp_solver,
        fast_predict=args.fast_predict,
        background=args.background,
        prior_blend=args.prior_blend,
        gp_bias=args.gp_bias,
        gp_nugget=args.gp_nugget,
        memory=args.memory,
        gp_fit_points=args.gp_fit_points,
        prior_share=args.prior_share,
        prior_forgetting=args.prior_forgetting,
        model_update=args.model_update_options,
    )
    summary["config"].update(
        preset=args.preset,
        data=args.data,
        model=args.model,
        command="passt-mav evaluate " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["evaluate"] else None,
    )
    return summary


def _trivial_lines(summary: dict) -> list[str]:
    """One line per path length naming the methods whose final-window RMSE does not beat the trivial maps
    (results.json ``baselines``: no current, the time mean of the model alone; ``per_L.*.beats_trivial``)."""
    base = summary.get("baselines") or {}
    if not base:
        return []
    w = int(summary["config"]["window"])
    fin = ", ".join(f"{k.removeprefix('rmse_')} {sum(v[-w:]) / len(v[-w:]):.4f}" for k, v in base.items() if v)
    out = []
    for L, per in summary["per_L"].items():
        bad = [m for m, ok in (per.get("beats_trivial") or {}).items() if not ok]
        if bad:
            out.append(f"WARNING: L={L}: {', '.join(bad)} do(es) not beat the trivial maps (final-window RMSE {fin})")
    return out


def _drifter_lines(summary: dict) -> list[str]:
    """Per path length the virtual drifters' mean separation from the true ones after the horizon (km, and
    km/day) per method and for persistence (results.json ``per_L.*.drifter_sep_km``); none without them."""
    out = []
    for L, per in summary["per_L"].items():
        sep, rate = per.get("drifter_sep_km"), per.get("drifter_km_per_day")
        if sep:
            cells = ", ".join(f"{m} {sep[m]:.2f} km ({rate[m]:.2f} km/day)" for m in sep)
            out.append(
                f"drifters L={L}: separation after {per['drifter_horizon_h']:.1f} h, {per['drifter_n']} drifters: {cells}"
            )
    return out


def _print_table(table: dict, *, window: int, trials: int, unit: str) -> None:
    """Print per path length each method's final-window RMSE (in ``unit``: the field's) and its ratio to PASST's."""
    ms = list(next(iter(table.values()))["final_rmse"])
    print(f"final-window RMSE ({unit}, last {window} steps), mean over {trials} trials; ratio = method / passt")
    print("L".rjust(6) + "".join(m.rjust(16) for m in ms))
    for L, row in table.items():
        cells = []
        for m in ms:
            r = row["ratio_to_passt"][m] if row["ratio_to_passt"] else float("nan")
            cells.append(f"{row['final_rmse'][m]:.4f} ({r:.2f})".rjust(16))
        print(str(L).rjust(6) + "".join(cells))


def _run_fleet(args, field, predictor, L: int, out_dir) -> int:
    import json

    from passt_mav.loop.campaign import fleet_comparison

    res = fleet_comparison(
        field,
        predictor,
        boats=args.boats,
        path_length=L,
        trials=args.trials,
        planner=args.planner,
        reward=args.reward,
        steps=args.steps,
        t0=args.t0,
        steps_per_leg=args.steps_per_leg,
        noise=args.noise,
        hyper=args.hyper,
        sampling=args.sampling,
        window=args.window,
        seed=args.seed,
        background=args.background,
        preset=PRESETS[args.preset],
    )
    res["config"].update(
        preset=args.preset, data=args.data, model=args.model, rmse_unit=speed_unit(None, field.units).label
    )
    fig = write_fleet_figure(res, out_dir)
    (out_dir / "fleet.json").write_text(json.dumps(res) + "\n")
    if args.json:
        print(json.dumps({"out": str(out_dir), "final_rmse": {k: v["final_rmse"] for k, v in res["runs"].items()}}))
    else:
        print(
            f"final-window RMSE ({res['config']['rmse_unit']}, last {args.window} steps), "
            f"mean over {args.trials} trials"
        )
        for name, run in res["runs"].items():
            print(f"  {name:>18}: {run['final_rmse']:.4f}")
        print(f"figure: {fig.name}")
    print(f"results written to {out_dir}", file=sys.stderr if args.json else sys.stdout)
    return 0
