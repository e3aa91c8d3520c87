"""The floor no planner can pass in the same-loop protocol: a perfect reconstruction at every leg end.

    .venv/bin/python benchmarks/oracle_floor.py --data builtin:ocean --model builtin:ocean

`passt-mav evaluate`'s loop methods estimate the field at every snapshot: the model's forecast
from the last reconstruction between legs, the reconstruction at each leg's end (``steps_per_leg``
snapshots apart). Their final-window RMSE (m/s, the mean of the last ``window`` snapshots' RMSE
over water, against the truth) can fall no lower than with the truth itself as each leg's
reconstruction: then only the model's error over one leg's forecast remains. Printed beside it:
the same with persistence of the truth (the state held a leg), and the model alone from the truth
at ``t0`` (the protocol's "model" row). A method's distance to the floor, not its distance to
zero, is what a better path can still win.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def oracle_floor(field, predictor, *, t0: int = 0, steps: int = 300, steps_per_leg: int = 10, window: int = 50) -> dict:
    """Final-window RMSE (field units) of: the model forecast from the truth at each leg start
    (``oracle``), the truth held over each leg (``persistence_of_truth``), the model alone from
    the truth at ``t0`` (``model_alone``); snapshots ``t0 .. t0 + steps``."""
    from passt_mav.loop.measurement import rmse

    land = field.land_mask
    T = int(min(steps, field.n_times - 1 - t0))
    truth = [np.asarray(field.data[t0 + k], np.float32) for k in range(T + 1)]
    oracle = np.zeros((T + 1, 2) + field.grid.shape, np.float32)
    oracle[0] = truth[0]
    for k in range(0, T, steps_per_leg):
        n = min(steps_per_leg, T - k)
        fc = np.asarray(predictor.predict(np.where(land, np.float32(0), truth[k]), n), np.float32)
        oracle[k + 1 : k + n + 1] = fc[:n]
        oracle[k + n] = truth[k + n]  # the perfect reconstruction at the leg's end
    alone = np.asarray(predictor.predict(np.where(land, np.float32(0), truth[0]), T), np.float32)
    w = max(1, min(window, T))
    last = range(T + 1 - w, T + 1)
    return {
        "oracle": float(np.mean([rmse(oracle[k], truth[k]) for k in last])),
        "persistence_of_truth": float(
            np.mean([rmse(truth[(k // steps_per_leg) * steps_per_leg], truth[k]) for k in last])
        ),
        "model_alone": float(np.mean([rmse(alone[k - 1], truth[k]) for k in last])),
    }


def main() -> None:
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.models.base import load_predictor

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="builtin:ocean")
    ap.add_argument("--model", default="builtin:ocean")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--steps-per-leg", type=int, default=10)
    ap.add_argument("--window", type=int, default=50)
    a = ap.parse_args()
    f = resolve_field(a.data)
    out = oracle_floor(f, load_predictor(a.model), steps=a.steps, steps_per_leg=a.steps_per_leg, window=a.window)
    print(json.dumps({"data": a.data, "model": a.model, **out}))


if __name__ == "__main__":
    main()
