"""PASST with a fleet, offline (passt_mav.loop.engine.run_offline_fleet, ``passt-mav evaluate --boats``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from passt_mav.fields.datasets import resolve_field
from passt_mav.loop.campaign import fleet_comparison
from passt_mav.loop.engine import run_offline, run_offline_fleet, same_step_clashes
from passt_mav.loop.presets import PAPER
from passt_mav.models import make_predictor


@pytest.fixture(scope="module")
def cylinder():
    field = resolve_field("builtin:cylinder")
    return field, make_predictor("dmd").fit(field, start=200, stop=300)


def test_one_boat_fleet_equals_the_independent_lockstep_engine(cylinder):
    """``run_offline`` is the one-boat fleet; the lockstep engine (written separately, batching trials)
    must give the same estimates and paths (DMD: batched and single predictions agree bit for bit)."""
    from passt_mav.loop.engine import run_offline_lockstep

    field, dmd = cylinder
    kw = dict(t0=300, n_steps=40, path_length=20, steps_per_leg=10, noise_std=0.02, planner="greedy")
    a = run_offline_fleet(field, dmd, start_cells=[(10, 12)], seed=3, **kw)
    (b,) = run_offline_lockstep(field, dmd, start_cells=[(10, 12)], seeds=[3], **kw)
    np.testing.assert_allclose(a.estimate, b.estimate, atol=1e-6, equal_nan=True)
    assert [x["path"] for x in a.legs] == [x["path"] for x in b.legs]
    assert run_offline(field, dmd, start_cell=(10, 12), seed=3, **kw).legs[-1]["path"] == a.legs[-1]["path"]


def test_boats_are_given_disjoint_cells_every_leg_and_runs_repeat(cylinder):
    field, dmd = cylinder
    # the allocation does not depend on the GP's options: the paper's (no blend, no bias, no background) keep the
    # test fast; the default preset's loop passes it too (three times slower)
    kw = dict(
        t0=300, n_steps=60, noise_std=0.02, **PAPER.kwargs(path_length=25, steps_per_leg=10, seed=1, background=0)
    )
    starts = [(5, 5), (15, 20), (25, 8)]
    r = run_offline_fleet(field, dmd, start_cells=starts, **kw)
    assert len(r.legs) == 6
    for leg in r.legs:
        paths = [[tuple(c) for c in p] for p in leg["paths"]]
        assert len(paths) == 3 and all(len(p) == 26 for p in paths)
        for a in range(3):
            for b in range(a + 1, 3):
                # a later boat's moves avoid every cell of an earlier boat's path; its start (where it is when
                # the leg begins) may lie on an earlier boat's path, which no two boats then hold at one move
                shared = set(paths[a]) & set(paths[b][1:])
                assert not shared, (leg["step"], a, b, shared)
        _no_two_boats_at_one_cell_at_once([leg])
        for p in paths:  # 8-neighbour moves inside the grid
            d = np.abs(np.diff(np.array(p), axis=0))
            assert d.max() <= 1 and np.array(p).min() >= 0 and np.array(p).max() < 30
    r2 = run_offline_fleet(field, dmd, start_cells=starts, **kw)
    np.testing.assert_array_equal(r.estimate, r2.estimate)


@pytest.mark.long(reason="two campaigns of several trials each (three boats, one boat): ~17 s")
def test_three_boats_beat_one_boat_of_the_same_path_length(cylinder):
    """Small version of the claim (3 trials, 60 steps) with persistence as the model, so the estimate
    rests on the samples (DMD is near exact on this wake: every configuration ends at 0.0092): two or
    three boats of 25 moves end below one boat of 25. Measured with the guard (the model alone as the
    background where it fits a leg's samples better): 0.356 (1 boat), 0.340 (2), 0.348 (3), 0.338
    (1 boat x 75); without it 0.415, 0.399, 0.348, 0.352, when three boats also beat two. The
    shipped-KNODE, 10-trial figure is in the slow test below."""
    field, _ = cylinder
    pers = make_predictor("persistence").fit(field)
    res = fleet_comparison(field, pers, boats=3, path_length=25, trials=3, steps=60, t0=300, window=20, progress=False)
    f = {k: v["final_rmse"] for k, v in res["runs"].items()}
    assert set(f) == {"1 boat x 25", "2 boats x 25", "3 boats x 25", "1 boat x 75"}
    assert f["3 boats x 25"] < f["1 boat x 25"] and f["2 boats x 25"] < f["1 boat x 25"], f


def test_same_step_clashes_known_answers():
    a = np.array([[0, 0], [0, 1], [0, 2], [0, 3]])
    b = np.array([[1, 0], [0, 1], [1, 2], [0, 2]])  # (0,1) at move 1 as a; (0,2) a move after a left it
    m = same_step_clashes(b, [a], (3, 4))
    assert m.sum() == 1 and m[0, 1]
    c = np.array([[2, 2], [2, 3], [1, 3], [0, 3], [0, 3], [0, 3]])  # longer: waits on a's last cell after a stops
    m = same_step_clashes(c, [a], (3, 4))
    assert m.sum() == 1 and m[0, 3]
    assert not same_step_clashes(a, [], (3, 4)).any()


def _no_two_boats_at_one_cell_at_once(legs):
    for leg in legs:
        paths = [np.array(p) for p in leg["paths"]]
        for b in range(1, len(paths)):
            clash = same_step_clashes(paths[b], paths[:b], (30, 30))
            assert not clash.any(), (leg["step"], b, np.argwhere(clash).tolist())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_boats_packed_together_never_meet_and_repeat(cylinder, seed, monkeypatch):
    """Three boats side by side with long random walks (L = 120 on 30x30) get boxed in by each
    other's paths: the fallback then crosses earlier paths (collecting nothing there), and before
    the repair it put two boats on one cell at the same move (seen here: 4, 1 and 1 times for
    seeds 0-2). After the repair no two boats share a cell at the same move, every path is a
    valid grid path, and a second run gives the same paths and estimate."""
    import geo
    from passt_mav.loop import engine

    field, _ = cylinder
    pers = make_predictor("persistence").fit(field)
    # the paths are the point here: the paper's GP (no prior blend, no bias) without the guard's scoring,
    # which spends most of a run's time on 1,000-point likelihoods that do not touch the paths
    kw = dict(
        start_cells=[(14, 14), (14, 15), (15, 14)],
        t0=300,
        n_steps=30,
        noise_std=0.02,
        **PAPER.kwargs(path_length=120, steps_per_leg=10, seed=seed, planner="random", guard="off"),
    )
    found = []
    real = engine.same_step_clashes
    monkeypatch.setattr(engine, "same_step_clashes", lambda *a: found.append(int(real(*a).any())) or real(*a))
    r = run_offline_fleet(field, pers, **kw)
    monkeypatch.setattr(engine, "same_step_clashes", real)
    assert len(r.legs) == 3 and sum(found) >= 1, found  # the repair had work to do
    _no_two_boats_at_one_cell_at_once(r.legs)
    for leg in r.legs:
        for p in leg["paths"]:
            assert len(p) == 121
            np.testing.assert_array_equal(geo.validate_path(field.grid, p), np.array(p))
    r2 = run_offline_fleet(field, pers, **kw)
    assert [x["paths"] for x in r.legs] == [x["paths"] for x in r2.legs]
    np.testing.assert_array_equal(r.estimate, r2.estimate)


@pytest.mark.parametrize("seed", [4, 5])
def test_policy_gradient_fleet_keeps_apart_and_off_land(seed):
    """The default planner, 3 boats, a strip of land across the grid: over every leg no boat is
    on land, no two boats share a cell at one move, and no cell after a boat's start is given to
    two boats (the sequential allocation)."""
    from passt_mav.fields.field import FlowField

    field = resolve_field("builtin:cylinder")
    data = field.data[300:341].copy()
    data[:, :, 10:20, 12:15] = np.nan  # land
    f = FlowField(data, field.grid, field.times[300:341])
    pers = make_predictor("persistence").fit(f)
    r = run_offline_fleet(
        f,
        pers,
        start_cells=[(5, 5), (25, 25), (5, 25)],
        n_steps=40,
        noise_std=0.02,
        # the default planner; the paper's GP without the guard's scoring (the paths are the point)
        **PAPER.kwargs(path_length=40, steps_per_leg=10, seed=seed, guard="off"),
    )
    assert len(r.legs) == 4
    _no_two_boats_at_one_cell_at_once(r.legs)
    for leg in r.legs:
        paths = [np.array(p) for p in leg["paths"]]
        for p in paths:
            assert not f.land_mask[p[:, 0], p[:, 1]].any()
        for a in range(3):
            for b in range(a + 1, 3):
                assert not set(map(tuple, paths[b][1:])) & set(map(tuple, paths[a])), (leg["step"], a, b)
    assert np.isnan(r.estimate[:, :, 10:20, 12:15]).all() and np.isfinite(r.estimate[:, :, :10]).all()


@pytest.mark.slow(reason="the claim's own campaign, 10 trials x 4 fleets with the shipped KNODE: ~5 min on two cores")
def test_fleet_beats_one_boat_with_the_shipped_model_over_ten_trials(tmp_path):
    """The issue's acceptance: 10 trials, 300 steps, the shipped cylinder KNODE, L = 50. Measured
    (same numbers as ``passt-mav evaluate --data builtin:cylinder --model builtin:cylinder --boats 3
    --trials 10 --path-lengths 50``, 5 min on 2 cores; the cylinder KNODE trained with row shifts):
    final-window RMSE 1 boat 0.0769, 2 boats 0.0654, 3 boats 0.0545 (lower than 1 boat in 10 of 10
    trials), 1 boat x 150 0.0560 (with the earliest shipped model: 0.395, 0.292, 0.200, 0.189)."""
    from passt_mav.models.base import load_predictor

    field = resolve_field("builtin:cylinder")
    res = fleet_comparison(
        field, load_predictor("builtin:cylinder"), boats=3, path_length=50, trials=10, steps=300, progress=False
    )
    f = {k: v["final_rmse"] for k, v in res["runs"].items()}
    (tmp_path / "fleet.json").write_text(json.dumps(f))
    assert f["3 boats x 50"] < f["2 boats x 50"] < f["1 boat x 50"], f
    per = {k: v["final_rmse_trials"] for k, v in res["runs"].items()}
    wins = sum(a < b for a, b in zip(per["3 boats x 50"], per["1 boat x 50"]))
    assert wins >= 9, (wins, per)


def test_two_boats_on_one_start_cell_are_refused(cylinder):
    from passt_mav.errors import PlannerError

    field, dmd = cylinder
    with pytest.raises(PlannerError, match="start cells must differ"):
        run_offline_fleet(field, dmd, start_cells=[(3, 4), (3, 4)], t0=300, n_steps=10, path_length=5)


def test_evaluate_boats_cli_writes_the_comparison_and_figure(tmp_path, capsys):
    """`passt-mav evaluate --boats 2`: fleet.json with 1 and 2 boats of L and 1 boat of 2L, their
    mean RMSE over every step, fleet_rmse.png; --boats 0 is a one-line error (exit 2)."""
    from passt_mav.cli import main

    out = tmp_path / "fleet"
    rc = main(
        [
            "evaluate",
            "--data",
            "builtin:cylinder",
            "--model",
            "persistence",
            "--boats",
            "2",
            "--trials",
            "2",
            "--path-lengths",
            "10",
            "--steps",
            "20",
            "--t0",
            "300",
            "--window",
            "10",
            "--json",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    j = json.loads(capsys.readouterr().out)
    assert set(j["final_rmse"]) == {"1 boat x 10", "2 boats x 10", "1 boat x 20"}
    res = json.loads((out / "fleet.json").read_text())
    assert res["config"]["boats"] == 2 and res["config"]["trials"] == 2
    for run in res["runs"].values():
        assert len(run["rmse_mean"]) == 21 and len(run["final_rmse_trials"]) == 2
        assert run["rmse_mean"][0] == pytest.approx(0.0, abs=1e-6)  # every trial starts from the truth
        assert run["final_rmse"] == pytest.approx(float(np.mean(run["final_rmse_trials"])))
    assert (out / "fleet_rmse.png").stat().st_size > 1000
    assert (
        main(
            [
                "evaluate",
                "--data",
                "builtin:cylinder",
                "--model",
                "persistence",
                "--boats",
                "0",
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "--boats" in err and len(err.splitlines()) == 1


def test_keep_out_is_one_rule_for_live_times_and_offline_moves():
    """:func:`passt_mav.loop.engine.keep_out` on field times (as the live FleetStep gives it: boats of
    different speeds, a tolerance of one move of the slower) and on move counts (offline): a cell
    clashes when another boat is at it within the tolerance, or stands on it after its path ended."""
    from passt_mav.loop.engine import keep_out

    a = np.array([[0, 0], [0, 1], [0, 2]])
    ta = np.array([0.0, 10.0, 20.0])  # a: 10 s a move
    b = np.array([[1, 1], [0, 1], [0, 2], [0, 3]])
    tb = np.array([0.0, 6.0, 12.0, 18.0])  # b: 6 s a move, reaches (0,1) 4 s before a
    m = keep_out(b, tb, [(a, ta, 10.0)], (2, 4))
    assert m[0, 1] and m[0, 2] and m.sum() == 2  # (0,2): 8 s before a gets there
    assert not keep_out(b, tb, [(a, ta, 3.0)], (2, 4))[0, 1]  # 4 s apart: no clash within 3 s
    late = tb + 100.0  # long after a's path ended: a stands on (0,2), nowhere else
    m = keep_out(b, late, [(a, ta, 10.0)], (2, 4))
    assert m.sum() == 1 and m[0, 2]
    assert not keep_out(b, tb, [], (2, 4)).any()
    np.testing.assert_array_equal(
        keep_out(b, np.arange(4), [(a, np.arange(3), 1.0)], (2, 4)), same_step_clashes(b, [a], (2, 4))
    )


def test_loop_options_are_one_set_for_every_offline_shape(cylinder):
    """LoopOptions built once and passed: the same run as the loop's options given as keywords; an
    unknown option is refused by name."""
    from passt_mav.loop.passt import LoopOptions

    field, dmd = cylinder
    opts = LoopOptions(planner="greedy", path_length=20, steps_per_leg=10)
    kw = dict(t0=300, n_steps=20, noise_std=0.02, seed=2)
    a = run_offline(field, dmd, start_cell=(10, 12), options=opts, **kw)
    b = run_offline(field, dmd, start_cell=(10, 12), planner="greedy", path_length=20, steps_per_leg=10, **kw)
    np.testing.assert_array_equal(a.estimate, b.estimate)
    assert opts.loop(dmd, field.grid).path_length == 20 and LoopOptions.of(opts, path_length=5).planner == "greedy"
    with pytest.raises(TypeError, match="path_lenght"):
        run_offline(field, dmd, start_cell=(10, 12), path_lenght=20, **kw)
