"""Virtual drifters (passt_mav.models.drifters): separations with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from passt_mav.models.drifters import advect, drifter_separation, seed_cells


def _uniform(u, frames, R=5, C=5):
    f = np.zeros((frames, 2, R, C))
    f[:, 0] = u
    return f


@pytest.mark.parametrize("frames, dt_s", [(2, 86400.0), (5, 21600.0), (25, 3600.0)])
def test_uniform_current_against_still_water_separates_8_64_km_a_day(frames, dt_s):
    # u = 0.1 m/s for one day against u = 0: 0.1 x 86400 s = 8.64 km, whatever the snapshot spacing (cells of
    # 100 km: no drifter reaches the grid's edge)
    d = drifter_separation(_uniform(0.1, frames), _uniform(0.0, frames), dt_s, (100e3, 100e3))
    assert d["sep_km"] == pytest.approx(8.64, rel=0.01)
    assert d["km_per_day"] == pytest.approx(8.64, rel=0.01)
    assert d["horizon_h"] == pytest.approx(24.0) and d["n"] == 25
    assert drifter_separation(_uniform(0.1, frames), _uniform(0.1, frames), dt_s, (100e3, 100e3))["sep_km"] == 0.0


def test_solid_body_rotation_returns_a_drifter_after_one_period():
    # u = -w y, v = w x with a period of one day: a drifter 10 cells east of the centre is back after a day
    # (midpoint steps of <= half a cell: within 0.02 cell of 1 km) and 10 cells west after half a day
    n = 41
    yy, xx = np.meshgrid(np.arange(n) - 20.0, np.arange(n) - 20.0, indexing="ij")
    w, cell = 2 * np.pi / 86400.0, 1000.0
    f = np.stack([np.stack([-w * yy * cell, w * xx * cell])] * 2)
    start = np.array([[20.0, 30.0]])
    assert advect(f, 86400.0, (cell, cell), start) == pytest.approx(start, abs=0.02)
    assert advect(f, 43200.0, (cell, cell), start) == pytest.approx(np.array([[20.0, 10.0]]), abs=0.02)


def test_drifters_stop_at_the_grid_edge_and_on_land():
    # 1 m/s east for a day on 10 km cells: the drifter leaves the grid and stops half a cell beyond the
    # last centre; one on a cell with land all round does not move
    f = _uniform(1.0, 2, R=3, C=3)
    assert advect(f, 86400.0, (10e3, 10e3), np.array([[1.0, 1.0]]))[0] == pytest.approx([1.0, 2.5])
    land = f.copy()
    land[:, :, :, :] = np.nan
    assert advect(land, 86400.0, (10e3, 10e3), np.array([[1.0, 1.0]]))[0] == pytest.approx([1.0, 1.0])


def test_seeds_are_a_regular_subset_of_the_wet_cells():
    wet = np.ones((30, 30), bool)
    wet[:, :10] = False
    s = seed_cells(wet, n=100)
    assert 50 <= len(s) <= 150 and wet[s[:, 0], s[:, 1]].all()
    assert len(np.unique(np.diff(np.unique(s[:, 0])))) == 1  # evenly spaced rows
    assert drifter_separation(np.full((2, 2, 3, 3), np.nan), np.full((2, 2, 3, 3), np.nan), 3600.0, (1e3, 1e3)) is None
