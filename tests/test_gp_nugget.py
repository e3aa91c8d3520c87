"""The GP's state nugget: white variance above the sensor's is the field's grid-scale error, which a
sample corrects in its own cell (GPReconstructor ``nugget="state"``).

Known answers: the posterior against the dense GP written out by hand (cell-sharing covariance, sensor
noise independent between samples) to 1e-8; cells no sample is in read the same under both readings;
the likelihood gate keeps no nugget for samples that are sensor noise alone and keeps one for white
grid-scale error four times the sensor's variance; the planner's prior puts the nugget on the state.
"""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

import geo
from passt_mav.reconstruction import GPReconstructor

R = C = 12
CELL = 1000.0  # metres
S2 = 0.02**2  # sensor noise variance, (m/s)^2
NUG = 3 * S2  # grid-scale error variance of the forecast, (m/s)^2


@pytest.fixture(scope="module")
def grid():
    return geo.MetricRegionGrid(0, CELL * (C - 1), 0, CELL * (R - 1), R, C, anchor_lat=40.0, anchor_lon=-70.0)


def _gp(grid, nugget: str) -> GPReconstructor:
    """A GP with known kernels (signal 0.05 m/s, length 3 cells, white = sensor + nugget) held fixed."""
    X, Y = grid.centres_xy()
    gp = GPReconstructor(grid_xy=(X, Y), noise_std=0.02, solver="cholesky", nugget=nugget, space_time=False)
    k = ConstantKernel(0.05**2) * Matern(3 * CELL, nu=2.5) + WhiteKernel(S2 + NUG)
    gp.kernels_, gp.cell_m_, gp.n_inputs_ = [k, k], CELL, 2
    gp.nugget_var_ = [NUG, NUG]
    return gp


def _samples(grid, rng):
    cells = np.array([(2, 2), (2, 3), (5, 7), (5, 7), (9, 1), (10, 10)])  # (5, 7) sampled twice
    x, y = grid.cell_to_xy(cells[:, 0], cells[:, 1])
    res = rng.normal(0, 0.05, (len(cells), 2))
    return cells, np.column_stack([x, y]), res


def test_the_posterior_is_the_dense_gp_with_a_shared_cell_error(grid):
    rng = np.random.default_rng(3)
    cells, xy, res = _samples(grid, rng)
    gp = _gp(grid, "state")
    fc = np.zeros((2, R, C))
    mean, std = gp.reconstruct(xy, res, forecast=fc, forecast_at_samples=np.zeros_like(res))
    X, Y = grid.centres_xy()
    G = np.column_stack([X.ravel(), Y.ravel()])
    flat = cells[:, 0] * C + cells[:, 1]
    k1 = gp.kernels_[0].k1
    same = (flat[:, None] == flat[None, :]).astype(float)
    K = k1(xy) + NUG * same + (S2 + gp.alpha) * np.eye(len(xy))  # alpha: the solver's jitter
    Ks = k1(G, xy) + NUG * (np.arange(R * C)[:, None] == flat[None, :])
    for k in range(2):
        want = Ks @ np.linalg.solve(K, res[:, k])
        np.testing.assert_allclose(mean[k].ravel(), want, rtol=0, atol=1e-8)  # float32 output
        var = k1.diag(G) + NUG + S2 - np.einsum("ij,ji->i", Ks, np.linalg.solve(K, Ks.T))
        np.testing.assert_allclose(std[k].astype(np.float64).ravel() ** 2, var, rtol=1e-6, atol=1e-9)


def test_a_sample_corrects_its_own_cell_and_leaves_the_others_as_before(grid):
    rng = np.random.default_rng(4)
    cells, xy, res = _samples(grid, rng)
    keep = [0, 1, 2, 4, 5]  # one sample per cell: the two readings share the samples' covariance
    cells, xy, res = cells[keep], xy[keep], res[keep]
    fc = np.zeros((2, R, C))
    kw = {"forecast": fc, "forecast_at_samples": np.zeros_like(res)}
    m_state, _ = _gp(grid, "state").reconstruct(xy, res, **kw)
    m_noise, _ = _gp(grid, "noise").reconstruct(xy, res, **kw)
    sampled = np.zeros((R, C), bool)
    sampled[cells[:, 0], cells[:, 1]] = True
    np.testing.assert_allclose(m_state[:, ~sampled], m_noise[:, ~sampled], atol=1e-6)
    # at a sampled cell the state reading moves further toward the sample
    at = res.T
    got_s = m_state[:, cells[:, 0], cells[:, 1]]
    got_n = m_noise[:, cells[:, 0], cells[:, 1]]
    assert np.all(np.abs(at - got_s) < np.abs(at - got_n))


def _fit(grid, white_var: float, seed: int) -> GPReconstructor:
    """Fit on 60 samples whose residual is a smooth signal plus white error of variance
    ``white_var`` (on top of which the sensor adds nothing more here: the white part IS the residual)."""
    rng = np.random.default_rng(seed)
    X, Y = grid.centres_xy()
    gp = GPReconstructor(grid_xy=(X, Y), noise_std=0.02, solver="cholesky", space_time=False)
    cells = np.argwhere(np.ones((R, C), bool))[rng.choice(R * C, 60, replace=False)]
    x, y = grid.cell_to_xy(cells[:, 0], cells[:, 1])
    smooth = np.stack([0.08 * np.sin(x / 4e3), 0.08 * np.cos(y / 5e3)], 1)
    res = smooth + rng.normal(0, np.sqrt(white_var), (60, 2))
    return gp.fit(np.column_stack([x, y]), res, np.zeros_like(res))


def test_the_likelihood_gate_keeps_no_nugget_for_sensor_noise_and_keeps_a_real_one(grid):
    kept_noise = [max(_fit(grid, S2, s).nugget_var_) for s in range(10)]
    assert sum(v > 0 for v in kept_noise) <= 2, kept_noise
    kept_real = [min(_fit(grid, 4 * S2, s).nugget_var_) for s in range(10)]
    assert sum(v > 0 for v in kept_real) >= 8, kept_real
    assert np.median(kept_real) == pytest.approx(3 * S2, rel=0.6)


def test_the_planners_prior_holds_the_nugget_on_the_state(grid):
    F_s, d_s, n_s = _gp(grid, "state").prior_factors()
    F_n, d_n, n_n = _gp(grid, "noise").prior_factors()
    np.testing.assert_allclose(F_s, F_n)
    np.testing.assert_allclose(d_s - d_n, NUG)
    np.testing.assert_allclose(n_n - n_s, NUG)
    np.testing.assert_allclose(n_s, S2 + 1e-8)


def test_an_unknown_nugget_reading_is_refused(grid):
    from passt_mav.errors import ReconstructionError

    X, Y = grid.centres_xy()
    with pytest.raises(ReconstructionError, match="unknown GP nugget"):
        GPReconstructor(grid_xy=(X, Y), nugget="both").fit(
            np.zeros((3, 2)) + [[0, 0], [1e3, 0], [0, 1e3]], np.zeros((3, 2)), np.zeros((3, 2))
        )
