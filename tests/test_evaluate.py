"""`passt-mav evaluate`: campaign numbers, parallel back-ends agree, CLI (the paper's claims: test_paper_claims.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_passt import WRONG_VEL, Persistence, ShiftPredictor, make_field

from passt_mav.cli import main
from passt_mav.commands.evaluate import write_figures
from passt_mav.loop.campaign import METHODS, run_campaign

SMALL = dict(path_lengths=(12, 24), trials=2, steps=20, steps_per_leg=10, noise=0.01, progress=False)


@pytest.fixture(scope="module")
def field():
    return make_field(T=40)


@pytest.fixture(scope="module")
def serial(field):
    """The original one-trial-at-a-time path; the parallel back-ends run the lockstep engine."""
    return run_campaign(field, ShiftPredictor(WRONG_VEL), engine="serial", keep_trials=True, **SMALL)


def test_campaign_structure_and_ratios(serial, tmp_path):
    assert set(serial["per_L"]) == {"12", "24"}
    for per in serial["per_L"].values():
        assert set(per["final_rmse"]) == set(METHODS)
        for m in METHODS:
            assert len(per["rmse_mean"][m]) == 21 and per["rmse_mean"][m][0] == pytest.approx(0.0, abs=1e-6)
        assert per["ratio_to_passt"]["passt"] == pytest.approx(1.0)
        assert per["ratio_to_passt"]["lawnmower_gp"] == pytest.approx(
            per["final_rmse"]["lawnmower_gp"] / per["final_rmse"]["passt"]
        )
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
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        # by address, as `--scheduler tcp://...` does
        par = run_campaign(
            field, ShiftPredictor(WRONG_VEL), scheduler=cluster.scheduler_address, **dict(SMALL, path_lengths=(12,))
        )
    assert _numbers(par)["12"] == _numbers(serial)["12"]


def _paths(s):
    return {(r["L"], r["trial"]): r["paths"] for r in s["_trials"]}


@pytest.mark.parametrize("batch", [None, 1])
def test_lockstep_engine_equals_serial(field, serial, batch):
    """Batched (lockstep) and serial runs of the same configuration: identical paths, RMSE to 1e-6."""
    from test_passt import BatchShiftPredictor

    lock = run_campaign(
        field, BatchShiftPredictor(WRONG_VEL), engine="lockstep", batch=batch, keep_trials=True, **SMALL
    )
    assert _paths(lock) == _paths(serial) and len(_paths(lock)) == 4
    for L in serial["per_L"]:
        for m in METHODS:
            np.testing.assert_allclose(
                lock["per_L"][L]["rmse_mean"][m], serial["per_L"][L]["rmse_mean"][m], atol=1e-6, rtol=0
            )
    assert lock["trial_legs"] == 4 * 4 * 2 and set(lock["timings_s"]["passt"]) == {"predict", "reward", "plan", "gp"}


def test_gp_fit_points_reach_the_hyper_parameter_fit(field, serial):
    """--gp-fit-points caps the samples a leg's fit sees: at or above a leg's sample count (25 at L = 24)
    the campaign is the default's to the digit; below it the fitted kernels, hence the numbers, differ."""
    kw = dict(SMALL, path_lengths=(24,), methods=["passt"], engine="serial")
    same = run_campaign(field, ShiftPredictor(WRONG_VEL), gp_fit_points=25, **kw)
    fewer = run_campaign(field, ShiftPredictor(WRONG_VEL), gp_fit_points=5, **kw)
    ref = serial["per_L"]["24"]["rmse_mean"]["passt"]
    np.testing.assert_array_equal(same["per_L"]["24"]["rmse_mean"]["passt"], ref)
    # the first leg's estimate is the model's (the samples enter at its end); after it the fit differs
    # (by ~2e-8 on this smooth synthetic field; the same run is equal to the last bit, so any change is the option's)
    assert np.max(np.abs(np.subtract(fewer["per_L"]["24"]["rmse_mean"]["passt"], ref))) > 1e-12
    assert fewer["config"]["gp_kw"]["max_fit_points"] == 5 and "max_fit_points" not in serial["config"]["gp_kw"]


def test_fixed_kernel_campaign_solvers_agree(field):
    """hyper='state' (kernel fitted once on the initial state): sklearn per-leg regressors and the
    direct Cholesky posterior give the same paths and RMSE (1e-6), lockstep vs serial."""
    kw = dict(SMALL, path_lengths=(12,), hyper="state", keep_trials=True)
    a = run_campaign(field, ShiftPredictor(WRONG_VEL), engine="serial", gp_solver="sklearn", **kw)
    b = run_campaign(field, ShiftPredictor(WRONG_VEL), engine="lockstep", gp_solver="cholesky", **kw)
    assert _paths(a) == _paths(b)
    for m in METHODS:
        np.testing.assert_allclose(
            b["per_L"]["12"]["rmse_mean"][m], a["per_L"]["12"]["rmse_mean"][m], atol=1e-6, rtol=0
        )


def test_lockstep_with_a_real_batched_predictor(field):
    """A passt_mav Predictor (DMD) takes the whole batch in one call; lockstep = serial to 1e-6."""
    base = pytest.importorskip("passt_mav.models.base", reason="predictors (passt_mav.models) not available")
    dmd = base.make_predictor("dmd").fit(field)
    kw = dict(SMALL, path_lengths=(12,), hyper="state", methods=["passt", "model"], keep_trials=True)
    a = run_campaign(field, dmd, engine="serial", **kw)
    b = run_campaign(field, dmd, engine="lockstep", **kw)
    assert _paths(a) == _paths(b)
    np.testing.assert_allclose(
        b["per_L"]["12"]["rmse_mean"]["passt"], a["per_L"]["12"]["rmse_mean"]["passt"], atol=1e-6, rtol=0
    )


def test_bad_inputs_exit_2(tmp_path, capsys):
    assert (
        main(
            [
                "evaluate",
                "--data",
                "builtin:ocean",
                "--model",
                "persistence",
                "--path-lengths",
                "a,b",
                "--out",
                str(tmp_path),
            ]
        )
        == 2
    )
    assert "--path-lengths" in capsys.readouterr().err
    assert (
        main(["evaluate", "--data", str(tmp_path / "nope.nc"), "--model", "persistence", "--out", str(tmp_path)]) == 2
    )
    capsys.readouterr()
    for opt in ("--prior-share", "--prior-forgetting"):  # the blend's settings, checked before any work
        argv = [
            "evaluate",
            "--data",
            "builtin:ocean",
            "--model",
            "persistence",
            opt,
            "1.5",
            "--out",
            str(tmp_path / "x"),
        ]
        assert main(argv) == 2, opt
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{opt} must lie in [0, 1], got 1.5" in err[0], err
        assert not (tmp_path / "x").exists()
    argv = ["evaluate", "--data", "builtin:ocean", "--model", "persistence", "--gp-fit-points", "2"]
    assert main([*argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--gp-fit-points must be an integer >= 3, got 2" in err[0], err
    assert not (tmp_path / "x").exists()


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
    rc = main(
        [
            "evaluate",
            "--data",
            str(nc),
            "--model",
            "persistence",
            "--trials",
            "2",
            "--path-lengths",
            "10,20",
            "--steps",
            "20",
            "--json",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    j = json.loads(capsys.readouterr().out)
    assert j["out"] == str(out) and set(j["per_L"]) == {"10", "20"}
    assert (out / "results.json").exists() and (out / "rmse_vs_time.png").exists()


def test_baseline_prior_forecast_runs_full_loop(field):
    """With --baseline-prior forecast a baseline is PASST with another planner: a perfect
    model and noise-free samples then give the exact truth, unlike the GP-only baseline."""
    from test_passt import TRUE_VEL

    kw = dict(SMALL, path_lengths=(12,), trials=1, noise=0.0, methods=["passt", "lawnmower_gp"])
    loop = run_campaign(field, ShiftPredictor(TRUE_VEL), baseline_prior="forecast", **kw)["per_L"]["12"]
    gp_only = run_campaign(field, ShiftPredictor(TRUE_VEL), baseline_prior="none", **kw)["per_L"]["12"]
    assert loop["final_rmse"]["lawnmower_gp"] < 1e-4 and loop["final_rmse"]["passt"] < 1e-4
    assert gp_only["final_rmse"]["lawnmower_gp"] > 0.05


def test_auto_gp_schedule_fits_each_gp_on_what_it_models():
    """hyper="auto": PASST's residual GP (and a baseline run through the model loop) is fitted on
    every leg's residuals, a GP on samples alone once on the initial state; an unknown schedule
    (or background length) is refused."""
    from types import SimpleNamespace

    from passt_mav.errors import PlannerError
    from passt_mav.loop.campaign import _method_kw, run_campaign

    cfg = dict(hyper="auto", planner="policy_gradient", reward="speed", baseline_prior="none")
    assert _method_kw(cfg, "passt", object())[1]["hyper"] == "every_leg"
    assert _method_kw(cfg, "lawnmower_gp", object())[1]["hyper"] == "state"
    assert _method_kw(dict(cfg, baseline_prior="forecast"), "lawnmower_gp", object())[1]["hyper"] == "every_leg"
    assert _method_kw(dict(cfg, hyper="first_leg"), "greedy_gp", object())[1]["hyper"] == "first_leg"
    with pytest.raises(PlannerError, match="hyper-parameter schedule"):
        run_campaign(SimpleNamespace(n_times=10), None, hyper="nightly", methods=("lawnmower_gp",), progress=False)
    with pytest.raises(PlannerError, match="background"):
        run_campaign(SimpleNamespace(n_times=10), None, background=1, methods=("lawnmower_gp",), progress=False)


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_campaign_tasks_reuse_the_heap_under_dask_malloc_settings():
    """Dask starts workers with MALLOC_TRIM_THRESHOLD_=65536, which turns every 1 MiB array into
    a fresh mmap (a page fault per 4 KiB page, every time); inside a campaign task the heap is
    reused (almost no faults), and afterwards the environment's behaviour is back."""
    import os
    import subprocess
    import sys

    code = (
        "import resource, numpy as np\n"
        "from passt_mav.loop.campaign import _heap_reuse\n"
        "def faults():\n"
        "    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "    for _ in range(100):\n"
        "        a = np.ones(1 << 17); del a\n"
        "    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0\n"
        "before = faults()\n"
        "with _heap_reuse():\n"
        "    inside = faults()\n"
        "print(before, inside, faults())\n"
    )
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="65536")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    before, inside, after = map(int, out)
    assert before > 100 * 200  # ~256 faults per 1 MiB array
    assert inside < before / 20
    assert after > 100 * 200


def test_results_carry_calibration_and_the_trivial_maps(field, serial):
    """Per method and leg-end step the estimate's coverage95 and NLPD (each trial's engine record scored by
    passt_mav.models.calibration, averaged here), the trivial maps' RMSE over time, and beats_trivial."""
    from passt_mav.models.calibration import calibration

    per = serial["per_L"]["12"]
    loops = [m for m in METHODS if m != "model"]
    for m in loops:
        assert per["calibration_steps"][m] == [10, 20]  # legs of 10 steps over 20
        assert all(0.0 <= c <= 1.0 for c in per["coverage95_mean"][m])
        assert all(np.isfinite(x) for x in per["nlpd_mean"][m])
    t0 = [r for r in serial["_trials"] if r["L"] == 12]
    assert per["coverage95_mean"]["passt"][0] == pytest.approx(
        np.mean([r["calibration"]["passt"]["coverage95"][0] for r in t0])
    )
    assert "model" not in per["coverage95_mean"]  # the model alone has no std
    base = serial["baselines"]
    truth = field.data[: serial["config"]["steps"] + 1].astype(np.float64)
    zero = np.sqrt(np.nanmean(truth.reshape(len(truth), -1) ** 2, axis=1))
    np.testing.assert_allclose(base["rmse_zero"], zero, rtol=1e-9)
    assert len(base["rmse_forecast_mean"]) == len(zero)
    # model + GP on this field is far better than no current at all
    assert per["beats_trivial"]["passt"] is True
    assert serial["config"]["calibration"] is True
    # the engine's record is the module's figure of that leg's state and std
    from passt_mav.loop.engine import run_trials
    from passt_mav.loop.passt import LoopOptions

    opts = LoopOptions(path_length=12, steps_per_leg=10, prior="forecast")
    (r,) = run_trials(
        field, ShiftPredictor(WRONG_VEL), opts, starts=[[(5, 5)]], seeds=[0], n_steps=10, calibration=True
    )
    cal = r.legs[0]["calibration"]
    assert cal["step"] == 10 and 0 < cal["n"] <= 2 * 30 * 30 and set(cal) >= {"coverage95", "nlpd", "reliability"}
    assert calibration(r.estimate[10], np.ones_like(r.estimate[10]), field.data[10]) is not None
    (r0,) = run_trials(field, ShiftPredictor(WRONG_VEL), opts, starts=[[(5, 5)]], seeds=[0], n_steps=10)
    assert "calibration" not in r0.legs[0]
    np.testing.assert_array_equal(r0.estimate, r.estimate)  # scoring never changes the estimate


def test_results_carry_the_drifter_separation(field, serial):
    """Per path length the virtual drifters' mean separation after the horizon (km, km/day) per method, the
    model alone and persistence (passt_mav.models.drifters; the first true snapshot held fixed)."""
    from passt_mav.models.drifters import drifter_separation

    per = serial["per_L"]["12"]
    assert set(per["drifter_sep_km"]) == set(METHODS) | {"persistence"}
    t0 = [r for r in serial["_trials"] if r["L"] == 12]
    assert per["drifter_sep_km"]["passt"] == pytest.approx(np.mean([r["drifters"]["passt"]["sep_km"] for r in t0]))
    truth = field.data[:21].astype(np.float64)
    dt, cell = float(field.dt), field.grid.cell_size_m
    held = drifter_separation(np.broadcast_to(truth[:1], truth.shape), truth, dt, cell)
    assert per["drifter_sep_km"]["persistence"] == pytest.approx(held["sep_km"])
    assert per["drifter_km_per_day"]["persistence"] == pytest.approx(held["km_per_day"])
    assert per["drifter_horizon_h"] == pytest.approx(20 * dt / 3600.0) and per["drifter_n"] == held["n"]
    assert all(v >= 0 for v in per["drifter_sep_km"].values())
