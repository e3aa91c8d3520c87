"""Legs timed in the current (passt_mav.planning.transit) and the planners' move masks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from passt_mav.errors import PlannerError
from passt_mav.planning import PLANNERS, make_planner
from passt_mav.planning.grid import MOVES8, allowed_moves, check_path
from passt_mav.planning.transit import FEASIBLE_MARGIN, feasible_moves, ground_speed, leg_timing, move_feasibility

DY, DX = 1000.0, 2000.0  # metres between row centres / column centres


def uniform(u: float, v: float, R: int = 6, C: int = 6) -> np.ndarray:
    out = np.empty((2, R, C), np.float32)
    out[0], out[1] = u, v
    return out


def test_ground_speed_closed_form():
    g, ok = ground_speed([0.5, -0.5, 0.0], [0.0, 0.0, 1.2], 2.0)
    np.testing.assert_allclose(g, [2.5, 1.5, 1.6], rtol=1e-12)
    assert ok.all()
    g, ok = ground_speed(-1.67, 0.0, 2.0)  # against a Gulf-Stream-like jet: 0.33 m/s < 0.25 x 2
    assert g == pytest.approx(0.33) and not ok
    g, ok = ground_speed(0.0, 2.1, 2.0)  # the cross current beats the boat
    assert np.isnan(g) and not ok
    assert FEASIBLE_MARGIN == 0.25


def test_ground_speed_held_over_ground_like_ardupilot():
    # Rover holds 2 m/s over ground along the bow, the hull giving up to its top speed through the water
    along, against, across = ([0.5, 0.0], [-0.5, 0.0], [0.0, 1.2])
    g, ok = ground_speed(*np.transpose([along, against, across]), 2.0, hold="ground", max_water_speed=10.0)
    # across: g * cos(crab) = 2 with tan(crab) = 1.2 / g  ->  g^4 = 4 g^2 + 4 * 1.44
    np.testing.assert_allclose(g, [2.0, 2.0, math.sqrt((4.0 + math.sqrt(16.0 + 4 * 4 * 1.44)) / 2.0)], rtol=1e-9)
    assert ok.all()
    # a hull that makes only the commanded 2 m/s through the water: full throttle against the current and
    # across it (the crab formula), throttled back with it
    g, ok = ground_speed(*np.transpose([along, against, across]), 2.0, hold="ground")
    np.testing.assert_allclose(g, [2.0, 1.5, 1.6], rtol=1e-9)
    g, ok = ground_speed([-1.67, 3.0, 0.0], [0.0, 0.0, 2.5], 2.0, hold="ground", max_water_speed=2.4)
    np.testing.assert_allclose(g[:2], [0.73, 3.0], rtol=1e-9)  # a current faster than the boat carries it
    assert np.isnan(g[2]) and ok.tolist() == [True, True, False]
    with pytest.raises(ValueError, match="top speed"):
        ground_speed(0.0, 0.0, 2.0, hold="ground", max_water_speed=1.0)


@pytest.mark.parametrize(
    ("cur", "move", "g"),
    [
        ((0.5, 0.0), (0, 1), 2.5),  # along an eastward move
        ((-0.5, 0.0), (0, 1), 1.5),  # against it
        ((0.0, 1.2), (0, 1), 1.6),  # across it: sqrt(4 - 1.44)
        ((0.0, -0.8), (1, 0), 1.2),  # against a northward move
    ],
)
def test_uniform_current_one_move(cur, move, g):
    path = np.array([(2, 2), (2 + move[0], 2 + move[1])])
    t = leg_timing(path, uniform(*cur), (DY, DX), 2.0)
    length = math.hypot(move[1] * DX, move[0] * DY)
    np.testing.assert_allclose(t.ground_speed, [g], rtol=1e-6)
    np.testing.assert_allclose(t.duration, [length / g], rtol=1e-6)
    np.testing.assert_allclose(t.arrival, [0.0, length / g], rtol=1e-6)
    assert t.all_feasible


def test_diagonal_move_and_arrivals():
    # a diagonal move on square cells in an eastward current of 1 m/s: c_par = c_perp = 1/sqrt(2)
    path = np.array([(0, 0), (1, 1), (1, 2)])
    t = leg_timing(path, uniform(1.0, 0.0), (DX, DX), 2.0, start_s=10.0)
    g_diag = math.sqrt(4.0 - 0.5) + math.sqrt(0.5)
    np.testing.assert_allclose(t.ground_speed, [g_diag, 3.0], rtol=1e-6)
    np.testing.assert_allclose(
        t.arrival, [10.0, 10.0 + DX * math.sqrt(2) / g_diag, 10.0 + DX * math.sqrt(2) / g_diag + DX / 3.0], rtol=1e-6
    )
    assert t.total_s == pytest.approx(t.arrival[-1])


def test_time_varying_current_is_integrated_along_the_leg():
    # still water at the first snapshot, 1 m/s along the track from the second (600 s later) on,
    # linear between: the boat at 2 m/s through the water makes x(t) = 2 t + t**2 / 1200 m until
    # t = 600 s, then 3 m/s. Move 1 (1200 m) ends at t = 600 (sqrt(8) - 2) = 497.06 s; at 600 s the
    # boat is at 1500 m, so move 2 ends at 600 + 900 / 3 = 900 s.
    cur = np.stack([uniform(0.0, 0.0), uniform(1.0, 0.0)])
    path = np.array([(0, 0), (0, 1), (0, 2)])
    exact = [0.0, 600.0 * (math.sqrt(8.0) - 2.0), 900.0]
    t = leg_timing(path, cur, (DY, 1200.0), 2.0, snapshot_s=600.0)
    np.testing.assert_allclose(t.arrival, exact, rtol=3e-3)
    fine = leg_timing(path, cur, (DY, 1200.0), 2.0, snapshot_s=600.0, substeps=32)
    np.testing.assert_allclose(fine.arrival, exact, rtol=2e-4)
    # one current per move, taken at the moment it begins, misses the ramp: 480 s for move 1
    one = leg_timing(path, cur, (DY, 1200.0), 2.0, snapshot_s=600.0, substeps=1)
    assert one.arrival[1] < exact[1] - 10.0
    # begun halfway between the snapshots: 2 t + ((300 + t)**2 - 300**2) / 1200 reaches 825 m at
    # 300 s, the last 375 m at 3 m/s take 125 s: 425 s
    t = leg_timing(path[:2], cur, (DY, 1200.0), 2.0, snapshot_s=600.0, start_s=300.0)
    np.testing.assert_allclose(t.duration, [425.0], rtol=3e-3)


def test_a_current_varying_along_a_move_is_integrated_along_it():
    # along +col: no current at column 0, 1 m/s against the boat at column 1, linear between (the
    # simulator's bilinear field). dx/dt = 2 - x / 1000 from 0 to 1000 m takes 1000 ln 2 = 693.1 s;
    # the two cells' mean (0.5 m/s against) gives 1000 / 1.5 = 666.7 s.
    cur = np.zeros((2, 3, 3))
    cur[0, :, 1] = -1.0
    t = leg_timing(np.array([(1, 0), (1, 1)]), cur, (DY, 1000.0), 2.0)
    assert t.total_s == pytest.approx(1000.0 * math.log(2.0), rel=5e-3)
    one = leg_timing(np.array([(1, 0), (1, 1)]), cur, (DY, 1000.0), 2.0, substeps=1)
    assert one.total_s == pytest.approx(1000.0 / 1.5, rel=1e-9)
    # a move is feasible only where each of its sub-steps is: 1.9 m/s against at column 1 leaves
    # the midpoint's mean (0.95 m/s against) feasible for a 2 m/s boat, the last sub-step (1.66) not
    cur[0, :, 1] = -1.9
    ok, g = move_feasibility(cur, (DY, 1000.0), 2.0)
    east = [tuple(m) for m in MOVES8.tolist()].index((0, 1))
    assert not ok[1, 0, east]
    assert g[0, 1, 0, east] == pytest.approx(2.0 - 1.9 * 0.875, rel=1e-6)
    ok1, _ = move_feasibility(cur, (DY, 1000.0), 2.0, substeps=1)
    assert ok1[1, 0, east]


def test_infeasible_moves_are_refused():
    # a 1.67 m/s westward jet against a 2 m/s boat, square cells: east and the two eastward
    # diagonals are out (0.33 and sqrt(4 - 1.39) - 1.18 = 0.43 m/s < 0.5); the rest are offered
    ok, g = move_feasibility(uniform(-1.67, 0.0), (DX, DX), 2.0)
    east = [k for k, (dr, dc) in enumerate(MOVES8) if dc > 0]
    assert not ok[2, 2, east].any()
    assert ok[2, 2, [k for k in range(8) if k not in east]].all()
    np.testing.assert_allclose(g[0, 2, 2, 0], 0.33, rtol=1e-5)
    # off the grid: never offered
    assert not ok[0, 0, [k for k, (dr, dc) in enumerate(MOVES8) if dr < 0 or dc < 0]].any()
    # a northward current stronger than the boat: the moves across it and against it go, with it stays
    ok, _ = move_feasibility(uniform(0.0, 2.5), (DX, DX), 2.0)
    assert not ok[2, 2, [0, 4, 6]].any() and ok[2, 2, 2]
    t = leg_timing(np.array([(2, 2), (2, 3)]), uniform(-1.67, 0.0), (DX, DX), 2.0)
    assert not t.all_feasible and t.duration[0] == pytest.approx(DX / 0.33, rel=1e-5)


def test_feasible_moves_every_snapshot_and_stuck_cells():
    # a move must be feasible in every snapshot of the leg
    seq = np.stack([uniform(0.0, 0.0), uniform(-1.67, 0.0)])
    m = feasible_moves(seq, (DX, DX), 2.0)
    assert not m[2, 2, 0] and m[2, 2, 4]
    # a cell whose current is unknown around it keeps its traversable moves (the boat must go on)
    cur = uniform(0.0, 0.0)
    cur[:, :3, :3] = np.nan
    m = feasible_moves(cur, (DX, DX), 2.0)
    assert m[0, 0].sum() == 3  # its three in-grid neighbours, none with a finite current on both ends
    trav = np.ones((6, 6), bool)
    trav[2, 3] = False
    m = feasible_moves(uniform(0.0, 0.0), (DX, DX), 2.0, traversable=trav)
    assert not m[2, 2, 0] and not m[2, 3].any() and m[2, 2, 4]


def test_allowed_moves_combines_cells_and_move_mask():
    trav = np.ones((4, 4), bool)
    trav[1, 2] = False
    a = allowed_moves(trav)
    assert not a[1, 1, 0] and a[1, 1, 4] and not a[1, 2].any() and not a[0, 0, 4]
    mask = np.ones((4, 4, 8), bool)
    mask[1, 1, 4] = False
    b = allowed_moves(trav, mask)
    expected = a.copy()
    expected[1, 1, 4] = False
    np.testing.assert_array_equal(b, expected)


@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_every_planner_keeps_to_the_feasible_moves(name):
    # the reward lies east of the start, behind a westward jet the boat cannot stem
    R, C = 8, 10
    q = np.tile(np.linspace(0.0, 1.0, C), (R, 1))
    start = (4, 4)
    moves = feasible_moves(uniform(-1.67, 0.0, R, C), (DX, DX), 2.0)
    kw = {"n_rollouts": 4} if name == "policy_gradient" else {}
    free = make_planner(name, **kw).plan(q, start, 6, seed=1)
    held = make_planner(name, **kw).plan(q, start, 6, seed=1, mask=moves)
    d_free = np.diff(free, axis=0)
    d_held = np.diff(held, axis=0)
    if name != "random":  # (a random walk need not go east unmasked)
        assert (d_free[:, 1] > 0).any()
    assert not (d_held[:, 1] > 0).any()  # no eastward move offered, none taken
    check_path(held, R, C, traversable=moves, budget=6, start=start)
    with pytest.raises(PlannerError, match="move mask"):
        check_path(np.array([start, (4, 5)]), R, C, traversable=moves)


def test_planner_start_with_no_allowed_move():
    q = np.ones((4, 4))
    q[2, 3] = np.nan  # land east of the start, the one move the mask allows from it
    mask = np.zeros((4, 4, 8), bool)
    mask[2, 2, 0] = True
    with pytest.raises(PlannerError, match="may move to"):
        make_planner("greedy").plan(q, (2, 2), 3, mask=mask)


# -- the loop: moves offered, sample times, leg span ----------------------------------------------------
def _uniform_field(u: float, v: float, R: int = 8, C: int = 10, T: int = 4, dt: float = 600.0):
    import geo
    from passt_mav.fields.field import FlowField

    grid = geo.MetricRegionGrid(0, 100.0 * (C - 1), 0, 100.0 * (R - 1), R, C, anchor_lat=40.0, anchor_lon=-70.0)
    data = np.repeat(uniform(u, v, R, C)[None], T, axis=0)
    return FlowField(data, grid, dt * np.arange(T))


def test_steps_for_duration():
    from passt_mav.loop.passt import steps_for_duration, steps_for_leg

    assert steps_for_duration(5400.0, 3600.0) == 2 and steps_for_duration(10.0, 3600.0) == 1
    assert steps_for_duration(np.inf, 3600.0) == 10**6
    assert steps_for_leg(50, 6800.0, 1.5, 3600.0) == 63  # the still-water rule is unchanged


def test_loop_offers_only_the_moves_the_boat_can_make():
    from passt_mav.loop.passt import PasstLoop

    field = _uniform_field(-1.67, 0.0)
    state = field.data[0]
    kw = dict(planner="greedy", reward="speed", path_length=5, prior="none", background=0, guard="off")

    class EastIsBest:  # a model whose one-step forecast pays most in the east
        def predict(self, s, steps):
            out = np.repeat(np.asarray(s)[None], steps, axis=0).copy()
            out[:, 1] = np.linspace(0.0, 1.0, s.shape[-1])[None, None, :]  # v grows east: speed reward too
            out[:, 0] = -1.67
            return out

    free = PasstLoop(EastIsBest(), field.grid, **kw).plan_leg(state, (4, 2), 0.0, 600.0, steps=1)
    held = PasstLoop(EastIsBest(), field.grid, vehicle_speed=2.0, **kw).plan_leg(state, (4, 2), 0.0, 600.0, steps=1)
    assert (np.diff(free.path, axis=0)[:, 1] > 0).any()
    # against the jet (1.67 m/s westward, a little less after the forecast's v): no eastward move is offered
    assert not (np.diff(held.path, axis=0)[:, 1] > 0).any()
    with pytest.raises(PlannerError):
        PasstLoop(None, field.grid, vehicle_speed=0.0, **kw)


def test_field_sampler_reads_each_cell_when_the_boat_gets_there():
    from passt_mav.loop.passt import FieldSampler

    field = _uniform_field(0.5, 0.0)  # 0.5 m/s along an eastward path: 2.5 m/s over ground
    dx = field.grid.cell_size_m[1]
    path = np.array([(3, 1), (3, 2), (3, 3), (2, 3)])
    s = FieldSampler(field, speed=2.0, sample_at="spread").sample_path(path, 100.0)
    g_n = math.sqrt(4.0 - 0.25)  # the southward move crabs across the 0.5 m/s current
    dy = field.grid.cell_size_m[0]
    np.testing.assert_allclose(s.t, 100.0 + np.array([0.0, dx / 2.5, 2 * dx / 2.5, 2 * dx / 2.5 + dy / g_n]), rtol=1e-9)
    # still water timing without the current (the old rule, constant speed over the leg)
    s0 = FieldSampler(field, speed=2.0, sample_at="spread", current_aware=False).sample_path(path, 100.0)
    np.testing.assert_allclose(s0.t, 100.0 + np.arange(4) / 3 * 3 * field.grid.mean_cell_size_m / 2.0, rtol=1e-9)


def test_corners_to_path_expands_a_missions_waypoint_cells():
    from passt_mav.planning.transit import corners_to_path

    path = np.array([(15, 15), (14, 14), (13, 13), (12, 12), (11, 11), (10, 12), (9, 13), (9, 14)])
    np.testing.assert_array_equal(corners_to_path([(15, 15), (11, 11), (9, 13), (9, 14)]), path)
    with pytest.raises(ValueError, match="straight run"):
        corners_to_path([(0, 0), (1, 3)])


# -- the vehicle's step: the leg's span and the controller's expectation ---------------------------------
def _ocean_step(current_aware: bool):
    from passt_mav.fields.datasets import mission_field
    from passt_mav.loop.legstep import LegStep, build_loop, build_predictor
    from passt_mav.mission.config import load_mission

    cfg = load_mission(str(Path(__file__).resolve().parent.parent / "missions" / "north_atlantic.yaml"))
    planner = cfg.planner.model_copy(
        update={"name": "greedy", "reward": "speed", "path_length": 6, "current_aware": current_aware}
    )
    cfg = cfg.model_copy(update={"planner": planner, "gp": cfg.gp.model_copy(update={"background": 0})})
    field = mission_field(cfg, None)
    pred, _ = build_predictor("persistence", field, echo=lambda s: None)
    return LegStep(cfg, field, build_loop(cfg, pred, field.grid, land=field.land_mask)), field


def test_a_current_aware_leg_spans_its_time_in_the_current():
    from passt_mav.loop.legstep import leg_steps
    from passt_mav.loop.passt import steps_for_duration

    step, field = _ocean_step(True)
    state, t0 = step.initial_state()
    planned = step.plan(0, state, t0, (15, 15), k=0)
    tm = planned.timing
    # every move offered in the forecast current (2 m/s over ground up to 2 m/s through the water)
    assert tm.all_feasible and np.all(tm.ground_speed >= FEASIBLE_MARGIN * 2.0)
    assert planned.steps == steps_for_duration(tm.total_s, field.dt) >= 1
    # the controller's expectation: the same path timed in the forecast (no approach, no lag here)
    still = 1.0e9
    assert step.expected_vehicle_s(0, None, 2.0, still) == pytest.approx(tm.total_s, rel=1e-9)
    assert planned.planned_duration_vehicle_s == pytest.approx(tm.total_s, abs=1e-3)
    assert planned.record(field.dt)["planned_arrival_vehicle_s"][-1] == pytest.approx(tm.total_s, abs=0.1)
    assert step.expected_vehicle_s(99, None, 2.0, still) == still  # a leg it did not plan: the caller's figure
    # still water: the old rule, and the caller's figure
    step0, _ = _ocean_step(False)
    p0 = step0.plan(0, state, t0, (15, 15), k=0)
    assert p0.timing is None and p0.steps == leg_steps(step0.config, field.grid, 2.0, field.dt, 1.0)
    assert step0.expected_vehicle_s(0, None, 2.0, 1234.0) == 1234.0 and p0.planned_duration_vehicle_s == 1234.0
