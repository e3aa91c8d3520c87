"""passt-mav model: train or evaluate predictors (KNODE, DMD, persistence).

``model train`` fits a predictor on a window of a field and writes ``OUT.pt``
(a ``state_dict``) and ``OUT.json`` (metadata: architecture, grid, dt, scaler,
data hash, epochs, seed, loss curve, the command). ``model evaluate`` predicts
from every snapshot of the train/test windows at lookaheads 1..100 and reports MSE,
cosine distance and POD energy for the model next to DMD and persistence.
"""

from __future__ import annotations

import argparse
import sys

HELP = "Train or evaluate predictors (KNODE, DMD, persistence)"
EXAMPLES = """examples:
  passt-mav model train --data builtin:cylinder --start 200 --stop 300 --epochs 200 --seed 0 --out runs/knode_cyl
  passt-mav model train --data builtin:ocean --stop 400 --epochs 40 --n-batches 3 --out runs/knode_ocean
  passt-mav model train --data builtin:cylinder --start 200 --stop 300 --knowledge dmd --out runs/knode_dmd_cyl
  passt-mav model train --model dmd --data builtin:cylinder --start 200 --stop 300 --out runs/dmd_cyl
  passt-mav model evaluate --model builtin:cylinder --data builtin:cylinder --oscillating builtin:oscillating --out runs/eval_knode
  passt-mav model evaluate --model runs/knode_cyl.pt --data builtin:cylinder --json --out runs/eval
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="{train,evaluate}")
    sub.required = True
    t = sub.add_parser(
        "train",
        help="fit a predictor on a field window and save a checkpoint",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=EXAMPLES,
    )
    t.add_argument("--data", required=True, help="builtin:cylinder | builtin:oscillating | builtin:ocean | FILE.nc")
    t.add_argument("--model", default="knode", help="predictor name: knode (default) | dmd | persistence")
    t.add_argument("--start", type=int, default=None, help="first training snapshot (default 0)")
    t.add_argument("--stop", type=int, default=None, help="one past the last training snapshot (default: all)")
    t.add_argument("--epochs", type=int, default=100, help="KNODE epochs (default 100; the paper trained 1981)")
    t.add_argument("--seed", type=int, default=0, help="seed for weights and input noise (default 0)")
    t.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    t.add_argument(
        "--n-batches", type=int, default=1, help="1 = full batch (default); n splits snapshot pairs by i mod n"
    )
    t.add_argument("--substeps", type=int, default=6, help="integrator steps per snapshot interval (default 6)")
    t.add_argument("--method", default="euler", help="integrator: euler (default) | rk4")
    t.add_argument(
        "--kernel-variance", type=float, default=0.1, help="smoothing K variance in cell^2 (default 0.1, as the paper)"
    )
    t.add_argument(
        "--noise-var", type=float, default=1e-3, help="white training input-noise variance, scaled units (default 1e-3)"
    )
    t.add_argument(
        "--recipe",
        default="loop",
        choices=("loop", "paper"),
        help="loop (default): roll-out loss over a leg, GP-residual noise, validation with best-epoch selection, start from persistence; paper: one-step loss, white noise, no validation (the options below override either)",
    )
    t.add_argument(
        "--loss",
        default=None,
        choices=("one_step", "rollout"),
        help="training loss (recipe loop: rollout; paper: one_step)",
    )
    t.add_argument(
        "--horizon",
        type=int,
        default=None,
        help="roll-out length in snapshots for --loss rollout (default 10, a PASST leg)",
    )
    t.add_argument(
        "--curriculum",
        type=float,
        default=None,
        help="fraction of epochs over which the roll-out grows from 1 to --horizon (default 0.3)",
    )
    t.add_argument(
        "--noise",
        default=None,
        choices=("white", "gp"),
        help="input noise: gp = size/correlation measured from GP reconstructions (loop) | white (paper)",
    )
    t.add_argument(
        "--noise-scale", type=float, default=None, help="multiplier on the measured GP-residual noise (default 1)"
    )
    t.add_argument(
        "--val-frac",
        type=float,
        default=None,
        help="last fraction of the window held out for validation and the skill report (loop: 0.2; paper: 0)",
    )
    t.add_argument("--val-every", type=int, default=None, help="epochs between validations (default 1)")
    t.add_argument(
        "--patience",
        type=int,
        default=None,
        help="stop after this many epochs without a better validation loss (default 60; 0 = never)",
    )
    t.add_argument("--train-batch", type=int, default=None, help="initial conditions per optimiser step (default 32)")
    t.add_argument("--max-ics", type=int, default=None, help="initial conditions drawn per epoch (default 0 = all)")
    t.add_argument(
        "--init",
        default=None,
        help="fine-tune: start from this KNODE checkpoint (its weights and scaler; same grid and architecture), e.g. builtin:cylinder",
    )
    t.add_argument(
        "--select",
        default=None,
        choices=("best", "last"),
        help="weights kept: best validation epoch (default) | last epoch (for a --horizon longer than the validation window)",
    )
    t.add_argument(
        "--shift-rows",
        type=int,
        default=None,
        help="augmentation: move each training roll-out by a random whole number of rows in [-N, N] (cross-stream; where a wake sits in the crop), edge rows replicated; fields without land only (default 0 = off)",
    )
    t.add_argument(
        "--shift-fraction",
        type=float,
        default=None,
        help="with --shift-rows: share of training initial conditions shifted (the rest unshifted) and the shifted copies' weight in validation (default: uniform over all shifts, 0 included)",
    )
    t.add_argument(
        "--knowledge",
        default=None,
        choices=("none", "dmd"),
        help="known linear term of the KNODE's right-hand side: none (default, the paper: smoothing K only) | dmd (DMD's operator fitted on the training part, in continuous time, plus the learned correction)",
    )
    t.add_argument(
        "--knowledge-rank",
        type=int,
        default=None,
        help="with --knowledge dmd: DMD rank (default: by --knowledge-energy)",
    )
    t.add_argument(
        "--knowledge-energy",
        type=float,
        default=None,
        help="with --knowledge dmd: smallest rank reaching this share of the snapshots' energy (default 0.999)",
    )
    t.add_argument(
        "--knowledge-complement",
        default=None,
        metavar="{keep,drop,RATE}",
        help="with --knowledge dmd: the state outside DMD's subspace persists (keep, default), is dropped as DMD does (drop) or decays at RATE per snapshot interval (e.g. 0.2)",
    )
    t.add_argument(
        "--compile", action="store_true", help="train through torch.compile where it works (falls back to eager)"
    )
    t.add_argument("--no-skill", action="store_true", help="skip the skill report on the validation window")
    t.add_argument("--device", default="cpu", help="torch device (default cpu)")
    t.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    t.add_argument("--log", default=None, help="append 'epoch loss' lines to this file")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.add_argument("--json", action="store_true", help="print the summary as JSON")
    t.add_argument("--out", required=True, help="checkpoint path without suffix (writes OUT.pt and OUT.json)")
    e = sub.add_parser(
        "evaluate",
        help="prediction error vs lookahead, cosine distance, POD energy vs DMD and persistence",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=EXAMPLES,
    )
    e.add_argument(
        "--model",
        required=True,
        help="checkpoint | builtin:cylinder | builtin:ocean (shipped KNODEs; the old spelling shipped:NAME is deprecated, still accepted) | a predictor name (fitted on the train window)",
    )
    e.add_argument("--data", required=True, help="field (builtin:NAME or FILE.nc)")
    e.add_argument("--train", default="200:300", help="train window START:STOP (default 200:300)")
    e.add_argument("--test", default="300:400", help="test window START:STOP (default 300:400)")
    e.add_argument(
        "--oscillating",
        default=None,
        help="optional second field evaluated on its test window (e.g. builtin:oscillating)",
    )
    e.add_argument("--lookaheads", default="1,2,5,10,20,50,100", help="comma-separated steps (clipped to the window)")
    e.add_argument(
        "--baselines",
        default="dmd,persistence",
        help="comma-separated predictor names fitted on the train window ('' for none)",
    )
    e.add_argument(
        "--ic-stride", type=int, default=1, help="use every n-th snapshot as initial condition (default 1: all)"
    )
    e.add_argument(
        "--pod-window", default="300:350", help="window for POD energy of predicted vs true (default 300:350)"
    )
    e.add_argument("--pod-modes", type=int, default=6, help="POD modes reported (default 6)")
    e.add_argument(
        "--no-gp-starts",
        action="store_true",
        help="skip the errors from GP-reconstructed initial states (the states the PASST loop starts from)",
    )
    e.add_argument(
        "--gp-ic-stride",
        type=int,
        default=4,
        help="every n-th test snapshot is GP-reconstructed as an initial condition (default 4)",
    )
    e.add_argument(
        "--gp-path-length",
        type=int,
        default=50,
        help="moves of the random sampling path per reconstruction (default 50)",
    )
    e.add_argument(
        "--gp-noise", type=float, default=0.02, help="sensor noise std of the samples, field units (default 0.02)"
    )
    e.add_argument("--seed", type=int, default=0, help="seed of the sampling paths and noise (default 0)")
    e.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    e.add_argument("--json", action="store_true", help="print the results as JSON")
    e.add_argument("--out", default=None, help="output directory for results.json and PNG plots")


def _window(s: str, name: str) -> tuple[int, int]:
    from passt_mav.errors import ModelError

    try:
        a, b = (int(x) for x in s.split(":"))
    except ValueError:
        raise ModelError(f"--{name} must be START:STOP, got {s!r}") from None
    if not 0 <= a < b:
        raise ModelError(f"--{name} must satisfy 0 <= START < STOP, got {s!r}")
    return a, b


def _train(args) -> int:
    import json

    from passt_mav.models.train import train

    logf = _open_log(args.log) if args.log else None

    def log(ep, loss):
        if logf is not None:
            logf.write(f"{ep + 1} {loss:.6g}\n")
            logf.flush()

    try:
        cmd = "passt-mav model " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["model"] else None
        s = train(
            args.data,
            out=args.out,
            model=args.model,
            start=args.start,
            stop=args.stop,
            epochs=args.epochs,
            seed=args.seed,
            lr=args.lr,
            n_batches=args.n_batches,
            substeps=args.substeps,
            method=args.method,
            kernel_variance=args.kernel_variance,
            noise_var=args.noise_var,
            device=args.device,
            threads=args.threads,
            progress=not args.no_progress,
            command=cmd,
            log=log,
            recipe=args.recipe,
            overrides=_recipe_overrides(args),
            skill=not args.no_skill,
        )
    finally:
        if logf is not None:
            logf.close()
    if args.json:
        print(json.dumps(s))
    else:
        _print_trained(s)
    return 0


def _open_log(path: str):
    """The loss log ``path`` opened for appending (its folder made), or the error naming it."""
    from pathlib import Path

    from passt_mav.errors import UserError

    # a recorded command may log into a folder this checkout does not have yet
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        return open(path, "a")  # noqa: SIM115 - closed by the caller
    except OSError as exc:
        raise UserError(f"--log {path}: cannot write it ({exc.strerror})") from None


def _recipe_overrides(args) -> dict:
    """The training options given on the command line that override the recipe's."""
    return {
        k: getattr(args, k)
        for k in (
            "loss",
            "horizon",
            "curriculum",
            "noise",
            "noise_scale",
            "val_frac",
            "val_every",
            "patience",
            "train_batch",
            "max_ics",
            "init",
            "select",
            "shift_rows",
            "shift_fraction",
            "knowledge",
            "knowledge_rank",
            "knowledge_energy",
            "knowledge_complement",
        )
        if getattr(args, k) is not None
    } | ({"compile": True} if args.compile else {})


def _print_trained(s: dict) -> None:
    """Print a training summary: its fields, the checkpoint's skill (and warning) and where it went."""
    for k, v in s.items():
        if k != "skill":
            print(f"{k:>18}: {v}")
    if s.get("skill"):
        from passt_mav.models.evaluate import skill_lines, skill_warning

        print("\n".join(skill_lines(s["skill"])))
        w = skill_warning({"skill": s["skill"]})
        if w:
            print(w)
    print(f"checkpoint written: {s['out']} (+ .json)")


def _evaluate(args) -> int:
    import json

    from passt_mav.models.evaluate import evaluate_command

    lookaheads = []
    for x in args.lookaheads.split(","):
        if x.strip():
            try:
                lookaheads.append(int(x))
            except ValueError:
                from passt_mav.errors import ModelError

                raise ModelError(f"--lookaheads must be comma-separated integers, got {args.lookaheads!r}") from None
    res = evaluate_command(
        model=args.model,
        data=args.data,
        train=_window(args.train, "train"),
        test=_window(args.test, "test"),
        oscillating=args.oscillating,
        lookaheads=lookaheads,
        baselines=[b for b in args.baselines.split(",") if b.strip()],
        ic_stride=args.ic_stride,
        pod_window=_window(args.pod_window, "pod-window"),
        pod_modes=args.pod_modes,
        threads=args.threads,
        out=args.out,
        gp_starts=not args.no_gp_starts,
        gp_ic_stride=args.gp_ic_stride,
        gp_path_length=args.gp_path_length,
        gp_noise=args.gp_noise,
        seed=args.seed,
    )
    if args.json:
        print(json.dumps(res))
    else:
        from passt_mav.models.evaluate import format_table

        print(format_table(res))
        if res.get("skill"):
            from passt_mav.models.evaluate import skill_lines

            print("\n".join(skill_lines(res["skill"])))
        if res.get("skill_warning"):
            print(res["skill_warning"])
        if args.out:
            print(f"results written to {args.out}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.action == "train":
        return _train(args)
    return _evaluate(args)
