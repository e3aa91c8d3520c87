"""Item 6 of issue 27 on held-out real series: a predictor fitted on the first half of a series,
PASST flown over the second half with each prior blend.

    .venv/bin/python benchmarks/heldout_prior_blend.py builtin:rtofs /tmp/gc2.nc

(``/tmp/gc2.nc``: ``passt-mav data import ../shared/data/gridded_current.nc --region
47.0,-125.92,49.04,-123.92 --grid 20x20 --out /tmp/gc2.nc``; the data stay in ../shared/data.)

Per series: DMD fitted on snapshots ``[0, n/2)`` (and persistence), PASST started from the truth at
snapshot ``n/2`` and flown to the end in legs of one snapshot, ``--moves`` moves a leg, information
planner with the variance-reduction reward, GP with the sensor noise ``--noise`` (m/s), ``bias`` on
and the DMD's 200-snapshot background; the samples read from the true field along each path at the
times a constant-speed boat passes each cell. Rows: the DMD prior without a blend, with ``select``
and with ``bma``, persistence as the prior without a blend and with ``select`` (which may move it to
none, the GP of the samples alone), and a lawnmower with the GP alone (no prior mean, the
demo's counterfactual) over the same legs. Printed: each row's mean RMSE (m/s, over water)
over the last half of the legs, mean over ``--seeds`` seeds (planner, GP and sensor seed s), and
each seed's figure. Offline arithmetic (analysis.counterfactual's leg flyer), no vehicle.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

ROWS = ("dmd off", "dmd select", "dmd bma", "persistence prior", "persistence select", "lawnmower + GP")


def fly(
    field,
    predictor,
    blend: str,
    seed: int,
    *,
    moves: int = 10,
    noise: float = 0.02,
    share: float = 0.0,
    forgetting: float = 0.8,
) -> float:
    """Mean RMSE (field units) over the last half of the one-snapshot legs flown over the second
    half of ``field`` from the truth at its middle snapshot (see the module docstring)."""
    from passt_mav.analysis.counterfactual import _fly_rounds
    from passt_mav.loop.passt import FieldSampler, LoopOptions
    from passt_mav.models.persistence import PersistencePredictor

    n = field.n_times
    half = n // 2
    land = field.land_mask
    if blend == "lawnmower":  # the GP alone on a lawnmower (analysis.counterfactual's baseline)
        opts = LoopOptions(
            planner="lawnmower",
            path_length=moves,
            steps_per_leg=1,
            prior="none",
            gp_kw={"seed": seed, "noise_std": noise},
        )
    else:
        opts = LoopOptions(
            planner="information",
            reward="variance_reduction",
            path_length=moves,
            steps_per_leg=1,
            prior="forecast",
            gp_kw={"seed": seed, "noise_std": noise, "bias": True},
            hyper="every_leg",
            background=0 if isinstance(predictor, PersistencePredictor) else 200,
            prior_blend=blend,
            share=share,
            forgetting=forgetting,
        )
    loop = opts.loop(predictor, field.grid, land=land, seed=seed)
    sampler = FieldSampler(field, noise_std=noise, seed=seed + 7919, steps_per_leg=1, sample_at="spread")
    state = np.array(field.data[half], np.float32)
    state[:, land] = np.nan
    water = np.argwhere(~land)
    centre = np.array(field.grid.shape) / 2.0
    start = tuple(int(x) for x in water[np.argmin(((water - centre) ** 2).sum(axis=1))])
    spans = [(float(field.times[j]), float(field.times[j + 1])) for j in range(half, n - 1)]
    out = _fly_rounds(loop, sampler, field, spans, state, float(field.times[half]), [start])
    return float(np.mean(out[len(out) // 2 :]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fields", nargs="+", help="builtin:NAME or a .nc file (a real series)")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--moves", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.02)
    ap.add_argument("--share", type=float, default=0.0, help="the blend's fixed share (PasstLoop share)")
    ap.add_argument(
        "--forgetting", type=float, default=0.8, help="the blend's forgetting factor (PasstLoop forgetting)"
    )
    ap.add_argument(
        "--rows", default=",".join(ROWS), help="comma-separated subset of the rows (default all): " + ", ".join(ROWS)
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    wanted = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = [r for r in wanted if r not in ROWS]
    if unknown:
        ap.error(f"--rows: unknown {', '.join(map(repr, unknown))}; choose from {', '.join(ROWS)}")
    warnings.filterwarnings("ignore")
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.models.dmd import DMDPredictor
    from passt_mav.models.persistence import PersistencePredictor

    result = {}
    for name in args.fields:
        field = resolve_field(name)
        half = field.n_times // 2
        dmd = DMDPredictor().fit(field, start=0, stop=half)
        pers = PersistencePredictor().fit(field, start=0, stop=half)
        rows = {
            "dmd off": (dmd, "off"),
            "dmd select": (dmd, "select"),
            "dmd bma": (dmd, "bma"),
            "persistence prior": (pers, "off"),
            "persistence select": (pers, "select"),
            "lawnmower + GP": (None, "lawnmower"),
        }
        result[name] = {}
        for label in [r for r in ROWS if r in wanted]:
            pred, blend = rows[label]
            v = [
                fly(
                    field,
                    pred,
                    blend,
                    s,
                    moves=args.moves,
                    noise=args.noise,
                    share=args.share,
                    forgetting=args.forgetting,
                )
                for s in range(args.seeds)
            ]
            result[name][label] = {"mean": float(np.mean(v)), "per_seed": v}
            print(f"{name} {label:18s} {np.mean(v):.4f}  per seed {np.round(v, 4).tolist()}", flush=True)
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
