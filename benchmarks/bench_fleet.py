"""Benchmark: joint planning per leg interval of the offline fleet (passt_mav.loop.engine.run_offline_fleet) vs one boat.

    .venv/bin/python benchmarks/bench_fleet.py --json
    .venv/bin/python benchmarks/bench_fleet.py --boats 3 --path-length 100 --legs 4

The field is builtin:cylinder (30x30) with the shipped cylinder KNODE and the policy-gradient
planner, L moves per boat per leg. Offline, the fleet's boats plan from one forecast and one
reward map, each keeping out of the earlier boats' cells (passt_mav.loop.engine.run_offline_fleet);
the joint planning of one leg interval is the reward map and every boat's planner call
(with its same-move repairs). The forecast is shared by all boats and reported apart: offline it
is the whole leg's roll-out (10 snapshots, the GP prior), while planning needs only its first
step (the live loop predicts one step to plan: benchmarks/bench_fleet_planning.py, ocean KNODE,
one forecast per boat). The GP update is not planning and is left out. Printed side by side in
one run: seconds per leg interval for 1 boat and for N boats (median over the legs after the
first, which pays for warm-up), their ratio, the worst leg and the shared forecast's time.
Target (issue 15): 3 boats at 30x30, L = 100, planning under 1 s.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

KEYS = ("reward", "plan")  # joint planning; "predict" is the shared forecast


def _intervals(field, predictor, boats: int, path_length: int, legs: int) -> dict:
    from passt_mav.loop.campaign import fleet_starts
    from passt_mav.loop.engine import run_offline_fleet

    r = run_offline_fleet(
        field,
        predictor,
        start_cells=fleet_starts(field, 0, 0, path_length, boats),
        t0=0,
        n_steps=10 * (legs + 1),
        path_length=path_length,
        steps_per_leg=10,
        noise_std=0.02,
        seed=0,
    )
    walls = [sum(leg["timings"][k] for k in KEYS) for leg in r.legs[1:]]  # leg 0 warms up
    return {
        "boats": boats,
        "s_per_interval": statistics.median(walls),
        "s_max": max(walls),
        "legs": len(walls),
        "split_s": {k: statistics.median(leg["timings"][k] for leg in r.legs[1:]) for k in KEYS},
        "forecast_s": statistics.median(leg["timings"]["predict"] for leg in r.legs[1:]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boats", type=int, default=3)
    ap.add_argument("--path-length", type=int, default=100)
    ap.add_argument("--legs", type=int, default=3, help="timed leg intervals (after one warm-up leg)")
    ap.add_argument("--model", default="builtin:cylinder")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.boats < 1 or a.legs < 1 or a.path_length < 1:
        print("bench_fleet: --boats, --legs and --path-length must be >= 1", file=sys.stderr)
        return 2
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.models.base import load_predictor

    field = resolve_field("builtin:cylinder")
    predictor = load_predictor(a.model)
    one = _intervals(field, predictor, 1, a.path_length, a.legs)
    many = _intervals(field, predictor, a.boats, a.path_length, a.legs)
    out = {
        "path_length": a.path_length,
        "grid": "x".join(map(str, field.grid.shape)),
        "model": a.model,
        "one_boat": one,
        "fleet": many,
        "ratio_fleet_over_one": many["s_per_interval"] / one["s_per_interval"],
        "target_s": 1.0,
        "meets_target": many["s_max"] < 1.0,
    }
    if a.json:
        print(json.dumps(out, indent=2))
    else:
        print(
            f"L={a.path_length}, {out['grid']}, {a.model}: 1 boat {one['s_per_interval']:.3f} s, {a.boats} boats "
            f"{many['s_per_interval']:.3f} s per leg interval (x{out['ratio_fleet_over_one']:.2f}; worst "
            f"{many['s_max']:.3f} s); {a.boats} boats split "
            + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in many["split_s"].items())
            + f"; shared 10-snapshot forecast {many['forecast_s']:.3f} s (1 boat {one['forecast_s']:.3f} s)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
