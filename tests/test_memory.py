"""The information prior's per-cell memory (passt_mav.loop.memory.CellMemory) against a process with a
known persistence, and its place in the loop."""

from __future__ import annotations

import numpy as np
import pytest

from passt_mav.loop.memory import CellMemory


def _simulate(rho_true: float, seed: int, legs: int = 60, n_cells: int = 200, per_leg: int = 40, sigma2: float = 0.1):
    """A per-cell error with the memory's own model: AR(1) between legs with persistence ``rho_true``
    (stationary variance 1), a Kalman update of the cells sampled (one sample each, noise ``sigma2``).
    Returns the memory after ``legs`` legs and the true error variance fractions it should track."""
    rng = np.random.default_rng(seed)
    mem = CellMemory(n_cells)
    x = rng.standard_normal(n_cells)  # the estimate's error, cell by cell (truth - estimate)
    P = np.ones(n_cells)  # its true variance
    zeros, ones, noise = np.zeros((2, n_cells)), np.ones((2, n_cells)), np.full((2, n_cells), sigma2)
    for _ in range(legs):
        # a boat that keeps to half the region: cells come back within a few legs
        cells = np.sort(rng.choice(n_cells // 2, per_leg, replace=False))
        eps = np.sqrt(sigma2) * rng.standard_normal((per_leg, 2))
        xx = np.stack([x[cells], x[cells]], axis=1)  # u and v share the cell's error here
        innov = xx + eps
        mem.observe(cells, np.ones(per_leg), innov, zeros, ones, noise)
        K = P[cells] / (P[cells] + sigma2)
        x[cells] = x[cells] - K * innov[:, 0]
        P[cells] = P[cells] * sigma2 / (P[cells] + sigma2)
        x = np.sqrt(rho_true) * x + np.sqrt(1 - rho_true) * rng.standard_normal(n_cells)
        P = rho_true * P + (1 - rho_true)
    return mem, P


@pytest.mark.parametrize("rho_true", [0.0, 0.8])
def test_the_fitted_persistence_is_the_process_s(rho_true):
    # over 10 seeds: a process that forgets at once keeps rho at most 0.2 (no memory worth having),
    # one that keeps 80 % of a correction per leg is found within 0.1
    fits = [_simulate(rho_true, seed)[0].rho for seed in range(10)]
    if rho_true == 0.0:
        assert max(fits) <= 0.2, fits
    else:
        assert abs(np.median(fits) - rho_true) <= 0.1 and min(fits) >= 0.6, fits


def test_the_fractions_track_the_true_error_variance():
    # cell by cell over the sampled half, the remembered fraction follows the true variance on every
    # seed; where rho is fitted right (most seeds: rho and kappa trade off on a few) it is the truth
    errs = []
    for seed in range(10):
        mem, P = _simulate(0.8, seed)
        s = mem.fractions()
        assert np.allclose(s[100:], 1.0) and np.allclose(P[100:], 1.0, atol=1e-6)  # never sampled
        assert np.corrcoef(s[:100], P[:100])[0, 1] > 0.95
        errs.append(abs(np.mean(s[:100]) - np.mean(P[:100])))
    assert np.median(errs) < 0.02 and max(errs) < 0.3, errs


def test_without_revisits_there_is_no_memory():
    # every leg samples fresh cells: no innovation can tell one rho from another; the tie keeps 0
    mem = CellMemory(100)
    rng = np.random.default_rng(0)
    z, o = np.zeros((2, 100)), np.ones((2, 100))
    for k in range(5):
        cells = np.arange(20 * k, 20 * k + 20)
        mem.observe(cells, np.ones(20), rng.standard_normal((20, 2)), z, o, 0.1 * o)
    assert mem.rho == 0.0 and np.allclose(mem.fractions(), 1.0)


def test_the_loop_plans_on_the_remembered_prior():
    """PasstLoop(memory="fitted"): the information model's local part of a cell (kernel columns and
    diagonal) is the stationary prior's times the memory's fraction; the modes are whole; a bad name
    is refused."""
    import geo
    from passt_mav.errors import PlannerError
    from passt_mav.loop.passt import PasstLoop

    R, C = 5, 6
    N = R * C
    grid = geo.MetricRegionGrid(0, 100.0 * (C - 1), 0, 100.0 * (R - 1), R, C, anchor_lat=40.0, anchor_lon=-70.0)
    kw = dict(planner="information", reward="variance_reduction")
    loop = PasstLoop(None, grid, memory="fitted", gp_kw=dict(noise_std=0.05, solver="cholesky", space_time=False), **kw)
    gp = loop.gp
    gp.background = np.random.default_rng(3).normal(0, 0.2, (3, 2, R, C))
    gp.background_scale = 0.7
    gp.kernels_ = [gp.start_kernel()[0].set_params(k1__k1__constant_value=0.04 + 0.01 * k) for k in range(2)]
    gp.cell_m_, gp.n_inputs_ = 100.0, 2
    F0, d0, _, m = gp.prior_factors(loop.land, with_mode_count=True)
    assert m == 3
    loop.memory.s[:, 9] = 0.25
    info = loop.information_model(np.zeros((2, R, C), np.float32))
    assert np.array_equal(info.F[:, :m], F0[:, :m])  # the modes: the whole field's, not remembered
    rows = [9, N + 9]
    assert np.allclose(info.F[rows, m:], 0.5 * F0[rows, m:]) and np.allclose(info.d[rows], 0.25 * d0[rows])
    rest = np.setdiff1d(np.arange(2 * N), rows)
    assert np.allclose(info.F[rest], F0[rest]) and np.allclose(info.d[rest], d0[rest])
    with pytest.raises(PlannerError, match="unknown planner memory"):
        PasstLoop(None, grid, memory="yes", **kw)
