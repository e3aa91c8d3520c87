"""Benchmark the PASST loop.

1. Per-leg compute in milliseconds at 30x30 for L = 50, 100, 200 moves (one sample per
   cell): predict (steps_per_leg snapshots), reward, plan (policy gradient: 12 stochastic
   roll-outs + greedy), GP (hyper-parameter fit + reconstruction). Median over legs.
2. Wall time of a reduced campaign (passt-mav evaluate's run_campaign) run serially,
   with joblib on 2 local workers, and on a 2-worker Dask LocalCluster; ratios to serial.

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

    from passt_mav.passt import FieldSampler, PasstLoop

    loop = PasstLoop(predictor, field.grid, planner="policy_gradient", path_length=L, steps_per_leg=steps_per_leg, prior="forecast" if predictor is not None else "none", land=field.land_mask, seed=0)
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


def campaign(field, predictor, args) -> dict:
    from passt_mav.commands.evaluate import run_campaign

    kw = dict(path_lengths=tuple(args.campaign_lengths), trials=args.trials, steps=args.steps, steps_per_leg=args.steps_per_leg, progress=False)
    if predictor is None:  # hold mode: only the GP-only baselines can run
        kw["methods"] = ("lawnmower_gp", "greedy_gp", "random_gp")
    out = {}
    t = time.perf_counter()
    serial = run_campaign(field, predictor, **kw)
    out["serial_s"] = round(time.perf_counter() - t, 2)
    t = time.perf_counter()
    par = run_campaign(field, predictor, workers=2, **kw)
    out["joblib_2_s"] = round(time.perf_counter() - t, 2)
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        t = time.perf_counter()
        dk = run_campaign(field, predictor, scheduler=cluster.scheduler_address, **kw)
        out["dask_2_s"] = round(time.perf_counter() - t, 2)
    same = all(serial["per_L"][L]["rmse_mean"] == o["per_L"][L]["rmse_mean"] for o in (par, dk) for L in serial["per_L"])
    out["identical_numbers"] = same
    out["ratio_joblib_to_serial"] = round(out["joblib_2_s"] / out["serial_s"], 3)
    out["ratio_dask_to_serial"] = round(out["dask_2_s"] / out["serial_s"], 3)
    out["tasks"] = len(args.campaign_lengths) * args.trials
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
    ap.add_argument("--no-campaign", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    args.campaign_lengths = [int(x) for x in args.campaign_lengths.split(",")]

    import torch

    torch.set_num_threads(1)
    from passt_mav.fields.datasets import resolve_field

    field = resolve_field(args.data)
    predictor, used = _predictor(args.model, field)
    res = {"data": args.data, "model": used, "grid": list(field.grid.shape), "cpu_count": os.cpu_count(), "per_leg_ms": {}}
    for L in (int(x) for x in args.lengths.split(",")):
        res["per_leg_ms"][str(L)] = per_leg(field, predictor, L, args.legs, args.steps_per_leg)
    if not args.no_campaign:
        res["campaign"] = campaign(field, predictor, args)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"data {res['data']}, model {res['model']}, grid {res['grid']}, {res['cpu_count']} CPUs")
        print("per-leg compute, ms (median):")
        for L, r in res["per_leg_ms"].items():
            print(f"  L={L:>4}: " + "  ".join(f"{k} {v:8.1f}" for k, v in r.items()))
        if "campaign" in res:
            c = res["campaign"]
            print(f"campaign ({c['tasks']} trials): serial {c['serial_s']} s, joblib x2 {c['joblib_2_s']} s ({c['ratio_joblib_to_serial']}), dask LocalCluster x2 {c['dask_2_s']} s ({c['ratio_dask_to_serial']}); identical numbers: {c['identical_numbers']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
