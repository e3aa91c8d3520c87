"""Benchmark the PASST loop.

1. Per-leg compute in milliseconds at 30x30 for L = 50, 100, 200 moves (one sample per
   cell): predict (steps_per_leg snapshots), reward, plan (policy gradient: 12 stochastic
   roll-outs + greedy), GP (hyper-parameter fit + reconstruction). Median over legs.
2. Engine throughput, side by side in one run, on the same reduced campaign (all five
   methods, ``--campaign-lengths`` x ``--trials`` x ``--steps``): trial-legs per second of
   - ``today``: the original path - one trial after another, GP hyper-parameters refitted
     every leg with sklearn (``engine="serial", hyper="every_leg", gp_solver="sklearn"``);
   - ``serial_fixed``: the same serial path with the paper's fixed kernel (fitted once on
     the initial state, ``hyper="state"``) and the direct Cholesky posterior;
   - ``lockstep``: the campaign engine - the trials of a path length in lockstep, one
     batched predictor call per leg through the model's compiled path (``fast_predict``),
     one batched policy-gradient planning call per leg, fixed kernel, Cholesky posterior;
   - ``paper``: what ``passt-mav paper`` runs: ``lockstep`` with the ``auto`` GP schedule
     (PASST's residual GP refitted every leg, the baselines' fitted once on the state) and
     PASST's background covariance from a 200-snapshot model roll-out;
     every variant above runs in this one process on one thread;
   - ``paper_dask2``: ``paper`` on both cores of a 2-core machine, as ``passt-mav paper
     --scheduler`` runs it (Dask LocalCluster, 2 single-threaded worker processes, the
     trials of a path length in 2 batches) - against ``today`` on one core, so this ratio
     includes the parallelism that the serial path could not use.
   ``--variants`` picks some (``today`` is always the reference; ``paper_dask2`` is not in
   the default set: on a small campaign its workers' compilation dominates). The compiled path's
   first call per batch shape compiles (seconds): a warm-up campaign runs first and is
   not timed.
   Ratios to ``today`` and the per-component split (seconds summed over trial-legs).
   A trial-leg = one leg of one loop method (passt / lawnmower_gp / greedy_gp / random_gp)
   of one trial; the "model" method is one roll-out per campaign.
3. Scale-out of the lockstep engine: serial, joblib x2 and Dask LocalCluster with 1 and 2
   worker processes; whether the numbers are identical.

    .venv/bin/python benchmarks/bench_passt.py [--data builtin:cylinder] [--model builtin:cylinder] [--json]

Without passt_mav.models (predictors) the loop runs in "hold" mode (no model), which
times everything but the predictor; the output says which was used.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from passt_mav.reconstruction.background import DEFAULT_BACKGROUND


def _predictor(spec, field):
    try:
        from passt_mav.models.base import PREDICTORS, load_predictor, make_predictor
    except ImportError:
        return None, "none (hold mode: passt_mav.models not available)"
    try:
        if spec in PREDICTORS:
            return make_predictor(spec).fit(field), spec
        return load_predictor(spec), spec
    except Exception as exc:  # noqa: BLE001 - fall back to persistence and say why
        return make_predictor("persistence").fit(field), f"persistence ({spec} unavailable: {exc})"


def per_leg(field, predictor, L: int, legs: int, steps_per_leg: int) -> dict:
    import numpy as np

    from passt_mav.loop.passt import FieldSampler, PasstLoop

    loop = PasstLoop(
        predictor,
        field.grid,
        planner="policy_gradient",
        path_length=L,
        steps_per_leg=steps_per_leg,
        prior="forecast" if predictor is not None else "none",
        land=field.land_mask,
        seed=0,
    )
    sampler = FieldSampler(field, noise_std=0.02, seed=0, steps_per_leg=steps_per_leg)
    state = field.data[0].copy()
    start = (field.grid.rows // 2, 2)
    rec = {"predict": [], "reward": [], "plan": [], "gp": [], "total": []}
    for k in range(legs):
        t0 = field.times[0] + k * steps_per_leg * field.dt
        leg = loop.plan_leg(state, start, t0, field.dt)
        state = loop.update(leg, sampler.sample_path(leg.path, leg.t_start))
        start = tuple(int(x) for x in leg.path[-1])
        for key in ("predict", "reward", "plan", "gp"):
            rec[key].append(leg.timings[key] * 1e3)
        rec["total"].append(sum(leg.timings[key] for key in ("predict", "reward", "plan", "gp")) * 1e3)
    # the first leg pays imports and checkpoint loading; report the median of the rest
    return {k: round(float(np.median(v[1:] if len(v) > 1 else v)), 2) for k, v in rec.items()}


def _timed(field, predictor, **kw) -> tuple[float, dict]:
    from passt_mav.loop.campaign import run_campaign

    t = time.perf_counter()
    out = run_campaign(field, predictor, **kw)
    return time.perf_counter() - t, out


def _split(summary: dict) -> dict:
    tot: dict = {}
    for d in summary["timings_s"].values():
        for k, v in d.items():
            tot[k] = round(tot.get(k, 0.0) + v, 2)
    return tot


VARIANT_LOCKSTEP = dict(engine="lockstep", hyper="state", gp_solver="cholesky", fast_predict=True)
VARIANT_PAPER = dict(VARIANT_LOCKSTEP, hyper="auto", background=DEFAULT_BACKGROUND)
VARIANTS = ("today", "serial_fixed", "lockstep", "paper", "paper_dask2")


def throughput(field, predictor, args) -> dict:
    kw = dict(
        path_lengths=tuple(args.campaign_lengths),
        trials=args.trials,
        steps=args.steps,
        steps_per_leg=args.steps_per_leg,
        progress=False,
    )
    if predictor is None:  # hold mode: only the GP-only baselines can run
        kw["methods"] = ("lawnmower_gp", "greedy_gp", "random_gp")
    variants = {
        "today": dict(engine="serial", hyper="every_leg", gp_solver="sklearn"),
        "serial_fixed": dict(engine="serial", hyper="state", gp_solver="cholesky"),
        "lockstep": VARIANT_LOCKSTEP,
        "paper": VARIANT_PAPER,
        # the same on this machine's 2 cores, as `passt-mav paper --scheduler` runs it: a Dask
        # LocalCluster of 2 single-threaded worker processes, each path length's trials in 2 batches
        "paper_dask2": dict(VARIANT_PAPER, batch=max(1, -(-args.trials // 2))),
    }
    variants = {k: v for k, v in variants.items() if k in args.variants}
    out: dict = {}
    _timed(field, predictor, **dict(kw, steps=args.steps_per_leg), **VARIANT_LOCKSTEP)  # compile outside the timing
    for name, v in variants.items():
        if name == "paper_dask2":
            wall, s = _dask_timed(field, predictor, 2, dict(kw, **v), warm=dict(kw, steps=args.steps_per_leg, **v))
        else:
            wall, s = _timed(field, predictor, **kw, **v)
        out[name] = {
            "wall_s": round(wall, 2),
            "trial_legs": s["trial_legs"],
            "trial_legs_per_s": round(s["trial_legs"] / wall, 2),
            "split_s": _split(s),
            "final_rmse": {L: {m: round(x, 4) for m, x in per["final_rmse"].items()} for L, per in s["per_L"].items()},
        }
    for name in set(out) - {"today"}:
        out[name]["speedup_vs_today"] = round(out[name]["trial_legs_per_s"] / out["today"]["trial_legs_per_s"], 2)
    return out


def _dask_timed(field, predictor, n_workers: int, kw: dict, warm: dict) -> tuple[float, dict]:
    """``_timed`` on a fresh Dask LocalCluster of ``n_workers`` single-threaded processes.

    A one-leg warm-up campaign with the same batch shapes runs on the cluster first, so
    the timed run's workers find the compiled model in inductor's on-disk cache (they
    still trace it once per batch shape, as the workers of a real run do).
    """
    from distributed import LocalCluster

    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        _timed(field, predictor, scheduler=cluster.scheduler_address, **warm)
        return _timed(field, predictor, scheduler=cluster.scheduler_address, **kw)


def scale_out(field, predictor, args) -> dict:
    from distributed import LocalCluster

    kw = dict(
        path_lengths=tuple(args.campaign_lengths),
        trials=args.trials,
        steps=args.steps,
        steps_per_leg=args.steps_per_leg,
        progress=False,
        hyper="state",
        engine="lockstep",
        batch=max(1, args.trials // 2),
    )
    if predictor is None:
        kw["methods"] = ("lawnmower_gp", "greedy_gp", "random_gp")
    out = {}
    wall, serial = _timed(field, predictor, **kw)
    out["serial_s"] = round(wall, 2)
    wall, par = _timed(field, predictor, workers=2, **kw)
    out["joblib_2_s"] = round(wall, 2)
    runs = [par]
    for n in (1, 2):
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
            wall, dk = _timed(field, predictor, scheduler=cluster.scheduler_address, **kw)
        out[f"dask_{n}_s"] = round(wall, 2)
        runs.append(dk)
    out["identical_numbers"] = all(
        serial["per_L"][L]["rmse_mean"] == o["per_L"][L]["rmse_mean"] for o in runs for L in serial["per_L"]
    )
    out["tasks"] = len(args.campaign_lengths) * len(range(0, args.trials, kw["batch"]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="builtin:cylinder")
    ap.add_argument("--model", default="builtin:cylinder")
    ap.add_argument("--lengths", default="50,100,200")
    ap.add_argument("--legs", type=int, default=6)
    ap.add_argument("--steps-per-leg", type=int, default=10)
    ap.add_argument("--trials", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--campaign-lengths", default="50")
    ap.add_argument(
        "--variants",
        default="today,serial_fixed,lockstep,paper",
        help=f"engine variants to time, a comma list of {', '.join(VARIANTS)} ('today' is the reference and always needed; paper_dask2 pays the workers' compilation, so time it on a protocol-sized campaign)",
    )
    ap.add_argument("--no-campaign", action="store_true", help="skip the throughput comparison")
    ap.add_argument("--no-scale", action="store_true", help="skip the joblib / Dask scale-out")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    args.campaign_lengths = [int(x) for x in args.campaign_lengths.split(",")]
    args.variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    if set(args.variants) - set(VARIANTS) or "today" not in args.variants:
        ap.error(
            f"--variants: choose from {', '.join(VARIANTS)} and include 'today' (the ratios' reference); got {','.join(args.variants)}"
        )

    import torch

    torch.set_num_threads(1)
    from passt_mav.fields.datasets import resolve_field

    field = resolve_field(args.data)
    predictor, used = _predictor(args.model, field)
    res = {
        "data": args.data,
        "model": used,
        "grid": list(field.grid.shape),
        "cpu_count": os.cpu_count(),
        "per_leg_ms": {},
    }
    for L in (int(x) for x in args.lengths.split(",")):
        res["per_leg_ms"][str(L)] = per_leg(field, predictor, L, args.legs, args.steps_per_leg)
    if not args.no_campaign:
        res["throughput"] = throughput(field, predictor, args)
    if not args.no_scale:
        res["scale_out"] = scale_out(field, predictor, args)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"data {res['data']}, model {res['model']}, grid {res['grid']}, {res['cpu_count']} CPUs")
        print("per-leg compute, ms (median):")
        for L, r in res["per_leg_ms"].items():
            print(f"  L={L:>4}: " + "  ".join(f"{k} {v:8.1f}" for k, v in r.items()))
        if "throughput" in res:
            print(
                f"engine throughput, L={args.campaign_lengths}, {args.trials} trials x {args.steps} steps (trial-legs/s; split = seconds summed over trial-legs):"
            )
            for name, r in res["throughput"].items():
                sp = f"  x{r['speedup_vs_today']} vs today" if "speedup_vs_today" in r else ""
                print(
                    f"  {name:>12}: {r['wall_s']:7.2f} s  {r['trial_legs']} trial-legs  {r['trial_legs_per_s']:7.2f}/s{sp}  split {r['split_s']}"
                )
        if "scale_out" in res:
            c = res["scale_out"]
            print(
                f"lockstep scale-out ({c['tasks']} batches): serial {c['serial_s']} s, joblib x2 {c['joblib_2_s']} s, dask LocalCluster x1 {c['dask_1_s']} s, x2 {c['dask_2_s']} s; identical numbers: {c['identical_numbers']}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
