"""Benchmark: planning one leg with the information reward (issue 27) vs the paper's planner.

    .venv/bin/python benchmarks/bench_information.py --json
    .venv/bin/python benchmarks/bench_information.py --data builtin:ocean --model builtin:ocean --path-length 100

A PASST loop on the field (30x30) with its shipped KNODE and the background covariance (200
snapshots) flies two legs on the true field (so the GP's kernels and background factor are
fitted, as in a campaign's later legs), then the next leg is planned ``--repeats`` times by each
planner/reward, on one thread. Printed side by side in one run: seconds per leg for the reward
map (for ``variance_reduction``: the prior's factors - two truncated eigendecompositions - and
the per-cell gains) and for the planner, and each variant's ratio to the policy-gradient
planner on the speed reward. Target: planning <= 1 s per leg at 30x30, L = 100, on one core.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

VARIANTS = (
    ("policy_gradient", "speed", {}),
    ("greedy", "speed", {}),
    ("information", "variance_reduction", {"beam_width": 1}),
    ("information", "variance_reduction", {"beam_width": 8}),
    ("information", "variance_reduction", {"beam_width": 32}),
    ("policy_gradient", "variance_reduction", {}),
)


def _leg_times(field, predictor, planner: str, reward: str, kw: dict, L: int, repeats: int) -> dict:
    import numpy as np

    from passt_mav.loop.passt import FieldSampler, PasstLoop

    loop = PasstLoop(
        predictor,
        field.grid,
        planner=planner,
        planner_kw=kw,
        reward=reward,
        path_length=L,
        steps_per_leg=10,
        land=field.land_mask,
        background=200,
        gp_kw={"solver": "cholesky"},
    )
    sampler = FieldSampler(field, noise_std=0.02, steps_per_leg=10)
    state = np.array(field.data[0], np.float32)
    start = (field.grid.rows // 2, field.grid.cols // 2)
    for k in range(2):
        leg = loop.plan_leg(state, start, float(field.times[0]) + 10 * k * field.dt, field.dt)
        state = loop.update(leg, sampler.sample_path(leg.path, leg.t_start))
        start = tuple(int(x) for x in leg.path[-1])
    fc = loop.forecast(state, 10)
    rew, pl = [], []
    for _ in range(repeats):
        loop._info_key = None  # rebuild the prior's factors every repeat (a new leg does)
        leg = loop.plan_leg(state, start, 0.0, field.dt, forecast=fc)
        rew.append(leg.timings["reward"])
        pl.append(leg.timings["plan"])
    return {
        "planner": planner,
        "reward": reward,
        "options": kw,
        "reward_s": min(rew),
        "plan_s": min(pl),
        "leg_s": min(rew) + min(pl),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="builtin:cylinder")
    ap.add_argument("--model", default="builtin:cylinder")
    ap.add_argument("--path-length", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    import torch
    from threadpoolctl import threadpool_limits

    from passt_mav.fields.datasets import resolve_field
    from passt_mav.loop.campaign import load_predictor

    torch.set_num_threads(1)
    field = resolve_field(a.data)
    predictor = load_predictor(a.model, field)
    rows = []
    with threadpool_limits(1):
        for planner, reward, kw in VARIANTS:
            rows.append(_leg_times(field, predictor, planner, reward, kw, a.path_length, a.repeats))
    base = rows[0]["leg_s"]
    for r in rows:
        r["ratio_to_pg_speed"] = r["leg_s"] / base
    out = {
        "data": a.data,
        "model": a.model,
        "path_length": a.path_length,
        "grid": f"{field.grid.rows}x{field.grid.cols}",
        "threads": 1,
        "variants": rows,
        "target_s": 1.0,
        "meets_target": all(
            r["leg_s"] <= 1.0 for r in rows if r["planner"] == "information" and r["options"].get("beam_width") == 8
        ),
    }
    if a.json:
        print(json.dumps(out, indent=2))
    else:
        for r in rows:
            print(
                f"{r['planner']:>16} {r['reward']:<18} {json.dumps(r['options']):<20} reward {r['reward_s'] * 1e3:7.1f} ms  "
                f"plan {r['plan_s'] * 1e3:7.1f} ms  leg {r['leg_s'] * 1e3:7.1f} ms  x{r['ratio_to_pg_speed']:.2f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
