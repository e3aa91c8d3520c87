"""Known answers for the calibration figures (passt_mav.models.calibration), the GP's std checks
(passt_mav.reconstruction.gp: forward check, lead growth, the background share it estimates) and the leg scores."""

from __future__ import annotations

import math

import numpy as np
import pytest

from passt_mav.loop.scoring import beaten_message, leg_scores
from passt_mav.models.calibration import (
    RELIABILITY_LEVELS,
    beaten_by,
    calibration,
    coverage,
    nlpd,
    reliability,
    trivial_scores,
    z_rms,
)


def _draw(n=20000, s=0.3, seed=0):
    rng = np.random.default_rng(seed)
    mean = rng.normal(0.0, 1.0, (2, n // 100, 100))
    truth = mean + rng.normal(0.0, s, mean.shape)
    return mean, np.full(mean.shape, s), truth


def test_gaussian_draws_give_the_known_answers():
    mean, std, truth = _draw(s=0.3)
    n = mean.size  # 20000 pairs: binomial sd of the coverage sqrt(.95 * .05 / n) = 0.0015
    assert coverage(mean, std, truth) == pytest.approx(0.95, abs=0.006)
    # E[nlpd] = 0.5 ln(2 pi e s^2); its sd over n pairs is sqrt(0.5 / n) = 0.005
    assert nlpd(mean, std, truth) == pytest.approx(0.5 * math.log(2 * math.pi * math.e * 0.3**2), abs=0.02)
    assert z_rms(mean, std, truth) == pytest.approx(1.0, abs=0.015)
    rel = reliability(mean, std, truth)
    assert np.allclose(rel, RELIABILITY_LEVELS, atol=0.015)
    c = calibration(mean, std, truth)
    assert c["n"] == n and c["coverage95"] == pytest.approx(coverage(mean, std, truth))
    assert c["nlpd"] == pytest.approx(nlpd(mean, std, truth)) and c["reliability"] == pytest.approx(rel)


def test_a_std_half_too_small_is_caught():
    mean, std, truth = _draw(s=0.3)
    half = std / 2
    # |z| <= 1.96 / 2 = 0.98 standard deviations of the real error: P = 0.673
    assert coverage(mean, half, truth) == pytest.approx(0.673, abs=0.01)
    assert z_rms(mean, half, truth) == pytest.approx(2.0, abs=0.03)
    # overconfidence costs density: E[nlpd] = 0.5 ln(2 pi (s/2)^2) + 0.5 * 4
    assert nlpd(mean, half, truth) == pytest.approx(0.5 * math.log(2 * math.pi * 0.15**2) + 2.0, abs=0.05)
    assert nlpd(mean, half, truth) > nlpd(mean, std, truth) + 0.5
    # too wide is caught the other way: 1.96 * 2 std covers nearly all
    assert coverage(mean, 2 * std, truth) > 0.999


def test_invalid_pairs_are_left_out_and_nothing_valid_is_none():
    mean, std, truth = _draw(n=400, s=0.1)
    base = calibration(mean, std, truth)
    m2, s2, t2 = mean.copy(), std.copy(), truth.copy()
    m2[0, 0, :10] = np.nan
    s2[1, 1, :5] = 0.0  # no std: not a Gaussian
    t2[0, 2, :3] = np.nan  # land
    c = calibration(m2, s2, t2)
    assert c["n"] == base["n"] - 18
    assert calibration(mean, None, truth) is None and calibration(mean, std, None) is None
    assert coverage(mean, np.zeros_like(std), truth) is None
    with pytest.raises(ValueError):
        coverage(mean, std[:, :1], truth)


def test_trivial_maps_and_the_beaten_message():
    truth = np.zeros((2, 4, 4))
    truth[0] = 1.0  # 1 m/s east everywhere: zero current has RMSE sqrt(1/2)
    est = truth + 0.1
    fm = truth.copy()  # a perfect time mean
    sc = trivial_scores(est, truth, fm)
    assert sc["zero"] == pytest.approx(math.sqrt(0.5))
    assert sc["forecast_mean"] == pytest.approx(0.0) and sc["map"] == pytest.approx(0.1)
    assert beaten_by(sc) == ["forecast_mean"]
    cal, base = leg_scores(est, np.full(est.shape, 0.1), truth, fm)
    assert cal["coverage95"] == 1.0 and base["beaten_by"] == ["forecast_mean"]
    msg = beaten_message(base, "leg 2/5", lambda x: f"{x:.2f} m/s")
    assert msg == "leg 2/5: the map (RMSE 0.10 m/s) does not beat the forecast's time mean (RMSE 0.00 m/s)"
    assert leg_scores(est, None, None) == (None, None)
    _, good = leg_scores(truth, None, truth, fm + 0.5)
    assert good["beaten_by"] == [] and beaten_message(good, "leg 1", str) is None


def test_lead_growth_known_answer():
    from passt_mav.reconstruction.gp import lead_growth

    t = np.linspace(0.0, 2.0, 41)
    sq = 0.01 + 0.02 * t  # error variance growing linearly with lead
    # the map at t = 3: 0.07 against the samples' mean 0.01 + 0.02 * 1 = 0.03
    assert lead_growth(t, sq, 3.0) == pytest.approx(0.07 / 0.03)
    assert lead_growth(t, 0.05 - 0.02 * t, 3.0) == 1.0  # shrinking: never narrows
    assert lead_growth(np.ones(5), np.ones(5), 3.0) == 1.0  # no spread in time


def _gp_case(seed=0, scale=1.0):
    """A residual GP on a 12 x 12 grid of 100 m cells: the residual truth is a GP draw of the kernel the
    GP is given (right hyper-parameters), sampled along a track with sensor noise."""
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    from passt_mav.reconstruction import GPReconstructor

    rng = np.random.default_rng(seed)
    R = C = 12
    X, Y = np.meshgrid(np.arange(C) * 100.0, np.arange(R) * 100.0)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    k = ConstantKernel(0.04) * Matern(length_scale=300.0, nu=2.5)
    K = k(pts) + 1e-8 * np.eye(len(pts))
    L = np.linalg.cholesky(K)
    resid = np.stack([(L @ rng.normal(size=len(pts))).reshape(R, C) for _ in range(2)])
    fc = np.zeros((2, R, C))
    truth = fc + resid
    cells = [(r, c) for r in range(R) for c in range(C) if (r + c) % 3 == 0]
    idx = rng.choice(len(cells), 40, replace=False)
    rc = np.array([cells[i] for i in idx])
    xy = np.column_stack([X[rc[:, 0], rc[:, 1]], Y[rc[:, 0], rc[:, 1]]])
    uv = truth[:, rc[:, 0], rc[:, 1]].T + rng.normal(0, 0.02, (len(rc), 2))
    gp = GPReconstructor(grid_xy=(X, Y), solver="cholesky", space_time=False, noise_std=0.02)
    kern = ConstantKernel(0.04 * scale**2, "fixed") * Matern(300.0, "fixed", nu=2.5) + WhiteKernel(0.02**2, "fixed")
    gp.kernels_, gp.cell_m_, gp.n_inputs_ = [kern, kern], 100.0, 2
    return gp, xy, uv, fc, truth


def test_forward_check_leaves_a_right_std_alone_and_widens_a_small_one():
    # right hyper-parameters: the held-out third falls inside the std as it says (factor ~1; the map is
    # covered as the std says, a little over: a 12 x 12 draw varies less than its kernel's variance)
    facs, covs = [], []
    for seed in range(6):
        gp, xy, uv, fc, truth = _gp_case(seed)
        mean, std = gp.reconstruct(xy, uv, fc)
        facs.append(gp.std_inflation_)
        covs.append(calibration(mean, std, truth)["coverage95"])
    assert 1.0 <= np.mean(facs) <= 1.15
    assert 0.93 <= np.mean(covs) <= 0.995
    # a kernel std 0.3 of the truth's: the raw std covers ~0.8 of the map; the check widens it by ~2.5
    # (1 / 0.3 less the draws' smaller realised variance) and the coverage is back above 0.93
    facs, raw, fixed = [], [], []
    for seed in range(6):
        gp, xy, uv, fc, truth = _gp_case(seed, scale=0.3)
        mean, std = gp.reconstruct(xy, uv, fc)
        facs.append(gp.std_inflation_)
        fixed.append(calibration(mean, std, truth)["coverage95"])
        gp.std_calibration = "off"
        mean, std = gp.reconstruct(xy, uv, fc)
        raw.append(calibration(mean, std, truth)["coverage95"])
    assert np.mean(facs) == pytest.approx(2.5, abs=0.6)
    assert np.mean(raw) < 0.85 and np.mean(fixed) > 0.93


def test_std_calibration_checked():
    from passt_mav.errors import ReconstructionError

    gp, xy, uv, fc, _ = _gp_case(0)
    gp.std_calibration = "sometimes"
    with pytest.raises(ReconstructionError, match="std_calibration"):
        gp.reconstruct(xy, uv, fc)
    gp.std_calibration = "forward"
    gp.unresolved_share = 1.5
    with pytest.raises(ReconstructionError, match="unresolved_share"):
        gp.reconstruct(xy, uv, fc)
    gp.unresolved_share = "estimate"
    gp.std_calibration = "off"
    m0, s0 = gp.reconstruct(xy, uv, fc)
    gp.std_calibration = "forward"
    m1, s1 = gp.reconstruct(xy, uv, fc)
    assert np.array_equal(m0, m1)  # the check widens the std only, never moves the mean
    assert np.all(s1 >= s0 - 1e-7)


def test_unresolved_share_moment_known_answer():
    # errors drawn with variance post_var + s bvar: the moment estimate gives s back (1 % of 20000 pairs),
    # clipped at 0 when the posterior is already wider than the errors and at 1 beyond the whole background
    from passt_mav.reconstruction.gp import unresolved_share

    rng = np.random.default_rng(0)
    pv, bv = rng.uniform(1e-4, 4e-4, (10000, 2)), rng.uniform(1e-3, 4e-3, (10000, 2))
    err = rng.normal(size=pv.shape) * np.sqrt(pv + 0.3 * bv)
    assert unresolved_share(err, pv, bv) == pytest.approx(0.3, abs=0.01)
    assert unresolved_share(0.5 * err, 4 * pv, bv) == 0.0
    assert unresolved_share(4 * err, pv, bv) == 1.0
    assert unresolved_share(err, pv, np.zeros_like(bv)) is None


def _background_case(share, seed):
    """A residual GP with a background of 3 smooth modes (factor held at 1) on a 12 x 12 grid of 100 m
    cells: the truth is the modes times N(0, 1) amplitudes plus a white perturbation of variance
    ``share`` x diag B per cell (what the modes cannot resolve), sampled at 120 cells with 0.005 m/s noise.
    The stationary kernel is ~0: the background is the GP's whole prior."""
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    from passt_mav.reconstruction import GPReconstructor

    rng = np.random.default_rng(seed)
    R = C = 12
    X, Y = np.meshgrid(np.arange(C) * 100.0, np.arange(R) * 100.0)
    x, y = X / 1100.0, Y / 1100.0
    modes = 0.05 * np.stack(
        [np.stack([np.sin(np.pi * x), np.cos(np.pi * y)]), np.stack([x * y, x - y]), np.stack([np.cos(2 * x), y])]
    )
    bvar = np.sum(modes**2, axis=0)
    truth = np.tensordot(rng.normal(size=3), modes, axes=1) + rng.normal(size=bvar.shape) * np.sqrt(share * bvar)
    flat = rng.choice(R * C, 120, replace=False)
    rc = np.column_stack(np.unravel_index(flat, (R, C)))
    xy = np.column_stack([X[rc[:, 0], rc[:, 1]], Y[rc[:, 0], rc[:, 1]]])
    uv = truth[:, rc[:, 0], rc[:, 1]].T + rng.normal(0, 0.005, (len(rc), 2))
    gp = GPReconstructor(
        grid_xy=(X, Y), solver="cholesky", space_time=False, noise_std=0.005, background=modes, background_scale=1.0
    )
    kern = ConstantKernel(1e-8, "fixed") * Matern(300.0, "fixed", nu=2.5) + WhiteKernel(0.005**2, "fixed")
    gp.kernels_, gp.cell_m_, gp.n_inputs_ = [kern, kern], 100.0, 2
    return gp, xy, uv, np.zeros((2, R, C)), truth


@pytest.mark.parametrize("share", [0.0, 0.4])
def test_the_map_estimates_a_known_unresolved_share(share):
    # the forward check's held-out samples find the perturbation the modes cannot carry: the estimated share
    # is the one drawn (mean of 8 draws, within 0.05), and the map's std then covers the truth as it says
    est, covs = [], []
    for seed in range(8):
        gp, xy, uv, fc, truth = _background_case(share, seed)
        mean, std = gp.reconstruct(xy, uv, fc)
        est.append(gp.unresolved_share_)
        covs.append(calibration(mean, std, truth)["coverage95"])
    assert np.mean(est) == pytest.approx(share, abs=0.05)
    assert 0.9 <= np.mean(covs) <= 1.0
    gp.unresolved_share = 0.0  # a fixed share is used as given
    _, s0 = gp.reconstruct(xy, uv, fc)
    assert gp.unresolved_share_ == est[-1] and gp.share_in_use() == 0.0
    assert share == 0.0 or np.mean(s0) < np.mean(std)


def test_leg_line_and_the_trivial_map_warning():
    """The console's leg line carries the 95 % interval's coverage and the NLPD; a leg whose map does not beat
    a trivial map gets one WARNING line and a warning event (m/s: field units x velocity_scale)."""
    from passt_mav.units import SpeedUnit
    from passt_mav.vehicle.controller import _progress_line, leg_warnings

    rec = {
        "rmse_passt": 0.1,
        "rmse_model": 0.2,
        "link": {"rtt_ms": 1.0, "loss": 0.0},
        "n_samples": 10,
        "n_gp_points": 10,
        "duration_s": 1.0,
        "duration_vehicle_s": 100.0,
        "planning_s": 0.1,
        "upload_s": 0.05,
        "calibration": {"coverage95": 0.934, "nlpd": -0.52},
        "baselines": {"zero": 0.7, "forecast_mean": 0.08, "map": 0.1, "beaten_by": ["forecast_mean"]},
    }
    assert "95 % interval holds 93 % (NLPD -0.52)" in _progress_line(rec, SpeedUnit())
    unit = SpeedUnit(0.5)  # (m/s = field units x velocity_scale 0.5)
    assert leg_warnings(rec, "leg 4/5", unit, 2.0) == [
        (
            "warning",
            "warn",
            "leg 4/5: the map (RMSE 0.0500 m/s) does not beat the forecast's time mean (RMSE 0.0400 m/s)",
        )
    ]
    assert leg_warnings({**rec, "baselines": {**rec["baselines"], "beaten_by": []}}, "leg 1/5", unit, 2.0) == []
    assert leg_warnings({"baselines": None}, "leg 1/5", unit, 2.0) == []


def test_a_leg_flown_far_off_its_planned_time_is_said_once():
    """Issue 52, item 3: a leg's plan is timed in the forecast current at the mission's speed over ground, so a
    leg flown more than 1.25 x longer (or shorter) than planned did not fly the speed asked (or met another
    current): one warning line naming both times; within the factor, or cut for an overrun or through a link outage (said already), none."""
    from passt_mav.units import SpeedUnit
    from passt_mav.vehicle.controller import TIMING_WARN_FACTOR, leg_warnings

    rec = {"duration_vehicle_s": 3232.0, "planned_duration_vehicle_s": 8000.0, "overrun": None}
    ((kind, level, text),) = leg_warnings(rec, "leg 1/2", SpeedUnit(), 2.0)  # SITL flew WP_SPEED 5 m/s, not 2
    assert (kind, level) == ("warning", "warn")
    assert "flown in 3232 s of vehicle time, planned 8000 s in the forecast current (x 0.40)" in text
    assert "speed asked (2 m/s over ground" in text
    assert leg_warnings({**rec, "duration_vehicle_s": 8000.0 * TIMING_WARN_FACTOR}, "leg 1/2", SpeedUnit(), 2.0) == []
    assert leg_warnings({**rec, "duration_vehicle_s": 8000.0 * 1.3}, "leg 1/2", SpeedUnit(), 2.0)[0][2].endswith(
        "or the current was not the forecast's"
    )
    assert leg_warnings({**rec, "overrun": {"factor": 2.0}}, "leg 1/2", SpeedUnit(), 2.0) == []
    assert leg_warnings({**rec, "outages": [{"leg": 0, "vehicle_s": 90.0}]}, "leg 1/2", SpeedUnit(), 2.0) == []
