"""Benchmark: KNODE prediction throughput and training time per epoch, vs the CFD solver.

    .venv/bin/python benchmarks/bench_models.py --json          # shipped cylinder KNODE if present
    .venv/bin/python benchmarks/bench_models.py --quick --json

``predict_time_per_snapshot_batch1`` / ``..._batched`` are seconds of wall time per
predicted snapshot (one ``predict`` step = one snapshot interval, 6 Euler sub-steps);
``passt-mav bench`` divides the CFD's ``time_per_snapshot`` by the first one. The CFD
figure printed here is the shipped cylinder's recorded wall time per snapshot
(passt_mav/assets/README.md: 314 s for 500 snapshots + spin-up) unless
``benchmarks/bench_cfd.py`` is run alongside.

Training is also put against this CPU's fp32 limit: the FLOPs of an epoch (torch's
FlopCounterMode on one snapshot step, forward + backward) per second of each path, as a
fraction of a 2048 x 2048 matmul's rate in the same process (``train_fraction_of_matmul_*``).
Measured on the 2-core machine, 1 thread: eager 0.72, compiled 0.83 - the eager path is
already near the limit, so no path exact to fp32 rounding can train 2x faster here.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

# passt_mav/assets/README.md, cylinder.nc: 314 s wall for 31,961 lattice steps, 40 per snapshot
CFD_RECORDED_S_PER_SNAPSHOT = 314.0 / 31961 * 40


def _step_train_flops(net) -> float:
    """FLOPs of one snapshot step (6 Euler sub-steps) forward and backward, batch 1, as
    torch's FlopCounterMode counts them (convolutions and matmuls)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from passt_mav.models.knode import ode_step

    z = torch.zeros(1, 2, net.rows, net.cols, requires_grad=True)
    with FlopCounterMode(display=False) as fc:
        ode_step(net, z, 1.0, 6).square().sum().backward()
    net.zero_grad(set_to_none=True)
    return float(fc.get_total_flops())


def _matmul_gflops(n: int = 2048, reps: int = 5) -> float:
    """fp32 GFLOP/s of an n x n matmul at the current torch thread count (the CPU's practical peak)."""
    import torch

    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    t0 = time.perf_counter()
    for _ in range(reps):
        a @ b
    return 2 * n**3 * reps / (time.perf_counter() - t0) / 1e9


def _train_paths(f, quick: bool) -> dict:
    """Training s/epoch of the loop recipe (roll-out over 10 snapshots, batch 32) on the eager
    and the compiled path (``compile=True``: the compiled snapshot step), side by side in this
    one process, plus batched prediction eager / channels-last / compiled with freezing (what
    ``fast_predict`` runs). Each path trains the same network from the same seed for the same
    epochs; the first (compiling) epoch is timed separately."""
    import copy

    import numpy as np
    import torch

    from passt_mav.models import make_predictor
    from passt_mav.models.fast import compiled_or_eager
    from passt_mav.models.knode import ode_step

    epochs = 2 if quick else 4
    out = {}
    # 96 training ICs in batches of 32: every batch has one shape, so the compiled path
    # compiles once (in the first epoch, timed separately); s/epoch = mean of the later epochs
    kw = dict(
        loss="rollout",
        horizon=10,
        curriculum=0.0,
        noise="white",
        val_frac=0.0,
        zero_init=True,
        train_batch=32,
        progress=False,
        seed=0,
    )
    for name, opts in (("eager", {}), ("compiled", {"compile": True})):
        stamps = [time.perf_counter()]
        m = make_predictor("knode", epochs=epochs, **kw, **opts)
        m.fit(f, start=200, stop=306, callback=lambda ep, loss, stamps=stamps: stamps.append(time.perf_counter()))
        dts = np.diff(stamps)
        out[f"train_first_epoch_s_{name}"] = float(dts[0])
        out[f"train_s_per_epoch_{name}"] = float(np.mean(dts[1:]))
    out["train_speedup_compiled_over_eager"] = out["train_s_per_epoch_eager"] / out["train_s_per_epoch_compiled"]
    # how close each path is to this CPU's fp32 limit: the training FLOPs of an epoch
    # (counted by torch for one snapshot step, forward + backward, times ICs x horizon)
    # against a large matmul's rate in the same process and thread count
    n_ics = (306 - 200) - kw["horizon"]
    gflop = n_ics * kw["horizon"] * _step_train_flops(m.net_) / 1e9
    peak = _matmul_gflops()
    out["matmul_gflops"] = peak
    for name in ("eager", "compiled"):
        rate = gflop / out[f"train_s_per_epoch_{name}"]
        out[f"train_gflops_{name}"] = rate
        out[f"train_fraction_of_matmul_{name}"] = rate / peak
    net = m.net_
    x = torch.from_numpy(np.nan_to_num(f.data[300:364]).astype(np.float32))
    eager = lambda z: ode_step(net, z, 1.0, 6)  # noqa: E731
    cl_net = copy.deepcopy(net).to(memory_format=torch.channels_last)
    cl = lambda z: ode_step(cl_net, z.contiguous(memory_format=torch.channels_last), 1.0, 6)  # noqa: E731
    comp = compiled_or_eager(eager, net, options={"freezing": True})  # what KnodePredictor.fast_predict runs
    reps = 2 if quick else 5
    with torch.no_grad():
        ref = eager(x)
        out["predict_max_abs_diff_compiled_vs_eager"] = float((comp(x) - ref).abs().max())
        out["predict_max_abs_diff_channels_last_vs_eager"] = float((cl(x) - ref).abs().max())
        for name, fn in (("eager", eager), ("channels_last", cl), ("compiled", comp)):
            fn(x)
            t0 = time.perf_counter()
            for _ in range(reps):
                fn(x)
            out[f"predict_batch64_s_per_snapshot_{name}"] = (time.perf_counter() - t0) / (reps * len(x))
    out["predict_speedup_compiled_over_eager"] = (
        out["predict_batch64_s_per_snapshot_eager"] / out["predict_batch64_s_per_snapshot_compiled"]
    )
    out["predict_speedup_channels_last_over_eager"] = (
        out["predict_batch64_s_per_snapshot_eager"] / out["predict_batch64_s_per_snapshot_channels_last"]
    )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer repetitions")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--batch", type=int, default=64, help="initial conditions in the batched run (default 64)")
    p.add_argument("--json", action="store_true", help="print JSON")
    a = p.parse_args(argv)

    import numpy as np
    import torch

    torch.set_num_threads(a.threads)
    from passt_mav.fields.datasets import load_dataset
    from passt_mav.models import make_predictor
    from passt_mav.models.base import load_predictor

    f = load_dataset("cylinder")
    try:
        model, source = load_predictor("builtin:cylinder"), "builtin:cylinder"
    except Exception:  # noqa: BLE001 - untrained weights time the same
        model, source = (
            make_predictor("knode", epochs=0, progress=False).fit(f, start=200, stop=300),
            "untrained (no shipped model)",
        )
    steps = 5 if a.quick else 20
    x1 = np.nan_to_num(f.data[300])
    model.predict(x1, 1)  # warm-up
    t0 = time.perf_counter()
    model.predict(x1, steps)
    t_b1 = (time.perf_counter() - t0) / steps
    xb = np.nan_to_num(f.data[300 : 300 + a.batch])
    bsteps = 2 if a.quick else 5
    t0 = time.perf_counter()
    model.predict(xb, bsteps)
    t_bb = (time.perf_counter() - t0) / (bsteps * len(xb))
    epochs = 1 if a.quick else 3
    tr = make_predictor("knode", epochs=epochs, progress=False, seed=0)
    t0 = time.perf_counter()
    tr.fit(f, start=200, stop=300)
    t_ep = (time.perf_counter() - t0) / epochs
    train_paths = _train_paths(f, a.quick)
    t0 = time.perf_counter()
    dmd = make_predictor("dmd").fit(f, start=200, stop=300)
    t_dmd_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    dmd.predict(xb, bsteps)
    t_dmd = (time.perf_counter() - t0) / (bsteps * len(xb))
    cfd = CFD_RECORDED_S_PER_SNAPSHOT
    res = {
        "benchmark": "KNODE (30x30 cylinder, Euler x6 per snapshot, torch CPU)",
        "model": source,
        "threads": torch.get_num_threads(),
        "predict_time_per_snapshot_batch1": t_b1,
        "predict_snapshots_per_s_batch1": 1.0 / t_b1,
        "predict_time_per_snapshot_batched": t_bb,
        "predict_snapshots_per_s_batched": 1.0 / t_bb,
        "batch": len(xb),
        "train_s_per_epoch_100_snapshots": t_ep,
        **train_paths,
        "dmd_fit_s": t_dmd_fit,
        "dmd_predict_time_per_snapshot_batched": t_dmd,
        "cfd_recorded_time_per_snapshot": cfd,
        "cfd_over_knode_batch1": cfd / t_b1,
        "cfd_over_knode_batched": cfd / t_bb,
    }
    if a.json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:>40}: {v:.4g}" if isinstance(v, float) else f"{k:>40}: {v}")
        print(
            f"KNODE predicts a snapshot {cfd / t_b1:.0f}x (batch 1) / {cfd / t_bb:.0f}x (batched) faster than the CFD makes one"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
