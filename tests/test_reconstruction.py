"""GP reconstruction: known analytic fields, noise-level accuracy near samples, prior behaviour."""

from __future__ import annotations

import numpy as np
import pytest

import geo
from passt_mav.errors import ReconstructionError
from passt_mav.reconstruction import GPReconstructor

R = C = 30
CELL = 1000.0  # metres
NOISE = 0.02


@pytest.fixture(scope="module")
def grid():
    return geo.MetricRegionGrid(0, CELL * (C - 1), 0, CELL * (R - 1), R, C, anchor_lat=40.0, anchor_lon=-70.0)


def analytic(x, y):
    """A smooth non-divergent field (m/s): u = cos(kx x) sin(ky y) ..., wavelength ~ 20-25 km."""
    kx, ky = 2 * np.pi / 25e3, 2 * np.pi / 20e3
    u = 0.6 * np.cos(kx * x) * np.sin(ky * y) + 0.2
    v = -0.6 * (kx / ky) * np.sin(kx * x) * np.cos(ky * y)
    return np.stack([u, v])


def path_cells():
    """A serpentine over the southern half: rows 2, 6, 10 (every column), 3 legs joined."""
    cells = []
    for i, r in enumerate((2, 6, 10)):
        cols = range(C) if i % 2 == 0 else range(C - 1, -1, -1)
        cells += [(r, c) for c in cols]
    return np.array(cells)


def samples(grid, cells, rng):
    x, y = grid.cell_to_xy(cells[:, 0], cells[:, 1])
    xy = np.column_stack([x, y])
    uv = analytic(x, y).T + rng.normal(0, NOISE, (len(cells), 2))
    return xy, uv


def test_near_path_error_below_noise_and_std_grows(grid):
    rng = np.random.default_rng(0)
    cells = path_cells()
    xy, uv = samples(grid, cells, rng)
    X, Y = grid.centres_xy()
    truth = analytic(X, Y)
    gp = GPReconstructor(grid_xy=(X, Y), prior="none", noise_std=NOISE, kernel="matern52")
    mean, std = gp.fit(xy, uv).reconstruct(xy, uv)
    assert mean.shape == (2, R, C) and mean.dtype == np.float32 and std.dtype == np.float32
    err = np.hypot(*(mean - truth))
    rows_on = [2, 6, 10]
    # on the sampled rows the error is below the sensor noise (the GP averages it down)
    assert np.sqrt(np.mean(err[rows_on] ** 2)) < NOISE
    # between sampled rows too (4 km gaps << 20 km wavelength)
    assert np.sqrt(np.mean(err[3:10] ** 2)) < 1.5 * NOISE
    # std grows with distance from the sampled band: row 6 < row 16 < row 29
    s = np.hypot(*std).mean(axis=1)
    assert s[6] < s[16] < s[29]
    assert s[29] > 5 * s[6]


def test_forecast_prior_recovers_forecast_far_from_samples(grid):
    rng = np.random.default_rng(1)
    X, Y = grid.centres_xy()
    truth = analytic(X, Y)
    # forecast = truth + a localised bias near the path (the model is wrong there)
    bx, by = grid.cell_to_xy(6, 15)
    bias = 0.3 * np.exp(-((X - bx) ** 2 + (Y - by) ** 2) / (2 * 4e3**2))
    forecast = truth + np.stack([bias, -bias])
    cells = path_cells()
    xy, uv = samples(grid, cells, rng)
    f_at = forecast[:, cells[:, 0], cells[:, 1]].T
    gp = GPReconstructor(grid_xy=(X, Y), prior="forecast", noise_std=NOISE)
    mean, _std = gp.fit(xy, uv, forecast_at_samples=f_at).reconstruct(
        xy, uv, forecast=forecast, forecast_at_samples=f_at
    )
    # near the path the bias is removed
    err_before = np.hypot(*(forecast - truth))[2:11].mean()
    err_after = np.hypot(*(mean - truth))[2:11].mean()
    assert err_after < 0.25 * err_before
    # far from every sample the reconstruction returns to the forecast: the correction
    # decays with distance (fitted length scale ~7 km), < 0.01 m/s beyond 15 km (rows >= 25)
    corr = np.abs(mean - forecast).max(axis=(0, 2))
    assert corr[25:].max() < 0.01 and corr[5] > 0.2
    assert np.all(np.diff(corr[12:]) < 0)
    # nearest-cell default for forecast_at_samples gives the same answer on centred samples
    m2, _ = gp.reconstruct(xy, uv, forecast=forecast)
    np.testing.assert_allclose(m2, mean, atol=1e-5)


def test_land_stays_nan_and_kernel_is_held_fixed(grid):
    rng = np.random.default_rng(2)
    X, Y = grid.centres_xy()
    forecast = analytic(X, Y)
    forecast[:, 20:25, 5:9] = np.nan
    cells = path_cells()
    xy, uv = samples(grid, cells, rng)
    gp = GPReconstructor(grid_xy=(X, Y), noise_std=NOISE).fit_field(analytic(X, Y))
    k0 = [str(k) for k in gp.kernels_]
    mean, std = gp.reconstruct(xy, uv, forecast=forecast)
    assert np.isnan(mean[:, 20:25, 5:9]).all() and np.isnan(std[:, 20:25, 5:9]).all()
    assert np.isfinite(mean).sum() == 2 * (R * C - 20)
    assert [str(k) for k in gp.kernels_] == k0  # held fixed
    # the field fit finds the field's scale: length scale of a few km, below the 20-25 km wavelength
    ls = gp.kernels_[0].k1.k2.length_scale
    assert 2e3 < ls < 20e3


def test_errors(grid):
    X, Y = grid.centres_xy()
    xy = np.array([[0.0, 0.0], [1000.0, 0.0], [0.0, 1000.0]])
    uv = np.array([[0.1, 0.0], [0.2, 0.1], [0.0, 0.1]])
    gp = GPReconstructor(grid_xy=(X, Y), prior="none")
    gp.fit(xy, uv)
    # a negative jitter makes the kernel matrix indefinite: the same failure as an
    # ill-conditioned one, and the message must tell the user what to change
    bad = GPReconstructor(grid_xy=(X, Y), prior="none", alpha=-10.0)
    bad.kernels_ = gp.kernels_
    with pytest.raises(ReconstructionError, match="increase the noise level"):
        bad.reconstruct(xy, uv)
    with pytest.raises(ReconstructionError, match="forecast"):
        GPReconstructor(grid_xy=(X, Y)).reconstruct(xy, uv)
    with pytest.raises(ReconstructionError, match="prior"):
        GPReconstructor(grid_xy=(X, Y), prior="zero").fit(xy, uv)
    with pytest.raises(ReconstructionError, match="at least 2"):
        GPReconstructor(grid_xy=(X, Y), prior="none").fit(xy[:1], uv[:1])


@pytest.mark.parametrize("prior,space_time", [("forecast", False), ("none", False), ("forecast", True)])
def test_cholesky_solver_matches_sklearn(grid, prior, space_time):
    """The campaign engine's direct Cholesky posterior is sklearn's, to 1e-6, for a fixed kernel
    (space-only and space-time kernels, both priors)."""
    rng = np.random.default_rng(5)
    X, Y = grid.centres_xy()
    forecast = analytic(X, Y) * 0.8
    forecast[:, 20:25, 5:9] = np.nan
    cells = path_cells()
    xy, uv = samples(grid, cells, rng)
    t = np.linspace(0.0, 5.0, len(cells)) if space_time else None
    kw = dict(grid_xy=(X, Y), prior=prior, noise_std=NOISE)
    fa = analytic(xy[:, 0], xy[:, 1]).T * 0.8
    ref = GPReconstructor(**kw).fit(xy, uv, fa, samples_t=t)
    fast = GPReconstructor(solver="cholesky", **kw)
    fast.kernels_, fast.cell_m_, fast.n_inputs_ = ref.kernels_, ref.cell_m_, ref.n_inputs_
    call = dict(forecast=forecast, forecast_at_samples=fa, samples_t=t, t=5.0 if space_time else None)
    m0, s0 = ref.reconstruct(xy, uv, **call)
    m1, s1 = fast.reconstruct(xy, uv, **call)
    assert np.isnan(m1[:, 20:25, 5:9]).all()
    np.testing.assert_allclose(m1, m0, atol=1e-6, rtol=0)
    np.testing.assert_allclose(s1, s0, atol=1e-6, rtol=0)
    assert np.nanstd(m0) > 0.1  # a non-trivial posterior was compared
    with pytest.raises(ReconstructionError, match="solver"):
        GPReconstructor(solver="gpu", **kw).fit(xy, uv, fa).reconstruct(
            xy, uv, forecast=forecast, forecast_at_samples=fa
        )


def test_cholesky_column_cache_is_exact_and_std_can_be_skipped(grid):
    """The cached grid-to-sample covariance columns equal the kernel's own evaluation bit for
    bit, leg after leg (repeated, new and duplicated positions, a second time offset), a refit
    starts a new cache, and ``with_std=False`` gives the same mean without the std."""
    rng = np.random.default_rng(9)
    X, Y = grid.centres_xy()
    forecast = analytic(X, Y) * 0.8
    kw = dict(grid_xy=(X, Y), noise_std=NOISE, solver="cholesky")
    cells = path_cells()
    xy, uv = samples(grid, cells, rng)
    fa = analytic(xy[:, 0], xy[:, 1]).T * 0.8
    t = np.full(len(cells), 5.0)
    gp = GPReconstructor(**kw).fit(xy, uv, fa, samples_t=np.linspace(0.0, 5.0, len(cells)))
    assert gp.n_inputs_ == 3
    kern = gp.kernels_[0]
    grid_pts = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    legs = [cells[:40], cells[20:70], np.concatenate([cells[60:], cells[60:65]])]
    for i, part in enumerate(legs):
        pxy = np.column_stack([*grid.cell_to_xy(part[:, 0], part[:, 1]), np.full(len(part), -1.0 * (i % 2))])
        got = gp.cross_cov(0, kern, pxy, grid_pts)
        np.testing.assert_array_equal(got, kern(grid_pts, pxy))
    n_cached = len(gp._col_cache[0][2])
    # offset 0: cells[:40] and cells[60:] (the duplicates cached once); offset -1: cells[20:70]
    assert n_cached == 40 + 30 + 50
    # reconstruct through the cache twice (the second call all hits) == a fresh reconstructor
    call = dict(forecast=forecast, forecast_at_samples=fa, samples_t=t, t=5.0)
    m1, s1 = gp.reconstruct(xy, uv, **call)
    m2, s2 = gp.reconstruct(xy, uv, **call)
    fresh = GPReconstructor(**kw)
    fresh.kernels_, fresh.cell_m_, fresh.n_inputs_ = gp.kernels_, gp.cell_m_, gp.n_inputs_
    m0, s0 = fresh.reconstruct(xy, uv, **call)
    for m, s in ((m1, s1), (m2, s2)):
        np.testing.assert_allclose(m, m0, atol=1e-7, rtol=0)
        np.testing.assert_allclose(s, s0, atol=1e-7, rtol=0)
    m3, s3 = gp.reconstruct(xy, uv, with_std=False, **call)
    assert s3 is None
    np.testing.assert_allclose(m3, m0, atol=1e-7, rtol=0)
    # a refit replaces the kernel object: the next call starts a new cache
    gp.fit(xy, uv, fa, samples_t=np.linspace(0.0, 5.0, len(cells)))
    gp.reconstruct(
        xy[:10], uv[:10], forecast=forecast, forecast_at_samples=fa[:10], samples_t=t[:10], t=5.0, with_std=False
    )
    assert gp._col_cache[0][0] is gp.kernels_[0] and len(gp._col_cache[0][2]) == len({tuple(r) for r in cells[:10]})
    # the sklearn solver always returns the std
    sk = GPReconstructor(**{**kw, "solver": "sklearn"})
    sk.kernels_, sk.cell_m_, sk.n_inputs_ = fresh.kernels_, fresh.cell_m_, fresh.n_inputs_
    assert sk.reconstruct(xy, uv, with_std=False, **call)[1] is not None


def _smooth_modes(grid, n_modes: int) -> np.ndarray:
    """(n_modes, 2, R, C) large-scale patterns (wavelengths >= the grid) over both components."""
    X, Y = grid.centres_xy()
    x, y = X / (CELL * C), Y / (CELL * R)
    pats = [
        np.stack([np.sin(np.pi * x), np.cos(np.pi * y)]),
        np.stack([np.cos(np.pi * x) * y, -np.sin(np.pi * y)]),
        np.stack([x * y, x - y]),
    ]
    return 0.3 * np.stack(pats[:n_modes])


def test_background_posterior_equals_the_dense_joint_gp(grid):
    """The joint u/v posterior with background modes equals the textbook GP formulas written out
    with dense matrices (prior covariance B + blockdiag(k_u, k_v), np.linalg.solve), mean and std,
    with land; zero modes give the component-wise posterior."""
    rng = np.random.default_rng(11)
    X, Y = grid.centres_xy()
    forecast = analytic(X, Y) * 0.8
    forecast[:, 20:25, 5:9] = np.nan
    modes = _smooth_modes(grid, 3)
    cells = path_cells()[::2]
    xy, uv = samples(grid, cells, rng)
    fa = analytic(xy[:, 0], xy[:, 1]).T * 0.8
    ref = GPReconstructor(grid_xy=(X, Y), noise_std=NOISE, solver="cholesky").fit(xy, uv, fa)
    gp = GPReconstructor(
        grid_xy=(X, Y),
        noise_std=NOISE,
        solver="cholesky",
        background=modes,
        background_scale=1.0,
        std_calibration="off",  # the GP posterior's own std (test_calibration.py: the map's)
    )
    gp.kernels_, gp.cell_m_, gp.n_inputs_ = ref.kernels_, ref.cell_m_, ref.n_inputs_
    mean, std = gp.reconstruct(xy, uv, forecast=forecast, forecast_at_samples=fa)
    # dense reference
    n, N = len(xy), X.size
    G = np.column_stack([X.ravel(), Y.ravel()])
    Bg = modes.reshape(3, 2 * N)  # [u cells, v cells]
    flat = cells[:, 0] * C + cells[:, 1]
    Hb = np.concatenate([Bg[:, flat], Bg[:, N + flat]], axis=1)
    Kss = Hb.T @ Hb
    Kgs = Bg.T @ Hb
    prior_var = np.einsum("ij,ij->j", Bg, Bg)
    for k, kern in enumerate(ref.kernels_):
        Kss[k * n : (k + 1) * n, k * n : (k + 1) * n] += kern(xy) + gp.alpha * np.eye(n)
        Kgs[k * N : (k + 1) * N, k * n : (k + 1) * n] += kern(G, xy)
        prior_var[k * N : (k + 1) * N] += kern.diag(G)
    y = (uv - fa).T.ravel()
    m_ref = Kgs @ np.linalg.solve(Kss, y) + np.nan_to_num(forecast).ravel()
    v_ref = prior_var - np.einsum("ij,ji->i", Kgs, np.linalg.solve(Kss, Kgs.T))
    water = np.isfinite(forecast).all(axis=0)
    np.testing.assert_allclose(mean[:, water], m_ref.reshape(2, R, C)[:, water], atol=1e-6, rtol=0)
    np.testing.assert_allclose(std[:, water], np.sqrt(v_ref).reshape(2, R, C)[:, water], atol=1e-6, rtol=0)
    assert np.isnan(mean[:, ~water]).all() and np.isnan(std[:, ~water]).all()
    # zero modes: the joint posterior falls apart into the two component posteriors
    gp0 = GPReconstructor(
        grid_xy=(X, Y),
        noise_std=NOISE,
        solver="cholesky",
        background=np.zeros_like(modes),
        background_scale=1.0,
        std_calibration="off",
    )
    gp0.kernels_, gp0.cell_m_, gp0.n_inputs_ = ref.kernels_, ref.cell_m_, ref.n_inputs_
    ref.std_calibration = "off"
    m0, s0 = gp0.reconstruct(xy, uv, forecast=forecast, forecast_at_samples=fa)
    m1, s1 = ref.reconstruct(xy, uv, forecast=forecast, forecast_at_samples=fa)
    np.testing.assert_allclose(m0, m1, atol=1e-6, rtol=0)
    np.testing.assert_allclose(s0, s1, atol=1e-6, rtol=0)
    with pytest.raises(ReconstructionError, match="background modes must have shape"):
        GPReconstructor(grid_xy=(X, Y), solver="cholesky", background=modes[:, :, :10]).fit(xy, uv, fa).reconstruct(
            xy, uv, forecast=forecast, forecast_at_samples=fa
        )


def test_background_recovers_a_modal_error_far_from_the_samples(grid):
    """The forecast is wrong by one large-scale mode (RMS 0.5 m/s). Sampled only on rows 2-10,
    the stationary GP corrects those rows and returns to the (wrong) forecast in the north; with
    the modes as background covariance most of the error is removed in the north too."""
    rng = np.random.default_rng(12)
    X, Y = grid.centres_xy()
    modes = _smooth_modes(grid, 3)
    truth = analytic(X, Y)
    forecast = truth - 0.8 * modes[1] / 0.3  # error of amplitude ~0.8 m/s, shaped like mode 1
    cells = path_cells()
    xy = np.column_stack(grid.cell_to_xy(cells[:, 0], cells[:, 1]))
    uv = truth[:, cells[:, 0], cells[:, 1]].T + rng.normal(0, NOISE, (len(cells), 2))
    fa = forecast[:, cells[:, 0], cells[:, 1]].T
    plain = GPReconstructor(grid_xy=(X, Y), noise_std=NOISE, solver="cholesky").fit(xy, uv, fa)
    with_b = GPReconstructor(grid_xy=(X, Y), noise_std=NOISE, solver="cholesky", background=modes, background_scale=1.0)
    with_b.kernels_, with_b.cell_m_, with_b.n_inputs_ = plain.kernels_, plain.cell_m_, plain.n_inputs_
    north = (slice(None), slice(20, 30))
    e_fc = np.sqrt(np.mean((forecast - truth)[north] ** 2))
    e_plain = np.sqrt(
        np.mean((plain.reconstruct(xy, uv, forecast=forecast, forecast_at_samples=fa)[0] - truth)[north] ** 2)
    )
    e_bg = np.sqrt(
        np.mean((with_b.reconstruct(xy, uv, forecast=forecast, forecast_at_samples=fa)[0] - truth)[north] ** 2)
    )
    # measured: forecast 0.496, stationary GP 0.509 (it leaves the far error), with the mode 0.056
    # (the stationary kernel, fitted on this residual, takes a share of it near the track)
    assert e_plain > 0.7 * e_fc
    assert e_bg < 0.15 * e_fc


class _OscillatingStub:
    """A predictor whose roll-out is ``state + a (cos(wk) - 1) phi1 + a sin(wk) phi2``, k = 1..steps."""

    def __init__(self, phi1, phi2, a=0.5, period=8):
        self.phi1, self.phi2, self.a, self.w = phi1, phi2, a, 2 * np.pi / period

    def predict(self, state, steps):
        k = np.arange(1, steps + 1)[:, None, None, None]
        return (
            state[None] + self.a * (np.cos(self.w * k) - 1) * self.phi1 + self.a * np.sin(self.w * k) * self.phi2
        ).astype(np.float32)


def test_model_background_of_a_known_roll_out(grid):
    """Two orthonormal patterns oscillating in quadrature over whole periods: the anomaly
    covariance is a^2 n / (2 (n - 1)) (phi1 phi1^T + phi2 phi2^T) exactly, found as 2 modes; land
    stays NaN; a roll-out that does not vary (persistence) gives no background."""
    from passt_mav.reconstruction import model_background

    X, Y = grid.centres_xy()
    m = _smooth_modes(grid, 2).reshape(2, -1).astype(np.float64)
    q, _ = np.linalg.qr(m.T)
    phi1, phi2 = (q[:, j].reshape(2, R, C) for j in range(2))
    state = analytic(X, Y).astype(np.float32)
    a, period = 0.5, 8
    modes = model_background(_OscillatingStub(phi1, phi2, a, period), state, 4 * period - 1)
    n = 4 * period
    assert modes.shape == (2, 2, R, C)
    B = np.einsum("mi,mj->ij", modes.reshape(2, -1), modes.reshape(2, -1))
    B_ref = a**2 * n / (2 * (n - 1)) * (np.outer(phi1, phi1) + np.outer(phi2, phi2))
    np.testing.assert_allclose(B, B_ref, atol=1e-6)
    # land: NaN in the state -> NaN in the modes
    st = state.copy()
    st[:, :3, :3] = np.nan
    ml = model_background(_OscillatingStub(phi1, phi2, a, period), st, 4 * period - 1)
    assert np.isnan(ml[:, :, :3, :3]).all() and np.isfinite(ml[:, :, 3:, :]).all()

    class Persistence:
        def predict(self, s, steps):
            return np.repeat(s[None], steps, axis=0)

    assert model_background(Persistence(), state, 20) is None
    with pytest.raises(ReconstructionError, match="at least 2 steps"):
        model_background(Persistence(), state, 1)


def test_background_scale_by_marginal_likelihood(grid):
    """background_scale="ml" (fitted at each reconstruction): residuals that are sensor noise
    only get (almost) no background;
    a residual shaped like a mode gets a large factor, and the reconstruction then removes it far
    from the samples (as with the factor fixed at 1). Measured: factors 3.2e-4 and 3.16, far
    error 0.038 of 0.496."""
    rng = np.random.default_rng(13)
    X, Y = grid.centres_xy()
    modes = _smooth_modes(grid, 3)
    truth = analytic(X, Y)
    cells = path_cells()
    xy = np.column_stack(grid.cell_to_xy(cells[:, 0], cells[:, 1]))
    uv = truth[:, cells[:, 0], cells[:, 1]].T + rng.normal(0, NOISE, (len(cells), 2))
    # 1. the forecast is the truth: residual = noise
    fa = truth[:, cells[:, 0], cells[:, 1]].T
    gp = GPReconstructor(grid_xy=(X, Y), noise_std=NOISE, solver="cholesky", background=modes).fit(xy, uv, fa)
    gp.reconstruct(xy, uv, forecast=truth, forecast_at_samples=fa)
    assert gp.background_scale_ <= 1e-3
    # 2. the forecast is wrong by a mode
    forecast = truth - 0.8 * modes[1] / 0.3
    fa = forecast[:, cells[:, 0], cells[:, 1]].T
    gp = GPReconstructor(grid_xy=(X, Y), noise_std=NOISE, solver="cholesky", background=modes).fit(xy, uv, fa)
    north = (slice(None), slice(20, 30))
    e_fc = np.sqrt(np.mean((forecast - truth)[north] ** 2))
    e_bg = np.sqrt(np.mean((gp.reconstruct(xy, uv, forecast=forecast, forecast_at_samples=fa)[0] - truth)[north] ** 2))
    assert gp.background_scale_ >= 0.1
    assert e_bg < 0.15 * e_fc
    with pytest.raises(ReconstructionError, match="background_scale"):
        GPReconstructor(grid_xy=(X, Y), solver="cholesky", background=modes, background_scale=-1.0).fit(
            xy, uv, fa
        ).reconstruct(xy, uv, forecast=forecast, forecast_at_samples=fa)


def ten_hour_track(grid):
    """The first 60 cells of :func:`path_cells` flown over 10 h: (cells, xy metres, t s, a zero forecast at them)."""
    cells = path_cells()[:60]
    x, y = grid.cell_to_xy(cells[:, 0], cells[:, 1])
    t = np.linspace(0.0, 10 * 3600.0, len(cells))
    return cells, np.column_stack([x, y]), t, np.zeros((len(cells), 2))


def test_forward_validation_shortens_the_time_scale_of_a_turning_residual(grid):
    """A space-time fit along a track cannot tell space from time: a residual that turns with a tide
    (u-residual 0.3 cos(2 pi t / 12.4 h), the same everywhere, over a 10 h leg) is fitted as steady (a
    time length scale of months) and carried to the reconstruction's time. Forward validation on the
    leg's own last third keeps a shorter time length scale; the correction at 11 h near the track is
    then nearer the true residual (+0.23 m/s: the tide has turned back) than with the likelihood's
    length scale. A steady residual keeps the likelihood's length scale (factor 1)."""
    import copy

    rng = np.random.default_rng(3)
    cells, xy, t, fc_at = ten_hour_track(grid)
    tide = 0.3 * np.cos(2 * np.pi * t / (12.4 * 3600.0))
    turning = np.column_stack([tide, np.zeros_like(t)]) + rng.normal(0, NOISE, (len(t), 2))
    gp = GPReconstructor(grid_xy=grid.centres_xy(), noise_std=NOISE, seed=0)
    gp.fit(xy, turning, forecast_at_samples=fc_at, samples_t=t)
    factor = gp.time_scale_factor_[0]
    assert gp.n_inputs_ == 3 and factor < 1.0
    fitted = copy.deepcopy(gp)  # the likelihood's time length scale restored
    ls = np.asarray(fitted.kernels_[0].k1.k2.length_scale, float)
    fitted.kernels_[0].set_params(k1__k2__length_scale=np.array([ls[0], ls[1], ls[2] / factor]))
    t_end = 11 * 3600.0
    want = 0.3 * np.cos(2 * np.pi * t_end / (12.4 * 3600.0))
    near = np.zeros((R, C), bool)
    near[cells[:, 0], cells[:, 1]] = True
    err = []
    for g in (gp, fitted):
        mean, _ = g.reconstruct(xy, turning, np.zeros((2, R, C)), forecast_at_samples=fc_at, samples_t=t, t=t_end)
        err.append(abs(float(np.mean(mean[0][near])) - want))
    assert err[0] < err[1] - 0.01, err
    steady = np.column_stack([np.full_like(t, 0.2), np.zeros_like(t)]) + rng.normal(0, NOISE, (len(t), 2))
    gp2 = GPReconstructor(grid_xy=grid.centres_xy(), noise_std=NOISE, seed=0)
    gp2.fit(xy, steady, forecast_at_samples=fc_at, samples_t=t)
    assert gp2.time_scale_factor_[0] == 1.0


def test_decorrelation_time_of_a_tide_and_of_a_steady_current(grid):
    """A current turning with the 12.4 h tide, u = 0.5 cos(2 pi t / 12.4 h + phase(x)), sampled every
    15 min for 10 days: its autocorrelation is cos(2 pi tau / 12.4 h), which is 0.5 at a sixth of the
    period (2.07 h). A steady current has no variance in time: no decorrelation time (None)."""
    from passt_mav.fields.field import FlowField

    T = 12.4 * 3600.0
    times = np.arange(0.0, 10 * 86400.0, 900.0)
    x, _ = grid.centres_xy()
    phase = 2 * np.pi * x / 40e3
    u = 0.5 * np.cos(2 * np.pi * times[:, None, None] / T + phase[None])
    data = np.stack([u, 0.3 * u], axis=1).astype(np.float32)
    tide = FlowField(data, grid, times)
    assert tide.decorrelation_time() == pytest.approx(T / 6, rel=0.03)
    steady = FlowField(np.ones_like(data), grid, times)
    assert steady.decorrelation_time() is None


def test_time_scale_cap_holds_a_steady_looking_residual_to_the_current_s_own_memory(grid):
    """Along one track a residual that rises and falls within the leg is fitted as steady (a time
    length scale of days). With ``max_time_scale`` the kernel keeps at most that scale (before forward
    validation, which may only shorten it further), and the correction carried to 2 h after the last
    sample, where the true residual has gone, is smaller than without the cap."""
    rng = np.random.default_rng(5)
    _cells, xy, t, fc_at = ten_hour_track(grid)
    bump = 0.3 * np.exp(-0.5 * ((t - 5 * 3600.0) / (1.5 * 3600.0)) ** 2)  # gone by the leg's end
    res = np.column_stack([bump, np.zeros_like(t)]) + rng.normal(0, NOISE, (len(t), 2))
    cap = 2 * 3600.0
    out = {}
    for name, mts in (("capped", cap), ("free", None)):
        gp = GPReconstructor(grid_xy=grid.centres_xy(), noise_std=NOISE, seed=0, forward_validation=False)
        gp.max_time_scale = mts
        gp.fit(xy, res, forecast_at_samples=fc_at, samples_t=t)
        out[name] = gp
    lt = [float(np.asarray(k.k1.k2.length_scale)[2]) for k in out["capped"].kernels_]
    assert max(lt) <= cap * (1 + 1e-9) and out["capped"].time_scale_capped_[0]
    assert float(np.asarray(out["free"].kernels_[0].k1.k2.length_scale)[2]) > cap
    corr = {}
    for name, gp in out.items():
        mean, _ = gp.reconstruct(xy, res, np.zeros((2, R, C)), forecast_at_samples=fc_at, samples_t=t, t=12 * 3600.0)
        corr[name] = float(np.sqrt(np.nanmean(mean[0] ** 2)))
    assert corr["capped"] < 0.5 * corr["free"], corr
