"""The information reward and the path optimiser (issue 27).

Known answers: the variance a set of samples removes, computed in the low-rank form, equals
the dense textbook posterior, and equals what the GP reconstruction itself reports as its
posterior variance; the beam search finds the optimum of small instances found by
enumeration; planners keep out of land, fence and keep-out cells; samples with noise far
above the forecast's error leave the estimate at the forecast.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import geo
from passt_mav.planning import InformationModel, InformationPlanner, check_path, compute_reward
from passt_mav.planning.grid import MOVES8
from passt_mav.planning.information import brute_force_reduction
from passt_mav.reconstruction import GPReconstructor


def _random_model(seed, R=4, C=5, r=6):
    rng = np.random.default_rng(seed)
    N = R * C
    F = rng.normal(size=(2 * N, r))
    d = rng.uniform(0.0, 0.5, 2 * N)
    s = rng.uniform(0.05, 0.3, 2 * N)
    return F, d, s, (R, C)


@pytest.mark.parametrize("seed", range(4))
def test_low_rank_reduction_equals_dense_posterior(seed):
    F, d, s, shape = _random_model(seed)
    N = shape[0] * shape[1]
    m = InformationModel(F, d, s, shape)
    rng = np.random.default_rng(100 + seed)
    cells = rng.choice(N, 7, replace=False)
    rows = np.concatenate([cells, cells + N])
    dense = brute_force_reduction(F, d, s, rows)
    assert m.conditioned(cells).reduction == pytest.approx(dense, rel=1e-10, abs=1e-10)
    # one cell's gain after others = the dense difference
    m3 = m.conditioned(cells[:3])
    c = int(cells[3])
    want = brute_force_reduction(F, d, s, np.r_[cells[:4], cells[:4] + N]) - brute_force_reduction(
        F, d, s, np.r_[cells[:3], cells[:3] + N]
    )
    assert m3.gains()[divmod(c, shape[1])] == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert m3.gains()[divmod(int(cells[0]), shape[1])] == 0.0  # already sampled


def _fitted_gp(grid, background, seed=0):
    X, Y = grid.centres_xy()
    rng = np.random.default_rng(seed)
    cells = np.argwhere(np.ones(grid.shape, bool))[rng.choice(grid.shape[0] * grid.shape[1], 12, replace=False)]
    xy = np.column_stack(grid.cell_to_xy(cells[:, 0], cells[:, 1]))
    uv = rng.normal(0, 0.3, (12, 2))
    gp = GPReconstructor(
        grid_xy=(X, Y), noise_std=0.05, space_time=False, solver="cholesky", background=background, background_scale=0.7
    )
    gp.kernels_ = [gp.start_kernel()[0].set_params(k1__k1__constant_value=0.04 + 0.01 * k) for k in range(2)]
    gp.cell_m_, gp.n_inputs_ = 100.0, 2
    return gp, xy, uv


def test_prior_factors_reduction_equals_the_gp_posterior_variance():
    """The reward's prior IS the reconstruction's: the variance the low-rank model says a set of
    samples removes equals the sum of the GP's own posterior variances (background modes
    x factor, stationary kernels, sensor noise), to 1e-8 relative, with land."""
    R, C = 5, 6
    grid = geo.MetricRegionGrid(0, 100.0 * (C - 1), 0, 100.0 * (R - 1), R, C, anchor_lat=40.0, anchor_lon=-70.0)
    rng = np.random.default_rng(3)
    land = np.zeros((R, C), bool)
    land[0, :2] = True
    modes = rng.normal(0, 0.2, (3, 2, R, C))
    modes[:, :, land] = np.nan
    gp, _, _ = _fitted_gp(grid, modes)
    F, d, noise = gp.prior_factors(land, kernel_rank=R * C, kernel_energy=1.0)  # no truncation
    m = InformationModel(F, d, noise, (R, C))
    water = np.argwhere(~land)
    cells = water[rng.choice(len(water), 8, replace=False)]
    xy = np.column_stack(grid.cell_to_xy(cells[:, 0], cells[:, 1]))
    fc = np.zeros((2, R, C))
    fc[:, land] = np.nan
    gp.std_calibration = "off"  # the GP posterior's own std (the map's widens it: test_calibration.py)
    _, std = gp.reconstruct(xy, rng.normal(0, 0.1, (8, 2)), forecast=fc)
    # the GP's std includes the white (sensor) noise of a new reading at each cell
    post = float(np.nansum(std.astype(np.float64) ** 2)) - float(
        noise[0] * (~land).sum() + noise[R * C] * (~land).sum()
    )
    got = m.remaining - m.conditioned(cells).reduction
    assert got == pytest.approx(post, rel=2e-6)  # the GP's std is float32
    # and against the dense textbook posterior in float64, to 1e-8
    flat = cells[:, 0] * C + cells[:, 1]
    dense = brute_force_reduction(F, d, noise, np.r_[flat, flat + R * C])
    assert m.conditioned(cells).reduction == pytest.approx(dense, rel=1e-8)
    # a truncated kernel keeps the diagonal exact: the prior's total variance is unchanged
    F2, d2, _ = gp.prior_factors(land, kernel_rank=4)
    assert InformationModel(F2, d2, noise, (R, C)).prior_total == pytest.approx(m.prior_total, rel=1e-10)
    assert F2.shape[1] < F.shape[1]


def _enumerate_best(m, start, L, trav):
    R, C = m.shape
    best = -1.0
    for seq in itertools.product(range(8), repeat=L):
        path = [start]
        ok = True
        for a in seq:
            r, c = path[-1][0] + MOVES8[a][0], path[-1][1] + MOVES8[a][1]
            if not (0 <= r < R and 0 <= c < C) or not trav[r, c] or (r, c) in path:
                ok = False
                break
            path.append((r, c))
        if ok:
            best = max(best, m.path_reduction(np.array(path)))
    return best


@pytest.mark.parametrize("seed", range(3))
def test_beam_search_finds_the_enumerated_optimum(seed):
    F, d, s, shape = _random_model(seed, R=4, C=4, r=5)
    m = InformationModel(F, d, s, shape)
    trav = np.ones(shape, bool)
    trav[2, 1] = False  # land
    L = 4
    best = _enumerate_best(m, (0, 0), L, trav)
    path = InformationPlanner(beam_width=4096).plan(np.ones(shape), (0, 0), L, seed=seed, mask=trav, info=m)
    check_path(path, *shape, traversable=trav, budget=L, start=(0, 0))
    assert m.path_reduction(path) == pytest.approx(best, rel=1e-12)
    # the default beam gets within 2 % of it, greedy (beam 1) not better than the beam
    p8 = InformationPlanner().plan(np.ones(shape), (0, 0), L, seed=seed, mask=trav, info=m)
    p1 = InformationPlanner(beam_width=1).plan(np.ones(shape), (0, 0), L, seed=seed, mask=trav, info=m)
    assert m.path_reduction(p8) >= 0.98 * best
    assert m.path_reduction(p8) >= m.path_reduction(p1) - 1e-12


def test_beam_search_on_a_reward_map_collects_the_enumerated_best():
    """Without a model the optimiser maximises the map's sum over distinct cells (any reward)."""
    rng = np.random.default_rng(5)
    q = rng.random((4, 4))
    trav = np.ones((4, 4), bool)
    best = 0.0
    for seq in itertools.product(range(8), repeat=4):
        path, ok = [(1, 1)], True
        for a in seq:
            r, c = path[-1][0] + MOVES8[a][0], path[-1][1] + MOVES8[a][1]
            if not (0 <= r < 4 and 0 <= c < 4) or (r, c) in path:
                ok = False
                break
            path.append((r, c))
        if ok:
            best = max(best, sum(q[p] for p in path[1:]))
    path = InformationPlanner(beam_width=4096).plan(q, (1, 1), 4, mask=trav)
    assert sum(q[tuple(p)] for p in path[1:]) == pytest.approx(best)


def test_planners_keep_out_of_land_fence_and_keep_out_cells():
    F, d, s, _ = _random_model(7, R=12, C=12, r=8)
    m = InformationModel(F, d, s, (12, 12))
    trav = np.ones((12, 12), bool)
    trav[:, 6] = False  # a wall of land with one gap
    trav[9, 6] = True
    trav[3:5, 2:4] = False  # a fenced-off box
    keep_out = np.zeros((12, 12), bool)
    keep_out[9, 7] = True  # another boat's cell
    mask = trav & ~keep_out
    for K in (1, 8):
        path = InformationPlanner(beam_width=K).plan(np.ones((12, 12)), (0, 0), 60, seed=1, mask=mask, info=m)
        check_path(path, 12, 12, traversable=mask, budget=60, start=(0, 0))
        assert not keep_out[path[:, 0], path[:, 1]].any()
    q = compute_reward("variance_reduction", np.zeros((2, 12, 12)), info=m.conditioned([(5, 5)]))
    assert q[5, 5] == 0.0 and q.max() == pytest.approx(1.0)


def _smooth(rng, R, C, scale):
    from scipy.ndimage import gaussian_filter

    a = gaussian_filter(rng.normal(size=(2, R, C)), (0, scale, scale), mode="wrap")
    return a / a.std()


def _estimate_ratios(error: float, seeds, background: bool, bias: bool = False) -> list[float]:
    """Per seed: the reconstruction's RMSE / the forecast's, for forecast = truth + a smooth error
    of RMSE ``error`` and 51 samples with 0.05 m/s noise along a track (30 x 30 cells of 100 m)."""
    R = C = 30
    X, Y = np.meshgrid(np.arange(C) * 100.0, np.arange(R) * 100.0)
    ratios = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        truth = 0.5 * _smooth(rng, R, C, 4)
        fc = truth + error * _smooth(rng, R, C, 5)
        r = np.clip(np.cumsum(rng.integers(-1, 2, 51)) + 15, 0, R - 1)
        c = np.clip(np.arange(51) // 2 + 5, 0, C - 1)
        xy = np.column_stack([X[r, c], Y[r, c]])
        uv = truth[:, r, c].T + rng.normal(0, 0.05, (51, 2))
        modes = np.stack([0.3 * _smooth(rng, R, C, 6) for _ in range(5)]) if background else None
        gp = GPReconstructor(grid_xy=(X, Y), noise_std=0.05, solver="cholesky", background=modes, bias=bias)
        f_at = fc[:, r, c].T
        gp.fit(xy, uv, forecast_at_samples=f_at)
        est, _ = gp.reconstruct(xy, uv, forecast=fc, forecast_at_samples=f_at)
        ratios.append(np.sqrt(np.mean((est - truth) ** 2)) / np.sqrt(np.mean((fc - truth) ** 2)))
    return ratios


@pytest.mark.parametrize("background,bias", [(False, False), (True, False), (False, True), (True, True)])
def test_noisy_samples_leave_a_good_forecast_alone(background, bias):
    """Forecast = truth + a smooth error of RMSE e = 0.005 m/s; 51 samples along a track with
    sensor noise 0.05 m/s (10 e). Over 20 seeds the reconstruction's RMSE stays within 2 % of
    the forecast's (measured: 1.0000; before the GP kept its noise at the sensor's and gated its
    signal by evidence, 1.16 without background modes, 1.60 with them), also with the offset
    and forecast-anomaly modes of ``bias`` (their gates refuse what noise suggests)."""
    assert np.mean(_estimate_ratios(0.005, range(20), background, bias)) <= 1.02


def test_a_real_forecast_error_is_still_corrected():
    """The evidence gate does not switch off a correction the samples do show: forecast error
    0.1 m/s (smooth), sensor noise 0.05 m/s: the estimate's RMSE falls below 0.8 of the
    forecast's on average over 10 seeds (measured 0.74, as before the gate)."""
    assert np.mean(_estimate_ratios(0.1, range(10), False)) < 0.8


def _stale_case(seed: int, kind: str, track: str = "z"):
    """A 30 x 30 field (cells of 100 m) = a uniform current + a smooth pattern; the forecast is
    stale: ``offset`` - the uniform current changed by (0.3, -0.2) m/s since; ``reversed`` - the
    pattern reversed (a tide half a period on) and the uniform part moved by (0.1, 0.05). 51
    samples (noise 0.02 m/s) along a track: ``z`` - a Z over the whole region (top row, diagonal,
    bottom row), ``corner`` - a random walk in one corner (rows and columns 2..12)."""
    R = C = 30
    X, Y = np.meshgrid(np.arange(C) * 100.0, np.arange(R) * 100.0)
    rng = np.random.default_rng(seed)
    pattern = 0.3 * _smooth(rng, R, C, 5)
    base = np.array([0.4, 0.1])[:, None, None]
    if kind == "offset":
        fc, truth = base + pattern, base + np.array([0.3, -0.2])[:, None, None] + pattern
    else:
        fc, truth = base + pattern, base + np.array([0.1, 0.05])[:, None, None] - pattern
    if track == "z":
        s = np.linspace(0, 1, 17)
        r = np.concatenate([np.full(17, 3), 3 + s * 23, np.full(17, 26)]).round().astype(int)
        c = np.concatenate([2 + s * 25, 27 - s * 25, 2 + s * 25]).round().astype(int)
    else:
        r = np.clip(np.cumsum(rng.integers(-1, 2, 51)) + 7, 2, 12)
        c = np.clip(np.cumsum(rng.integers(-1, 2, 51)) + 7, 2, 12)
    xy = np.column_stack([X[r, c], Y[r, c]])
    uv = truth[:, r, c].T + rng.normal(0, 0.02, (51, 2))
    return (X, Y), fc, truth, xy, uv, fc[:, r, c].T


@pytest.mark.parametrize("kind", ["offset", "reversed"])
def test_bias_corrects_a_stale_forecast_far_from_the_samples(kind):
    """With ``bias`` the GP may shift the forecast by a constant and rescale its anomaly where
    samples that see the region show it: a Z track over the region then corrects it all. Measured
    (10 seeds, RMSE over the grid): offset 0.0160 with bias vs 0.0523 without (0.31x); reversed
    pattern 0.0388 vs 0.2158 (0.18x); asserted: below 0.4x, and the fitted variance kept."""
    from passt_mav.reconstruction.lowrank import BIAS_MIN_COVERAGE

    with_b, without = [], []
    for seed in range(10):
        grid, fc, truth, xy, uv, f_at = _stale_case(seed, kind)
        for bias, out in ((True, with_b), (False, without)):
            gp = GPReconstructor(grid_xy=grid, noise_std=0.02, solver="cholesky", bias=bias)
            gp.fit(xy, uv, forecast_at_samples=f_at)
            est, _ = gp.reconstruct(xy, uv, forecast=fc, forecast_at_samples=f_at)
            out.append(float(np.sqrt(np.mean((est - truth) ** 2))))
            if bias:
                assert gp.bias_coverage_ >= BIAS_MIN_COVERAGE
                assert (gp.bias_var_ > 0) if kind == "offset" else (gp.scale_var_ > 0)
    print(kind, "bias", np.mean(with_b), "plain", np.mean(without))
    assert np.mean(with_b) < 0.4 * np.mean(without)


@pytest.mark.parametrize("kind", ["offset", "reversed"])
def test_samples_in_one_corner_fit_no_global_mode(kind):
    """Samples bunched in one corner cannot tell a local error from a global one, and a global mode
    fitted from them carried a corner's error over the region (a random walk through the loop:
    ocean 0.0609 -> 0.1107 m/s). Below :data:`BIAS_MIN_COVERAGE` the ``bias`` modes are not
    fitted: the estimate is the one without them, to the bit."""
    from passt_mav.reconstruction.lowrank import BIAS_MIN_COVERAGE

    for seed in range(5):
        grid, fc, _truth, xy, uv, f_at = _stale_case(seed, kind, track="corner")
        ests = []
        for bias in (True, False):
            gp = GPReconstructor(grid_xy=grid, noise_std=0.02, solver="cholesky", bias=bias)
            gp.fit(xy, uv, forecast_at_samples=f_at)
            ests.append(gp.reconstruct(xy, uv, forecast=fc, forecast_at_samples=f_at)[0])
            if bias:
                assert gp.bias_coverage_ < BIAS_MIN_COVERAGE and gp.bias_var_ == 0 and gp.scale_var_ == 0
        np.testing.assert_array_equal(ests[0], ests[1])
