"""`passt-mav evaluate`: campaign numbers, parallel back-ends agree, CLI, and the paper's claims on the cylinder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from passt_mav.cli import main
from passt_mav.commands.evaluate import METHODS, run_campaign, write_figures
from test_passt import WRONG_VEL, Persistence, ShiftPredictor, make_field

SMALL = dict(path_lengths=(12, 24), trials=2, steps=20, steps_per_leg=10, noise=0.01, progress=False)


@pytest.fixture(scope="module")
def field():
    return make_field(T=40)


@pytest.fixture(scope="module")
def serial(field):
    return run_campaign(field, ShiftPredictor(WRONG_VEL), **SMALL)


def test_campaign_structure_and_ratios(serial, tmp_path):
    assert set(serial["per_L"]) == {"12", "24"}
    for L, per in serial["per_L"].items():
        assert set(per["final_rmse"]) == set(METHODS)
        for m in METHODS:
            assert len(per["rmse_mean"][m]) == 21 and per["rmse_mean"][m][0] == pytest.approx(0.0, abs=1e-6)
        assert per["ratio_to_passt"]["passt"] == pytest.approx(1.0)
        assert per["ratio_to_passt"]["lawnmower_gp"] == pytest.approx(per["final_rmse"]["lawnmower_gp"] / per["final_rmse"]["passt"])
        # a GP alone from <= 25 samples of a 900-cell field is far worse than model + GP
        assert per["ratio_to_passt"]["lawnmower_gp"] > 3
        assert len(per["pod"]["passt"]) == 6 and len(per["starts"]) == 2
    # truth's POD energy fractions are a valid spectrum
    e = np.array(serial["pod_truth"])
    assert np.all(np.diff(e) <= 1e-12) and 0 < e.sum() <= 1 + 1e-9
    files = write_figures(serial, tmp_path)
    assert {f.name for f in files} == {"rmse_vs_time.png", "pod_energy.png", "snapshots_L12.png", "snapshots_L24.png"}
    assert all(f.stat().st_size > 10_000 for f in files)


def _numbers(s):
    return {L: per["rmse_mean"] for L, per in s["per_L"].items()}


def test_joblib_workers_give_same_numbers(field, serial):
    import cloudpickle

    import test_passt

    cloudpickle.register_pickle_by_value(test_passt)  # the stand-in predictor travels by value
    try:
        par = run_campaign(field, ShiftPredictor(WRONG_VEL), workers=2, **dict(SMALL, path_lengths=(12,)))
    finally:
        cloudpickle.unregister_pickle_by_value(test_passt)
    assert _numbers(par)["12"] == _numbers(serial)["12"]


def test_dask_local_cluster_gives_same_numbers(field, serial):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        # by address, as `--scheduler tcp://...` does
        par = run_campaign(field, ShiftPredictor(WRONG_VEL), scheduler=cluster.scheduler_address, **dict(SMALL, path_lengths=(12,)))
    assert _numbers(par)["12"] == _numbers(serial)["12"]


def test_bad_inputs_exit_2(tmp_path, capsys):
    assert main(["evaluate", "--data", "builtin:ocean", "--model", "persistence", "--path-lengths", "a,b", "--out", str(tmp_path)]) == 2
    assert "--path-lengths" in capsys.readouterr().err
    assert main(["evaluate", "--data", str(tmp_path / "nope.nc"), "--model", "persistence", "--out", str(tmp_path)]) == 2


def test_unknown_method_or_planner(field):
    from passt_mav.errors import PlannerError

    with pytest.raises(PlannerError, match="method"):
        run_campaign(field, Persistence(), methods=["passt", "oracle"], **SMALL)
    with pytest.raises(PlannerError, match="planner"):
        run_campaign(field, Persistence(), planner="astar", **SMALL)


def test_cli_end_to_end(tmp_path, capsys):
    pytest.importorskip("passt_mav.models.base", reason="predictors (passt_mav.models) not available yet")
    f = make_field(T=30)
    nc = f.to_netcdf(tmp_path / "synth.nc")
    out = tmp_path / "eval"
    rc = main(["evaluate", "--data", str(nc), "--model", "persistence", "--trials", "2", "--path-lengths", "10,20", "--steps", "20", "--json", "--out", str(out)])
    assert rc == 0
    j = json.loads(capsys.readouterr().out)
    assert j["out"] == str(out) and set(j["per_L"]) == {"10", "20"}
    assert (out / "results.json").exists() and (out / "rmse_vs_time.png").exists()


# -- the paper's claims on the shipped scenarios (slow; skip without assets) ----------


def _cylinder_or_skip(name="cylinder"):
    from passt_mav.fields.datasets import ASSETS, load_dataset

    if not (ASSETS / f"{name}.nc").exists():
        pytest.skip(f"shipped {name}.nc is not in passt_mav/assets yet")
    try:
        from passt_mav.models.base import load_predictor

        model = load_predictor("builtin:cylinder")
    except Exception as exc:  # noqa: BLE001 - any missing model means skip, with the reason
        pytest.skip(f"KNODE builtin:cylinder not available: {exc}")
    return load_dataset(name), model


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "measured 2026-11-23 with the shipped KNODE (200 epochs, not the paper's 1981): final RMSE "
    "PASST 1.12, pure model 1.78, lawnmower+GP 0.33 - the KNODE diverges from GP-reconstructed "
    "states over 300 steps; with DMD as the model PASST 0.011 vs model 0.013 vs lawnmower+GP 0.34. "
    "Strict: remove this mark when a better-trained model makes the paper's claim hold."))
def test_cylinder_passt_bounded_and_beats_baselines():
    """Paper claim: over >= 250 steps PASST's RMSE stays bounded while the pure model's
    grows; final-window RMSE(PASST) <= 0.5 x pure model; PASST beats lawnmower + GP."""
    f, model = _cylinder_or_skip()
    s = run_campaign(f, model, path_lengths=(50,), trials=4, steps=300, t0=0, steps_per_leg=10, noise=0.02, progress=False)
    per = s["per_L"]["50"]
    passt = np.array(per["rmse_mean"]["passt"])
    pure = np.array(per["rmse_mean"]["model"])
    print(json.dumps({k: round(v, 4) for k, v in per["final_rmse"].items()}))
    assert per["final_rmse"]["passt"] <= 0.5 * per["final_rmse"]["model"]
    assert per["final_rmse"]["passt"] < per["final_rmse"]["lawnmower_gp"]
    assert passt[-50:].mean() < 1.5 * passt[100:150].mean()
    assert pure[-50:].mean() > pure[50:100].mean()


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "measured 2026-11-23 with the shipped KNODEs: PASST beats the pure model but not lawnmower+GP "
    "(oscillating: 0.93 vs 0.32; ocean: 0.49 vs 0.14). Strict: remove when the claim holds."))
@pytest.mark.parametrize("data,model", [("oscillating", "builtin:cylinder"), ("ocean", "builtin:ocean")])
def test_generalisation_scenarios(data, model):
    """Paper scenarios 2 and 3: the model drifts (oscillating cylinder with the static
    cylinder's model; ocean); PASST must end below the pure model and beat lawnmower + GP."""
    from passt_mav.fields.datasets import ASSETS, load_dataset

    if data != "ocean" and not (ASSETS / f"{data}.nc").exists():
        pytest.skip(f"shipped {data}.nc is not in passt_mav/assets yet")
    try:
        from passt_mav.models.base import load_predictor

        predictor = load_predictor(model)
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"{model} not available: {exc}")
    f = load_dataset(data)
    s = run_campaign(f, predictor, path_lengths=(100,), trials=3, steps=300, steps_per_leg=10, noise=0.02, progress=False)
    per = s["per_L"]["100"]
    print(data, json.dumps({k: round(v, 4) for k, v in per["final_rmse"].items()}))
    assert per["final_rmse"]["passt"] < per["final_rmse"]["model"]
    assert per["final_rmse"]["passt"] < per["final_rmse"]["lawnmower_gp"]


def test_baseline_prior_forecast_runs_full_loop(field):
    """With --baseline-prior forecast a baseline is PASST with another planner: a perfect
    model and noise-free samples then give the exact truth, unlike the GP-only baseline."""
    from test_passt import TRUE_VEL

    kw = dict(SMALL, path_lengths=(12,), trials=1, noise=0.0, methods=["passt", "lawnmower_gp"])
    loop = run_campaign(field, ShiftPredictor(TRUE_VEL), baseline_prior="forecast", **kw)["per_L"]["12"]
    gp_only = run_campaign(field, ShiftPredictor(TRUE_VEL), baseline_prior="none", **kw)["per_L"]["12"]
    assert loop["final_rmse"]["lawnmower_gp"] < 1e-4 and loop["final_rmse"]["passt"] < 1e-4
    assert gp_only["final_rmse"]["lawnmower_gp"] > 0.05
