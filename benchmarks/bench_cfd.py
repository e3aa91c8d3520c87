"""Benchmark: cylinder CFD (lattice Boltzmann) wall time per output snapshot, and its Strouhal number.

    .venv/bin/python benchmarks/bench_cfd.py                    # full resolution, default run (~minutes)
    .venv/bin/python benchmarks/bench_cfd.py --snapshots 50 --spin-up 80 --json

``time_per_snapshot`` (seconds of wall time per output snapshot, spin-up
excluded) is what the KNODE benchmark compares its prediction time with. The
Strouhal number needs a few shedding periods after spin-up (>= ~50 snapshots at
dt 0.4) to be meaningful; with fewer it is reported but flagged.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--snapshots", type=int, default=100, help="output snapshots to time (default %(default)s)")
    p.add_argument(
        "--spin-up", type=float, default=80.0, dest="spin_up", help="non-dimensional spin-up time (default %(default)s)"
    )
    p.add_argument("--resolution", type=int, default=None, help="cells per radius (default: the shipped data's)")
    p.add_argument("--amplitude", type=float, default=0.0, help="oscillation amplitude in radii (default 0: static)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print JSON")
    args = p.parse_args(argv)

    import torch

    from passt_mav.fields.cylinder import CylinderConfig, run_cylinder_lbm, strouhal_number

    cfg = CylinderConfig(
        n_snapshots=args.snapshots, spin_up=args.spin_up, amplitude=args.amplitude, threads=args.threads
    )
    if args.resolution is not None:
        cfg = CylinderConfig(**{**cfg.__dict__, "resolution": args.resolution})
    lp = cfg.lattice()
    t0 = time.perf_counter()
    run = run_cylinder_lbm(cfg, progress=not args.json)
    total = time.perf_counter() - t0
    spin_steps = lp["spin_up_steps"]
    time_per_step = run.wall_s / run.steps
    result = {
        "benchmark": "cylinder CFD (D2Q9 lattice Boltzmann, torch CPU)",
        "resolution_cells_per_radius": cfg.resolution,
        "lattice_nodes": int(round(50 / lp["dx"]) + 1) * int(round(40 / lp["dx"])),
        "steps_per_snapshot": lp["steps_per_output"],
        "dt_out": cfg.dt_out,
        "snapshots": cfg.n_snapshots,
        "spin_up_steps": spin_steps,
        "time_per_step": time_per_step,
        # the cost of producing one more snapshot once the flow is spun up
        "time_per_snapshot": time_per_step * lp["steps_per_output"],
        "mlups": (run.steps * (int(round(50 / lp["dx"]) + 1) * int(round(40 / lp["dx"])))) / run.wall_s / 1e6,
        "wall_s": total,
        "strouhal": strouhal_number(run.lift, run.dt_lift),
        "strouhal_reliable": cfg.n_snapshots * cfg.dt_out >= 20.0,
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(
            f"cylinder CFD, {cfg.resolution} cells/radius, {result['lattice_nodes']} nodes, {result['threads']} thread(s)"
        )
        print(f"  time per lattice step : {result['time_per_step'] * 1e3:.2f} ms ({result['mlups']:.1f} MLUPS)")
        print(
            f"  time per snapshot     : {result['time_per_snapshot']:.3f} s ({lp['steps_per_output']} steps, dt {cfg.dt_out})"
        )
        print(f"  total wall time       : {total:.1f} s for {run.steps} steps")
        flag = "" if result["strouhal_reliable"] else " (too few snapshots to be reliable)"
        print(f"  Strouhal number       : {result['strouhal']:.4f}{flag}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
