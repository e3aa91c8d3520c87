"""The paper's claims on the shipped scenarios with the shipped KNODEs (slow; skip without assets).

Each campaign is the acceptance protocol of issue 12 as `passt-mav paper` runs it, at 6 trials
(trial i uses seed i): 300 steps from snapshot 0, legs of 10 snapshots, sensor noise 0.02,
L = 50 and 100, lockstep engine, GP kernels fitted on what they model (hyper="auto": PASST's
residual GP every leg, with the model's background covariance; the GP-only baselines once).
A claim that our models do not (yet) make hold is marked as a strict xfail with the measured
numbers, so it fails loudly the day it starts to hold and the mark must go (none today).
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from passt_mav.loop.campaign import run_campaign
from passt_mav.reconstruction.background import DEFAULT_BACKGROUND

pytestmark = pytest.mark.slow(
    reason="the paper's protocol at 6 trials per scenario and path length with the shipped KNODEs: tens of minutes"
)

TRIALS = 6


@functools.cache
def _campaign(data: str, model: str, L: int) -> dict:
    from passt_mav.fields.datasets import ASSETS, load_dataset
    from passt_mav.models.base import load_predictor

    if data != "ocean" and not (ASSETS / f"{data}.nc").exists():
        pytest.skip(f"shipped {data}.nc is not in passt_mav/assets")
    try:
        predictor = load_predictor(model)
    except Exception as exc:  # noqa: BLE001 - any missing model means skip, with the reason
        pytest.skip(f"{model} not available: {exc}")
    # the campaign of `passt-mav paper` (lockstep engine, each GP's kernel fitted on what it
    # models: hyper="auto"; PASST's residual GP with the model's background covariance), at TRIALS trials
    s = run_campaign(
        load_dataset(data),
        predictor,
        path_lengths=(L,),
        trials=TRIALS,
        steps=300,
        t0=0,
        steps_per_leg=10,
        noise=0.02,
        progress=False,
        engine="lockstep",
        hyper="auto",
        background=DEFAULT_BACKGROUND,
    )
    per = s["per_L"][str(L)]
    print(data, L, json.dumps({k: round(v, 4) for k, v in per["final_rmse"].items()}))
    return per


@pytest.mark.parametrize("L", [50, 100])
def test_cylinder_passt_at_most_half_the_model(L):
    """Paper: on the static cylinder PASST's final-window RMSE is <= 0.5 x the model alone's.
    Measured (6 trials, cylinder KNODE trained with row shifts): L=50 PASST 0.0807 vs model alone
    0.481 (0.17x), L=100 0.0605 (0.13x); 30 trials (passt-mav paper): 0.0784 / 0.0595. With the
    model before row shifts 0.0365 / 0.0329 vs 0.197; without the background covariance and the
    per-leg refit 0.189 / 0.105 (0.96x / 0.54x)."""
    per = _campaign("cylinder", "builtin:cylinder", L)
    assert per["final_rmse"]["passt"] <= 0.5 * per["final_rmse"]["model"]


@pytest.mark.parametrize("L", [50, 100])
def test_cylinder_passt_beats_lawnmower(L):
    """Measured (6 trials): L=50 PASST 0.0807 vs lawnmower+GP 0.334; L=100 0.0605 vs 0.324."""
    per = _campaign("cylinder", "builtin:cylinder", L)
    assert per["final_rmse"]["passt"] < per["final_rmse"]["lawnmower_gp"]


@pytest.mark.parametrize("L", [50, 100])
def test_cylinder_passt_stays_bounded_while_the_model_drifts(L):
    """Paper: PASST's RMSE stays bounded while the model alone's grows. The model alone grows
    (steps 50-100: 0.196, last 50: 0.481); PASST stays within 1.5x of its steps 100-150 (30
    trials: 1.25x at L=50, 1.14x at L=100; at L=50 it did not before the background covariance)."""
    per = _campaign("cylinder", "builtin:cylinder", L)
    passt = np.array(per["rmse_mean"]["passt"])
    pure = np.array(per["rmse_mean"]["model"])
    assert pure[-50:].mean() > pure[50:100].mean()
    assert passt[-50:].mean() < 1.5 * passt[100:150].mean()


GENERALISATION = [("oscillating", "builtin:cylinder"), ("ocean", "builtin:ocean")]


@pytest.mark.parametrize(
    "data,model,L",
    [
        ("oscillating", "builtin:cylinder", 50),
        ("oscillating", "builtin:cylinder", 100),
        ("ocean", "builtin:ocean", 50),
        ("ocean", "builtin:ocean", 100),
    ],
)
def test_generalisation_passt_beats_the_model_alone(data, model, L):
    """Scenarios 2 and 3: the model drifts; sampling keeps the estimate closer. Measured (6 trials):
    oscillating (static-cylinder model) L=50 / 100 0.144 / 0.121 vs 0.408; ocean 0.0640 / 0.0484
    vs 0.0756 (before the background covariance and the per-leg refit, ocean L=50 was 0.081)."""
    per = _campaign(data, model, L)
    assert per["final_rmse"]["passt"] < per["final_rmse"]["model"]


@pytest.mark.parametrize("L", [50, 100])
@pytest.mark.parametrize("data,model", GENERALISATION)
def test_generalisation_passt_beats_lawnmower(data, model, L):
    """Measured (6 trials): oscillating L=50 PASST 0.144 vs lawnmower+GP 0.329, L=100 0.121 vs 0.317;
    ocean L=50 0.0640 vs 0.389, L=100 0.0484 vs 0.144."""
    per = _campaign(data, model, L)
    assert per["final_rmse"]["passt"] < per["final_rmse"]["lawnmower_gp"]


@pytest.mark.parametrize("window", ["test", "test/gp"])
def test_knode_beats_persistence_to_lookahead_20_on_both_wakes(window):
    """KNODE < persistence at every lookahead <= 20 on the static and the oscillating wake,
    from true states and from GP reconstructions (snapshots 300-400, never trained on)."""
    from passt_mav.models.evaluate import evaluate_command

    res = evaluate_command(
        model="builtin:cylinder",
        data="builtin:cylinder",
        oscillating="builtin:oscillating",
        lookaheads=(1, 2, 5, 10, 20),
        baselines=("persistence",),
        ic_stride=4,
        pod_window=(300, 320),
        gp_ic_stride=8,
    )
    for label in (window, window.replace("test", "oscillating")):
        per = res["lookahead"][label]
        for h, v in per["knode"].items():
            assert v["mse"] < per["persistence"][h]["mse"], (label, h)


@pytest.mark.parametrize("window", ["oscillating", "oscillating/gp"])
def test_knode_beats_dmd_on_the_oscillating_wake_to_lookahead_10(window):
    """Issue 12: KNODE < DMD (both fitted on the static wake) on the oscillating wake for h <= 10,
    from true states and from GP reconstructions. Measured (ic stride 2 / GP stride 4), KNODE/DMD
    MSE: true h=1 7.15e-4/5.83e-3, h=5 5.16e-3/7.12e-3, h=10 8.43e-3/9.10e-3; GP h=1 6.92e-3/1.05e-2,
    h=5 1.04e-2/1.18e-2, h=10 1.22e-2/1.37e-2. The model before row-shift augmentation lost from
    h=5 (h=10 1.34e-2/9.07e-3 and 2.02e-2/1.37e-2)."""
    from passt_mav.models.evaluate import evaluate_command

    res = evaluate_command(
        model="builtin:cylinder",
        data="builtin:cylinder",
        oscillating="builtin:oscillating",
        lookaheads=(1, 2, 5, 10),
        baselines=("dmd",),
        ic_stride=2,
        pod_window=(300, 320),
        gp_ic_stride=4,
    )
    per = res["lookahead"][window]
    for h, v in per["knode"].items():
        assert v["mse"] < per["dmd"][h]["mse"], h
