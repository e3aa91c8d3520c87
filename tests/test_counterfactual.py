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
