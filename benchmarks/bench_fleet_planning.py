"""Benchmark: per-leg planning of a live fleet (passt_mav.loop.legstep.FleetStep.plan_for) vs one boat.

    .venv/bin/python benchmarks/bench_fleet_planning.py --json
    .venv/bin/python benchmarks/bench_fleet_planning.py --boats 3 --path-length 100 --repeats 3

The mission is missions/north_atlantic.yaml's region (30x30) with the shipped ocean KNODE and
the policy-gradient planner, L moves per leg. One "fleet leg interval" is every boat planning
one leg from the same state, one after the other, each keeping out of the paths the boats
before it hold (what the boats do when their legs end together; in flight they plan one at a
time). Printed side by side in one run: wall seconds per leg interval for 1 boat and for N
boats, their ratio, and the split (forecast / reward / planner) of one plan. Target (issue 15):
3 boats at 30x30, L = 100, under 1 s per leg interval.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _fleet_step(boats: int, path_length: int, model: str):
    from passt_mav.commands.demo import fleet_starts, mission_mapping
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.loop.legstep import FleetStep, LegStep, build_loop, build_predictor
    from passt_mav.mission.config import mission_overrides, validate_mission

    base, _ = mission_mapping()
    cfg = validate_mission(
        mission_overrides(base, {"planner.path_length": path_length, "model": model}), source="bench"
    )
    field = resolve_field(cfg.field.source, seed=cfg.seeds.field)
    cells = fleet_starts(field.grid, field.land_mask, tuple(cfg.start_cell), boats)
    data = cfg.model_dump(mode="json")
    data.pop("vehicle")
    data["vehicles"] = [{"connect": f"tcp:127.0.0.1:{5760 + 10 * k}", "speed_mps": 2.0} for k in range(boats)]
    cfg = validate_mission(data, source="bench")
    predictor, _ = build_predictor(cfg.model, field, echo=lambda s: None)
    step = LegStep(cfg, field, build_loop(cfg, predictor, field.grid, land=field.land_mask))
    return FleetStep(step), cells


def _interval(boats: int, path_length: int, model: str, repeats: int) -> dict:
    fs, cells = _fleet_step(boats, path_length, model)
    fs.plan_for(0, 0, cells[0], k=0)  # warm-up (first predictor call, planner compilation)
    fs.release(0)
    walls, split = [], {}
    for r in range(repeats):
        t0 = time.perf_counter()
        for b in range(boats):
            planned = fs.plan_for(b, 1 + r * boats + b, cells[b], k=0)
            for key, x in planned.plan.timings.items():
                split[key] = split.get(key, 0.0) + x
        walls.append(time.perf_counter() - t0)
        for b in range(boats):
            fs.release(b)
    n = repeats * boats
    return {
        "boats": boats,
        "wall_s_per_interval": min(walls),
        "wall_s_mean": sum(walls) / len(walls),
        "per_plan_split_s": {k: v / n for k, v in split.items()},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boats", type=int, default=3)
    ap.add_argument("--path-length", type=int, default=100)
    ap.add_argument("--model", default="builtin:ocean")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.threads:
        import torch

        torch.set_num_threads(a.threads)
    one = _interval(1, a.path_length, a.model, a.repeats)
    many = _interval(a.boats, a.path_length, a.model, a.repeats)
    out = {
        "path_length": a.path_length,
        "grid": "30x30",
        "model": a.model,
        "one_boat": one,
        "fleet": many,
        "ratio_fleet_over_one": many["wall_s_per_interval"] / one["wall_s_per_interval"],
        "target_s": 1.0,
        "meets_target": many["wall_s_per_interval"] < 1.0,
    }
    if a.json:
        print(json.dumps(out, indent=2))
    else:
        print(
            f"L={a.path_length}, 30x30, {a.model}: 1 boat {one['wall_s_per_interval']:.3f} s, "
            f"{a.boats} boats {many['wall_s_per_interval']:.3f} s per leg interval "
            f"(x{out['ratio_fleet_over_one']:.2f}); split per plan "
            + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in many["per_plan_split_s"].items())
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
