"""The paper's claims on the shipped scenarios with the shipped KNODEs (slow; skip without assets).

Each campaign is the acceptance protocol of issue 12 at 6 trials (trial i uses seed i, so
these runs reproduce the figures in passt_mav/assets/README.md and the closing note exactly):
300 steps from snapshot 0, legs of 10 snapshots, sensor noise 0.02, L = 50 and 100.
A claim that our models do not (yet) make hold is a strict xfail with the measured numbers,
so it fails loudly the day it starts to hold and the mark must go.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from passt_mav.commands.evaluate import run_campaign

pytestmark = pytest.mark.slow

TRIALS = 6


@functools.lru_cache(maxsize=None)
def _campaign(data: str, model: str, L: int) -> dict:
    from passt_mav.fields.datasets import ASSETS, load_dataset
    from passt_mav.models.base import load_predictor

    if data != "ocean" and not (ASSETS / f"{data}.nc").exists():
        pytest.skip(f"shipped {data}.nc is not in passt_mav/assets")
    try:
        predictor = load_predictor(model)
    except Exception as exc:  # noqa: BLE001 - any missing model means skip, with the reason
        pytest.skip(f"{model} not available: {exc}")
    # the engine and GP solver that produced the recorded figures (the lockstep engine gives the
    # same numbers for predictors whose batched and single predictions agree bit for bit; a
    # KNODE's batched convolutions may round differently)
    s = run_campaign(load_dataset(data), predictor, path_lengths=(L,), trials=TRIALS, steps=300, t0=0, steps_per_leg=10, noise=0.02, progress=False, engine="serial", gp_solver="sklearn")
    per = s["per_L"][str(L)]
    print(data, L, json.dumps({k: round(v, 4) for k, v in per["final_rmse"].items()}))
    return per


def _xfail(reason: str):
    return pytest.mark.xfail(strict=True, reason="measured 2026-11-24, retrained KNODEs, 6 trials: " + reason)


@pytest.mark.parametrize("L", [pytest.param(50, marks=_xfail("final-window RMSE PASST 0.394 vs model alone 0.635 (0.62x, not <= 0.5x)")), 100])
def test_cylinder_passt_at_most_half_the_model(L):
    """Paper: on the static cylinder PASST's final-window RMSE is <= 0.5 x the model alone's.
    Measured at L=100: PASST 0.273, model 0.635 (0.43x)."""
    per = _campaign("cylinder", "builtin:cylinder", L)
    assert per["final_rmse"]["passt"] <= 0.5 * per["final_rmse"]["model"]


@pytest.mark.parametrize("L", [pytest.param(50, marks=_xfail("PASST 0.394 vs lawnmower+GP 0.335")), 100])
def test_cylinder_passt_beats_lawnmower(L):
    """Measured at L=100: PASST 0.273 vs lawnmower+GP 0.322."""
    per = _campaign("cylinder", "builtin:cylinder", L)
    assert per["final_rmse"]["passt"] < per["final_rmse"]["lawnmower_gp"]


@pytest.mark.parametrize("L", [pytest.param(50, marks=_xfail("PASST RMSE rises from ~0.15 (steps 100-150) to 0.39 (last 50)")),
                               pytest.param(100, marks=_xfail("PASST RMSE rises from ~0.15 (steps 100-150) to 0.27 (last 50)"))])
def test_cylinder_passt_stays_bounded_while_the_model_drifts(L):
    """Paper: PASST's RMSE stays bounded while the model alone's grows. Measured: the model alone
    grows (0.2 -> 0.6), and PASST grows too, more slowly: the KNODE's phase error accumulates in
    the cells a leg does not sample."""
    per = _campaign("cylinder", "builtin:cylinder", L)
    passt = np.array(per["rmse_mean"]["passt"])
    pure = np.array(per["rmse_mean"]["model"])
    assert pure[-50:].mean() > pure[50:100].mean()
    assert passt[-50:].mean() < 1.5 * passt[100:150].mean()


GENERALISATION = [("oscillating", "builtin:cylinder"), ("ocean", "builtin:ocean")]


@pytest.mark.parametrize("L", [50, 100])
@pytest.mark.parametrize("data,model", GENERALISATION)
def test_generalisation_passt_beats_the_model_alone(data, model, L):
    """Scenarios 2 and 3: the model drifts; sampling keeps the estimate closer. Measured:
    oscillating (static-cylinder model) 0.435 / 0.340 vs 0.598; ocean 0.248 / 0.189 vs 0.339."""
    per = _campaign(data, model, L)
    assert per["final_rmse"]["passt"] < per["final_rmse"]["model"]


@pytest.mark.parametrize("data,model,L", [
    pytest.param("oscillating", "builtin:cylinder", 50, marks=_xfail("PASST 0.435 vs lawnmower+GP 0.329")),
    pytest.param("oscillating", "builtin:cylinder", 100, marks=_xfail("PASST 0.340 vs lawnmower+GP 0.317")),
    ("ocean", "builtin:ocean", 50),
    pytest.param("ocean", "builtin:ocean", 100, marks=_xfail("PASST 0.189 vs lawnmower+GP 0.144")),
])
def test_generalisation_passt_beats_lawnmower(data, model, L):
    """Measured on the ocean at L=50: PASST 0.248 vs lawnmower+GP 0.389."""
    per = _campaign(data, model, L)
    assert per["final_rmse"]["passt"] < per["final_rmse"]["lawnmower_gp"]


@pytest.mark.parametrize("window", ["test", "test/gp"])
def test_knode_beats_persistence_to_lookahead_20_on_both_wakes(window):
    """KNODE < persistence at every lookahead <= 20 on the static and the oscillating wake,
    from true states and from GP reconstructions (snapshots 300-400, never trained on)."""
    from passt_mav.models.evaluate import evaluate_command

    res = evaluate_command(model="builtin:cylinder", data="builtin:cylinder", oscillating="builtin:oscillating", lookaheads=(1, 2, 5, 10, 20), baselines=("persistence",), ic_stride=4, pod_window=(300, 320), gp_ic_stride=8)
    for label in (window, window.replace("test", "oscillating")):
        per = res["lookahead"][label]
        for h, v in per["knode"].items():
            assert v["mse"] < per["persistence"][h]["mse"], (label, h)


@pytest.mark.parametrize("window", [
    pytest.param("oscillating", marks=_xfail("KNODE/DMD MSE h=1 1.19e-3/5.83e-3, h=2 3.62e-3/6.10e-3, h=5 1.01e-2/7.12e-3, h=10 1.56e-2/9.10e-3")),
    pytest.param("oscillating/gp", marks=_xfail("KNODE/DMD MSE h=1 7.92e-3/1.05e-2, h=2 9.92e-3/1.07e-2, h=5 1.46e-2/1.18e-2, h=10 1.69e-2/1.37e-2")),
])
def test_knode_beats_dmd_on_the_oscillating_wake_to_lookahead_10(window):
    """Issue 12: KNODE < DMD (both fitted on the static wake) on the oscillating wake for h <= 10.
    Holds for h <= 2 only (ic stride 2 / GP stride 4 in the note's run)."""
    from passt_mav.models.evaluate import evaluate_command

    res = evaluate_command(model="builtin:cylinder", data="builtin:cylinder", oscillating="builtin:oscillating", lookaheads=(1, 2, 5, 10), baselines=("dmd",), ic_stride=2, pod_window=(300, 320), gp_ic_stride=4)
    per = res["lookahead"][window]
    for h, v in per["knode"].items():
        assert v["mse"] < per["dmd"][h]["mse"], h
