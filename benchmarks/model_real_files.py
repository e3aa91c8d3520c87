"""Benchmark: models fitted on the earlier part of each real current file, flown on the later part.

    .venv/bin/python benchmarks/model_real_files.py --seed 0 --trials 10 --epochs 30   # prints the tables
    .venv/bin/python benchmarks/model_real_files.py --files hfradar --trials 1 --epochs 1  # smallest run
    .venv/bin/python benchmarks/model_real_files.py --tables out.json      # a --json file's tables again

Real files from ``../shared/data`` (read there, never copied): NOAA Global RTOFS off Washington, the
HYCOM-like file over the same coast and the MARACOOS HF-radar totals. One region per file is drawn
with ``--seed`` exactly as ``benchmarks/real_data_loop.py`` draws its cases (:func:`real_data_loop.make_cases`:
no cell with gaps, at most 65 % land), except that the HYCOM-like and HF-radar regions are regridded
to 16 x 14 and 14 x 16 cells instead of 14 x 12 and 12 x 14, the KNODE's convolutions needing at
least 13 x 13 cells.

Each file's snapshots are split in two: the earlier half ``0 .. T//2 - 1`` (the fit part) and the later
half ``T//2 .. T-1`` (the held-out part). Four predictors are fitted on the fit part only:

* ``persistence``;
* ``dmd`` (:class:`passt_mav.models.dmd.DMDPredictor`, the project's defaults);
* ``knode``: ``passt-mav model train`` with the ``loop`` recipe (the command is printed and recorded
  in the checkpoint);
* ``knode-dmd``: the same with ``--knowledge dmd --knowledge-complement 0.2`` (DMD's operator, in
  continuous time, as the known part of the right-hand side; the state outside DMD's subspace decays
  at 0.2 per snapshot interval, as in ``builtin:cylinder-dmd``).

The KNODE recipe (:data:`RECIPE`, :func:`knode_options`) was decided on the RTOFS file's fit part (its
own validation window, the last 20 % of the fit part) and is applied unchanged to every file; only
the roll-out horizon follows the fit part's length (a quarter of it, at most 10 snapshots), since the
short files hold 6 and 8 fit snapshots.

Printed, per file:

1. Lookahead MSE (field units^2, (m/s)^2) on the held-out part from the true states, every held-out
   snapshot an initial condition (:func:`passt_mav.models.evaluate.lookahead_errors`), at 1, 5 and 10
   snapshots (the lookaheads the held-out part allows), and each model's ratio to persistence.
2. PASST with each predictor as the prior (``passt-mav evaluate``'s campaign,
   :func:`passt_mav.loop.campaign.run_campaign`, the default preset: same planner, same GP) from the
   truth at the first held-out snapshot to the last: ``--trials`` trials (trial ``i``: start cell and
   sensor noise from seed ``--seed + i``, the same for every predictor), ``--path-length`` moves per
   leg, legs of ``max(1, steps // 8)`` snapshots, samples at each leg's end with N(0, 0.02 m/s)
   noise. Reported: the RMSE (m/s, water cells) averaged over the estimated held-out snapshots, mean
   +- std over the trials, and the model alone's (the predictor from the truth at the first
   held-out snapshot, never re-initialised).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

MODELS = ("persistence", "dmd", "knode", "knode-dmd")
LOOKAHEADS = (1, 5, 10)
#: the KNODE's training options beside the ``loop`` recipe (decided on the RTOFS file's fit part)
RECIPE = {"train_batch": 8}
#: KNODE-DMD's extra options
KNOWLEDGE = {"knowledge": "dmd", "knowledge_complement": "0.2"}
#: the files' region grids where real_data_loop's are below the KNODE's 13 x 13 cells
SHAPES = {"gridded": (16, 14), "hfradar": (14, 16)}


def draw_fields(files: list[str], seed: int, say=print) -> list[dict]:
    """One region per file of ``files`` (keys of ``real_data_loop.FILES`` whose file is present),
    drawn with ``seed`` by ``real_data_loop.make_cases`` on the grids of :data:`SHAPES`:
    ``[{"file", "region", "field"}]``."""
    import real_data_loop as rdl

    table = {k: v[:4] + (SHAPES.get(k, v[4]),) for k, v in rdl.FILES.items() if k in files}
    saved = rdl.FILES
    rdl.FILES = table  # make_cases draws over the module's table
    try:
        cases = rdl.make_cases(len(table), seed, say=say)
    finally:
        rdl.FILES = saved
    return [{"file": c["file"], "region": c["region"], "field": c["field"]} for c in cases]


def knode_options(n_fit: int, knowledge: bool) -> dict:
    """The KNODE's recipe overrides for a fit part of ``n_fit`` snapshots: :data:`RECIPE`, the roll-out
    horizon ``min(10, n_fit // 4)`` snapshots (at least 1), and :data:`KNOWLEDGE` for ``knowledge``."""
    return {**RECIPE, "horizon": max(1, min(10, n_fit // 4)), **(KNOWLEDGE if knowledge else {})}


def _cli_flags(opts: dict) -> str:
    return " ".join(f"--{k.replace('_', '-')} {v}" for k, v in opts.items())


def fit_models(case: dict, n_fit: int, out: Path, *, epochs: int, seed: int, models=MODELS) -> dict:
    """``{name: (fitted predictor, info)}`` for ``models``, each fitted on snapshots ``0 .. n_fit - 1`` of the
    case's field. The KNODEs are trained through :func:`passt_mav.models.train.train` on the region written
    to ``out/<file>.nc`` (one torch thread), their checkpoints written beside it; info holds the
    equivalent command, epochs, best epoch and wall seconds per epoch."""
    from passt_mav.models.base import load_predictor, make_predictor
    from passt_mav.models.train import train

    field = case["field"]
    nc = out / f"{case['file']}.nc"
    field.to_netcdf(nc)
    fitted = {}
    for name in models:
        if name in ("persistence", "dmd"):
            fitted[name] = (make_predictor(name).fit(field, stop=n_fit), {})
            continue
        opts = knode_options(n_fit, name == "knode-dmd")
        ckpt = out / f"{case['file']}_{name}"
        cmd = (
            f"passt-mav model train --data {nc} --stop {n_fit} --epochs {epochs} --seed {seed} --threads 1 "
            f"{_cli_flags(opts)} --no-skill --out {ckpt}"
        )
        s = train(
            str(nc), out=str(ckpt), stop=n_fit, epochs=epochs, seed=seed, threads=1, progress=False,
            command=cmd, overrides=opts, skill=False,
        )  # fmt: skip
        info = {k: s.get(k) for k in ("epochs", "best_epoch", "wall_s", "s_per_epoch", "knowledge_info")}
        fitted[name] = (load_predictor(ckpt), {**info, "command": cmd})
    return fitted


def lookahead_table(predictor, field, n_fit: int) -> dict:
    """``{h: mse}`` on the held-out part ``n_fit .. T-1`` from the true states, for the :data:`LOOKAHEADS` it allows."""
    from passt_mav.models.evaluate import lookahead_errors

    res = lookahead_errors(predictor, field.data, (n_fit, field.n_times), LOOKAHEADS)
    return {int(h): float(r["mse"]) for h, r in res.items()}


def fly(predictor, field, n_fit: int, *, trials: int, seed: int, path_length: int) -> dict:
    """PASST with ``predictor`` as the prior over the held-out part (module docstring): per-trial mean
    RMSE (m/s) over the estimated snapshots, the model alone's, and the legs' length in snapshots."""
    from passt_mav.loop.campaign import run_campaign

    steps = field.n_times - 1 - n_fit
    spl = max(1, steps // 8)
    res = run_campaign(
        field, predictor, path_lengths=(path_length,), trials=trials, t0=n_fit, steps=steps, steps_per_leg=spl,
        methods=["passt", "model"], seed=seed, progress=False, keep_trials=True, window=steps,
    )  # fmt: skip
    per_trial = [float(np.mean(r["rmse"]["passt"][1:])) for r in res["_trials"]]
    model = float(np.mean(res["per_L"][str(path_length)]["rmse_mean"]["model"][1:]))
    return {"passt": per_trial, "model": model, "steps": steps, "steps_per_leg": spl}


def run(files, *, seed: int, trials: int, epochs: int, path_length: int, out: Path, say=print) -> list[dict]:
    """The benchmark (module docstring) over ``files``; returns one record per file."""
    from passt_mav.progress import progress

    out.mkdir(parents=True, exist_ok=True)
    records = []
    cases = draw_fields(list(files), seed, say=say)
    with progress(len(cases) * len(MODELS), "model_real_files", "model") as bar:
        for case in cases:
            field = case["field"]
            n_fit = field.n_times // 2
            rec = {"file": case["file"], "region": case["region"], "n_times": field.n_times, "n_fit": n_fit}
            rec["dt_h"] = float(field.dt) / 3600.0
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fitted = fit_models(case, n_fit, out, epochs=epochs, seed=seed)
            rec["fit_s"] = round(time.perf_counter() - t, 1)
            rec["models"] = {}
            for name, (pred, info) in fitted.items():
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    m = {"lookahead": lookahead_table(pred, field, n_fit), "info": info}
                    m["loop"] = fly(pred, field, n_fit, trials=trials, seed=seed, path_length=path_length)
                rec["models"][name] = m
                bar.update(1)
            records.append(rec)
    return records


def print_tables(records: list[dict], say=print) -> None:
    """The two tables of the module docstring, one block per file."""
    for rec in records:
        ms = rec["models"]
        la = {k: {int(h): v for h, v in m["lookahead"].items()} for k, m in ms.items()}  # JSON keys are strings
        hs = sorted(la["persistence"])
        say(
            f"\n{rec['file']}: {rec['n_times']} snapshots every {rec['dt_h']:g} h; fit 0..{rec['n_fit'] - 1}, "
            f"held out {rec['n_fit']}..{rec['n_times'] - 1}"
        )
        say("  lookahead MSE (m/s)^2 [ratio to persistence], h in snapshots (" + ", ".join(
            f"h={h}: {h * rec['dt_h']:g} h" for h in hs) + ")")  # fmt: skip
        for name, m in ms.items():
            cells = [f"{la[name][h]:.3e} [{la[name][h] / la['persistence'][h]:.2f}]" for h in hs]
            say(f"    {name:<12} " + "  ".join(cells))
        loop = ms["persistence"]["loop"]
        say(
            f"  PASST mean RMSE (m/s) over the held-out snapshots, {len(loop['passt'])} trials, "
            f"legs of {loop['steps_per_leg']} snapshot(s): mean +- std [model alone]"
        )
        ref = {k: np.asarray(ms[k]["loop"]["passt"]) for k in ("persistence", "dmd")}
        say(
            "    (paired over the trials: PASST's RMSE minus the one with persistence / DMD, mean +- std, lower in k/n)"
        )
        for name, m in ms.items():
            p = np.asarray(m["loop"]["passt"])
            paired = "  ".join(
                f"vs {k} {(p - q).mean():+.4f} +- {(p - q).std():.4f} lower {(p < q).sum()}/{len(p)}"
                for k, q in ref.items()
                if k != name
            )
            say(f"    {name:<12} {p.mean():.4f} +- {p.std():.4f}  [{m['loop']['model']:.4f}]  {paired}")
        for name, m in ms.items():
            if m["info"].get("command"):
                i = m["info"]
                say(
                    f"  {name}: {i['epochs']} epochs, best {i['best_epoch']}, {i['s_per_epoch']} s/epoch: {i['command']}"
                )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", default="rtofs,gridded,hfradar", help="comma-separated keys of real_data_loop.FILES")
    ap.add_argument("--seed", type=int, default=0, help="regions, KNODE weights; trial i uses seed + i")
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--epochs", type=int, default=30, help="KNODE epochs")
    ap.add_argument("--path-length", type=int, default=20, help="moves per leg")
    ap.add_argument("--out", default="runs/model_real_files", help="folder for the regions and checkpoints")
    ap.add_argument("--json", default=None, help="write the records here")
    ap.add_argument("--tables", nargs="+", default=None, help="only print the tables of these --json files")
    a = ap.parse_args(argv)
    if a.tables:
        missing = [f for f in a.tables if not Path(f).is_file()]
        if missing:
            print(f"model_real_files: error: --tables: no such file: {', '.join(missing)}", file=sys.stderr)
            return 2
        print_tables([r for f in a.tables for r in json.loads(Path(f).read_text())])
        return 0
    import real_data_loop as rdl

    files = [f for f in a.files.split(",") if f]
    unknown = [f for f in files if f not in rdl.FILES]
    absent = [f for f in files if f in rdl.FILES and not (rdl.DATA / rdl.FILES[f][0]).exists()]
    problem = (
        f"--files: unknown key(s) {', '.join(unknown)}; choose from {', '.join(rdl.FILES)}"
        if unknown or not files
        else f"--files: not found in {rdl.DATA}: {', '.join(rdl.FILES[f][0] for f in absent)}"
        if absent
        else f"--trials {a.trials} and --epochs {a.epochs} must be at least 1"
        if min(a.trials, a.epochs) < 1
        else None
    )
    if problem:
        print(f"model_real_files: {problem}", file=sys.stderr)
        return 2
    records = run(files, seed=a.seed, trials=a.trials, epochs=a.epochs, path_length=a.path_length, out=Path(a.out))
    print_tables(records)
    if a.json:
        Path(a.json).write_text(json.dumps(records, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
