"""Where the DMD-knowledge KNODE loses to DMD on the static cylinder wake: the untrained knowledge model per
complement rule and DMD rank, beside the trained ``builtin:cylinder-dmd``.

    .venv/bin/python benchmarks/knode_dmd_static_gap.py            # prints the table
    .venv/bin/python benchmarks/knode_dmd_static_gap.py --checkpoint runs/knode_x   # and a trained candidate

Every model's DMD is fitted on the static wake's snapshots 200..299 (``builtin:cylinder``, the shipped
models' training window). MSE (field units^2) at lookaheads 1, 5, 10 and 20 snapshots from the true
states of 300..399 (every snapshot an initial condition, :func:`passt_mav.models.evaluate.lookahead_errors`)
on the static wake and on the oscillating wake (``builtin:oscillating``, never trained on). The
untrained models are the KNODE with ``knowledge="dmd"`` and its correction at zero (``epochs=0``):
``dz/dt = L z`` inside DMD's subspace, the complement kept, dropped or decayed at a rate per snapshot
interval. The last column is the validation the training selects on, without its shifted copies: the
MSE averaged over lookaheads 1..10 from the true states of 280..299 of the static wake.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

LOOKAHEADS = (1, 5, 10, 20)
#: snapshots (start, stop) the models are fitted on, scored on, and the validation window
TRAIN, TEST, VAL = (200, 300), (300, 400), (280, 300)
#: (label, knowledge_complement, knowledge_energy) of the untrained variants
VARIANTS = (
    ("drop, energy 0.999", "drop", 0.999),
    ("keep, energy 0.999", "keep", 0.999),
    ("rate 0.2, energy 0.999", "0.2", 0.999),
    ("keep, energy 0.9999", "keep", 0.9999),
    ("rate 0.2, energy 0.9999", "0.2", 0.9999),
)


def models(static, checkpoints=(), *, train=TRAIN, shipped: bool = True, **knode_kw) -> list[tuple[str, object]]:
    """(label, fitted predictor): DMD at the default energy 0.999 and at 0.9999, the untrained variants
    (``knode_kw``: further KNODE options), fitted on ``static``'s snapshots ``train`` (start, stop); with
    ``shipped`` the shipped ``builtin:cylinder-dmd``; the KNODE ``checkpoints``."""
    from passt_mav.models.base import load_predictor, make_predictor

    out = []
    for energy in (0.999, 0.9999):
        p = make_predictor("dmd", energy=energy).fit(static, start=train[0], stop=train[1])
        out.append((f"DMD, energy {energy} (rank {p.rank_})", p))
    for label, comp, energy in VARIANTS:
        p = make_predictor(
            "knode", epochs=0, zero_init=True, noise="white", knowledge="dmd", knowledge_complement=comp,
            knowledge_energy=energy, progress=False, **knode_kw,
        ).fit(static, start=train[0], stop=train[1])  # fmt: skip
        out.append((f"untrained, {label} (rank {p.knowledge_info_['rank']})", p))
    if shipped:
        out.append(("builtin:cylinder-dmd (trained, rate 0.2)", load_predictor("builtin:cylinder-dmd")))
    out += [(str(c), load_predictor(c)) for c in checkpoints]
    return out


def table_rows(preds, static, osc, *, test=TEST, val=VAL, lookaheads=LOOKAHEADS):
    """One markdown row per (label, predictor): MSE at ``lookaheads`` from the true states of ``test`` on
    ``static`` and ``osc``, and the mean MSE over lookaheads 1..10 from the true states of ``val`` on ``static``."""
    from passt_mav.models.evaluate import lookahead_errors

    for label, p in preds:
        cells = []
        for f in (static, osc):
            e = lookahead_errors(p, f.data, test, lookaheads)
            cells.append(" / ".join(f"{e[h]['mse']:.2e}" for h in lookaheads))
        v = lookahead_errors(p, static.data, val, range(1, 11))
        cells.append(f"{np.mean([r['mse'] for r in v.values()]):.2e}")
        yield f"| {label} | " + " | ".join(cells) + " |"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--checkpoint", action="append", default=[], help="also this KNODE checkpoint (repeatable)")
    a = ap.parse_args(argv)
    import torch

    from passt_mav.fields.datasets import resolve_field

    torch.set_num_threads(a.threads)
    static, osc = resolve_field("builtin:cylinder"), resolve_field("builtin:oscillating")
    hs = " / ".join(f"h={h}" for h in LOOKAHEADS)
    print(f"| model | static wake {hs} | oscillating wake {hs} | static 280:300, mean h=1..10 |")
    print("|---|---|---|---|")
    for row in table_rows(models(static, a.checkpoint), static, osc):
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
