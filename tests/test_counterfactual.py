"""The lawnmower counterfactual of a live run (passt_mav.analysis.counterfactual)."""

from __future__ import annotations

import numpy as np

import geo
from passt_mav.analysis.counterfactual import lawnmower_counterfactual
from passt_mav.fields.field import FlowField


def _field(kind: str) -> FlowField:
    R = C = 12
    T = 30
    grid = geo.RegionGrid(40.0, -63.0, 40.11, -62.85, R, C)
    rr, cc = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
    t = np.arange(T)[:, None, None]
    if kind == "uniform":
        u = np.full((T, R, C), 0.3)
        v = np.full((T, R, C), -0.1)
    else:  # a pattern moving east, one cell per snapshot
        u = 0.3 + 0.2 * np.sin(2 * np.pi * (cc - t) / 12.0)
        v = 0.1 * np.cos(2 * np.pi * rr / 12.0) + 0 * t
    data = np.stack([u, v], axis=1).astype(np.float32)
    return FlowField(data, grid, np.arange(T) * 600.0, "2024-01-01T00:00:00Z")


def _legs(f, n=3, span=5):
    return [{"t_start": float(f.times[k * span]), "t_end": float(f.times[(k + 1) * span])} for k in range(n)]


def test_uniform_field_is_recovered_exactly():
    """Noise-free samples of a uniform current: the GP reconstructs it to < 1e-3 m/s after every leg."""
    f = _field("uniform")
    out = lawnmower_counterfactual(f, _legs(f), path_length=20, start_cell=(0, 0), noise_std=0.0)
    assert len(out) == 3 and all(r is not None and r < 1e-3 for r in out), out


def test_moving_pattern_errors_and_missing_times():
    """A moving pattern: finite positive errors below the field's own spread; a leg without times,
    or outside the field's time span, gives None; same seed, same numbers."""
    f = _field("moving")
    legs = _legs(f) + [{"t_start": None, "t_end": None}, {"t_start": 1e9, "t_end": 1e9 + 600}]
    out = lawnmower_counterfactual(f, legs, path_length=20, start_cell=(6, 6), noise_std=0.02, seed=1)
    spread = float(np.std(f.data))
    assert all(0 < r < spread for r in out[:3]) and out[3:] == [None, None], out
    assert out == lawnmower_counterfactual(f, legs, path_length=20, start_cell=(6, 6), noise_std=0.02, seed=1)


def test_fleet_rounds_from_staggered_legs():
    """A fleet's asynchronous legs as synchronous intervals: interval j from the earliest start to
    the latest end of the boats' j-th legs, never starting before interval j-1 ended; an interval
    no boat has times for is (None, None)."""
    from passt_mav.analysis.counterfactual import fleet_rounds

    legs = [
        {"boat": 0, "t_start": 0.0, "t_end": 3600.0},
        {"boat": 1, "t_start": 600.0, "t_end": 4200.0},
        {"boat": 0, "t_start": 3700.0, "t_end": 7300.0},  # starts before boat 1's first leg ends
        {"boat": 1, "t_start": 4300.0, "t_end": 7900.0},
        {"boat": 0, "t_start": None, "t_end": None},
    ]
    assert fleet_rounds(legs) == [(0.0, 4200.0), (4200.0, 7900.0), (None, None)]
    one = [{"t_start": 0.0, "t_end": 10.0}, {"t_start": 12.0, "t_end": 20.0}]  # no boat key: one boat
    assert fleet_rounds(one) == [(0.0, 10.0), (12.0, 20.0)]


def _ocean_mission(boats: int):
    from pathlib import Path

    import yaml

    from passt_mav.mission.config import validate_mission

    data = yaml.safe_load((Path(__file__).resolve().parents[1] / "missions" / "north_atlantic.yaml").read_text())
    data.update(model="persistence", legs=3)
    data["planner"] = {"name": "information", "path_length": 6, "reward": "variance_reduction"}
    if boats > 1:
        veh = data.pop("vehicle")
        data["vehicles"] = [{**veh, "connect": f"tcp:127.0.0.1:{5760 + 10 * i}"} for i in range(boats)]
    return validate_mission(data, source="counterfactual test")


def test_same_loop_fleet_counterfactual():
    """The fleet's same-loop random walk: with one boat it is the one-boat counterfactual to the bit;
    with three boats (synchronous legs, keep-out rule) it returns one finite RMSE per interval,
    below the persistence model alone at the last one (samples from three boats correct it), and the
    same numbers for the same seeds."""
    from passt_mav.analysis.counterfactual import same_loop_counterfactual
    from passt_mav.fields.datasets import load_dataset
    from passt_mav.loop.measurement import rmse, truth_at
    from passt_mav.models.persistence import PersistencePredictor

    field = load_dataset("ocean")
    pred = PersistencePredictor().fit(field)
    legs = [{"t_start": 3600.0 * 6 * k, "t_end": 3600.0 * 6 * (k + 1)} for k in range(3)]
    cfg1 = _ocean_mission(1)
    one = same_loop_counterfactual(cfg1, field, pred, legs, start_cell=(15, 15))
    assert same_loop_counterfactual(cfg1, field, pred, legs, start_cells=[(15, 15)]) == one
    cfg3 = _ocean_mission(3)
    fleet_legs = [{**leg, "boat": b} for leg in legs for b in range(3)]
    three = same_loop_counterfactual(cfg3, field, pred, fleet_legs, start_cells=[(15, 15), (15, 5), (15, 25)])
    assert len(three) == 3 and all(r is not None and np.isfinite(r) for r in three), three
    model_alone = rmse(np.asarray(field.data[0]), truth_at(field, legs[-1]["t_end"]))
    assert three[-1] < model_alone, (three, model_alone)
    assert three == same_loop_counterfactual(cfg3, field, pred, fleet_legs, start_cells=[(15, 15), (15, 5), (15, 25)])
