"""Train the policy-gradient planner and write the shipped checkpoint.

    python -m passt_mav.planning.train --episodes 6000 --seed 0 --out passt_mav/assets/pg_planner.pt

Writes ``OUT`` (torch state_dict) and ``OUT.json`` (command, seed, episodes,
training curve, evaluation on held-out maps). Single-threaded CPU; minutes.
"""

from __future__ import annotations

import argparse
import sys
import time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m passt_mav.planning.train", description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=6000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--hidden", type=int, default=16)
    ap.add_argument("--lr", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="checkpoint path (default: the shipped passt_mav/assets/pg_planner.pt)")
    args = ap.parse_args(argv)

    import numpy as np
    import torch

    torch.set_num_threads(1)
    from passt_mav.planning.baselines import GreedyPlanner, RandomPlanner
    from passt_mav.planning.grid import path_reward, top_l_bound
    from passt_mav.planning.policy_gradient import (
        DEFAULT_CHECKPOINT,
        PolicyGradientPlanner,
        cache_policy,
        random_reward_map,
        save_policy,
        train_policy,
    )

    t0 = time.perf_counter()
    w, curve = train_policy(episodes=args.episodes, batch=args.batch, hidden=args.hidden, lr=args.lr, seed=args.seed)
    train_s = time.perf_counter() - t0
    out = args.out or DEFAULT_CHECKPOINT
    # held-out evaluation (seed 10_000 + seed): fraction of the top-L bound collected
    rng = np.random.default_rng(10_000 + args.seed)
    cache_policy(out, w)
    pg = PolicyGradientPlanner(checkpoint=out)
    fr = {"policy_gradient": [], "greedy": [], "random": []}
    for i in range(40):
        q, trav = random_reward_map(rng, 30, 30)
        cells = np.argwhere(trav)
        s = cells[rng.integers(len(cells))]
        L = int(rng.integers(20, 150))
        ub = top_l_bound(q, s, L)
        for name, pl in (("policy_gradient", pg), ("greedy", GreedyPlanner()), ("random", RandomPlanner())):
            fr[name].append(path_reward(q, pl.plan(q, s, L, seed=i, mask=trav), include_start=False) / ub)
    meta = {
        "command": "python -m passt_mav.planning.train " + " ".join(argv if argv is not None else sys.argv[1:]),
        "seed": args.seed,
        "episodes": args.episodes,
        "batch": args.batch,
        "lr": args.lr,
        "train_seconds": round(train_s, 1),
        "curve": {"episodes": [c[0] for c in curve], "fraction_of_top_L": [round(c[1], 4) for c in curve]},
        "heldout_30x30_40maps_fraction_of_top_L": {k: round(float(np.mean(v)), 4) for k, v in fr.items()},
    }
    p, j = save_policy(w, out, meta)
    print(
        f"trained in {train_s:.0f} s; held-out fraction of top-L bound: {meta['heldout_30x30_40maps_fraction_of_top_L']}"
    )
    print(f"wrote {p} and {j}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
