"""Gaussian-process reconstruction of one field snapshot from scattered samples.

Frames and units: sample and grid positions are local east/north metres
(``grid.centres_xy()``, ``grid.latlon_to_xy``); velocities in the field's units
(m/s). One scikit-learn ``GaussianProcessRegressor`` per velocity component.

Kernel: ``ConstantKernel * Matern(nu) + WhiteKernel`` (or RBF). :meth:`GPReconstructor.fit` fits the
hyper-parameters on a leg's samples; the caller decides how often (the loop's ``hyper``: on every
leg by default, on the first leg only, or once on the initial state). Between fits they are held
fixed (``optimizer=None``), so a reconstruction is one Cholesky of an n x n matrix: milliseconds
for the few hundred samples of a leg.

Prior mean:

* ``prior="forecast"`` (default): the GP models the residual ``samples - forecast``
  (forecast at each sample's position and time, given by the caller) with zero
  mean, and the reconstruction is ``forecast + residual``; far from any sample it
  returns the forecast.
* ``prior="none"`` (the paper's literal variant): the GP models the samples alone
  with a constant mean (their average); far from samples it returns that mean.

Hyper-parameters: :meth:`GPReconstructor.fit` fits them on one leg's samples
(the residuals in forecast mode); :meth:`GPReconstructor.fit_field` on a gridded
snapshot. The WhiteKernel noise never drops below ``noise_std**2``, the sensor's noise: a
fit allowed below it turns noise into signal (and repeated or nearby samples taken at
different times make the kernel matrix near-singular). A fitted signal kernel, and a
background factor, are kept only when the samples' likelihood pays for them (the Bayesian
information criterion, :meth:`GPReconstructor._evidence_gate`): samples that show only
noise leave the forecast alone.

Background covariance (optional, ``background=``): low-rank modes ``b_j`` (2, R, C) of the
residual's covariance over BOTH components, ``B = sum_j b_j b_j^T``, added to the stationary
kernels. The u and v residuals are then one joint GP (a u sample informs v), and a residual
shaped like the modes is recovered far from the samples. This is ensemble optimal
interpolation with a static ensemble (Oke, Allen, Miller, Egbert & Kosro 2002, J. Atmos.
Oceanic Technol. 19: the background covariance of the anomalies of one long model run);
:func:`passt_mav.reconstruction.model_background` makes the modes from the predictor's own
roll-out. The stationary kernels still carry what the modes do not span. The factor on
``B`` is fitted with the other hyper-parameters (``background_scale="ml"``).

Nugget (``nugget="state"``, the default): the WhiteKernel variance fitted above the sensor's
``noise_std**2`` is the field's error at grid scale (what the model got wrong cell by cell, which
a smooth kernel cannot carry), not measurement noise: a sample then corrects its own cell by that
share (a second sample in the cell sees the same error), while the sensor noise alone stays
independent between samples. It is kept only when the samples' likelihood pays for it over the
sensor noise alone (the information criterion's ``0.5 ln n``, one parameter), whether the signal
kernel was kept or not. Between samples in distinct cells the two readings give the same covariance; they
differ at the sampled cells' own estimate (and in the planner's prior: a fresh cell is worth its
nugget). ``nugget="noise"`` is the reading before (everything above the
sensor's variance is noise). (Cressie 1993, Statistics for Spatial Data, sec. 3.2.1: the nugget
effect as micro-scale variation plus measurement error.)

The map's std (``std_calibration="forward"``, the default): the posterior std of the residual is the
GP correction's; the map's also carries the forecast's error that the samples cannot remove. With a
background, a share of its variance stays (``unresolved_share``, estimated from the leg's own held-out
samples: :func:`unresolved_share`); and the std is widened when the leg's own later samples fall outside
it more often than it says, or when the residuals grow over the leg
(:meth:`GPReconstructor.forward_std_factor`, :func:`lead_growth`). Checked against the truth by
:mod:`passt_mav.models.calibration` wherever the truth is known.

Land / missing cells (NaN in the forecast, or ``mask`` False) stay NaN.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import ReconstructionError
from passt_mav.reconstruction import lowrank
from passt_mav.reconstruction.kernels import CrossCovCache, base_kernel, evidence_gate, fit_on_field

__all__ = ["MAX_FIT_POINTS", "GPReconstructor", "unresolved_share"]

_PRIORS = ("forecast", "none")
_KERNELS = ("matern32", "matern52", "rbf")
_SOLVERS = ("sklearn", "cholesky")
_NUGGETS = ("state", "noise")
_STD_CALIBRATIONS = ("forward", "off")
#: ``std_calibration="forward"``: the latest share of a reconstruction's samples held out to check its std
STD_HOLDOUT = 1.0 / 3.0
#: ... done only with at least this many valid samples (a handful says nothing about a variance)
STD_CHECK_MIN_SAMPLES = 12
#: the most the std is widened by
STD_INFLATION_MAX = 5.0
#: samples a hyper-parameter fit sees at most by default (``max_fit_points``; evenly spread along the track)
MAX_FIT_POINTS = 60
#: time length scales a space-time fit tries on its leg's own later samples besides the fitted one, in
#: units of the samples' time span, when shorter than the fitted (:meth:`GPReconstructor._forward_validate_time_scale`)
TIME_SCALE_SPANS = (4.0, 2.0, 1.0, 0.5, 0.25, 0.125)
#: factors on the fitted spatial length scales tried with them (the fitted first)
SPACE_SCALE_FACTORS = (1.0, 0.5, 0.25)
#: forward validation keeps other length scales only when they cut the later samples' squared error to
#: below this share of the fitted ones' (a marginal gain on a handful of samples is noise)
FORWARD_GAIN = 0.8


def lead_growth(t, sq, t_map: float) -> float:
    """How much larger the forecast's error variance is at the map's time ``t_map`` than on average over
    the samples: ``sq`` (n,) the samples' squared residual against the forecast (mean over u, v) at times
    ``t`` (n,); a line ``a + b (t - t_first)`` fitted to them by least squares (``b`` >= 0: a forecast's
    error grows with its lead time, rarely shrinks), and the ratio of the line at ``t_map`` to its mean over
    the samples (>= 1; 1 without a positive slope or a time spread). The residual GP's kernels are
    stationary in time: they give the map the samples' average residual variance, too little when a stale
    background drifts off over the leg (persistence, a model restarted from a poor state)."""
    t = np.asarray(t, np.float64)
    sq = np.asarray(sq, np.float64)
    ok = np.isfinite(t) & np.isfinite(sq)
    t, sq = t[ok], sq[ok]
    if t.size < 3 or np.ptp(t) <= 0:
        return 1.0
    tau = t - t.min()
    A = np.column_stack([np.ones_like(tau), tau])
    (a, b), *_ = np.linalg.lstsq(A, sq, rcond=None)
    mean_fit = float(np.mean(sq))  # = a + b mean(tau) for a least-squares line
    if not (b > 0) or mean_fit <= 0:
        return 1.0
    at_map = a + b * (float(t_map) - float(t.min()))
    return float(max(at_map / mean_fit, 1.0))


def unresolved_share(err, post_var, bvar) -> float | None:
    """The share of the background's variance that a map's std should keep, estimated from samples the map
    had not seen (a method-of-moments estimate; ``None`` when nothing can be said).

    ``err`` (n, 2): held-out samples minus the map's prediction at them (m/s, east/north; u and v);
    ``post_var`` (n, 2): the GP posterior's variance there, without any background share ((m/s)^2; the
    sensor noise included: the variance of one sample); ``bvar`` (n, 2): the background's variance there
    (factor x diag B, (m/s)^2).

    If the map's std were right with a share ``s``, ``E[err^2] = post_var + s bvar``: solved for ``s``
    over all valid (sample, component) pairs at once (a ratio of sums: one cell's ``bvar`` can be ~0) and
    clipped to [0, 1]. Below 0 the posterior was already wide enough there (nothing here narrows a std);
    above 1 more than the background's whole variance went missing, which the forward check's factor
    widens. By hand rather than by a likelihood: one number from a few dozen samples, and the moment
    ratio is unbiased in the variance with no search to tune."""
    e = np.asarray(err, np.float64).reshape(-1, 2)
    pv = np.asarray(post_var, np.float64).reshape(-1, 2)
    bv = np.asarray(bvar, np.float64).reshape(-1, 2)
    ok = np.isfinite(e) & np.isfinite(pv) & np.isfinite(bv) & (bv >= 0)
    den = float(np.sum(bv[ok]))
    if not ok.any() or den <= 0:
        return None
    return float(np.clip((np.sum(e[ok] ** 2) - np.sum(pv[ok])) / den, 0.0, 1.0))


class GPReconstructor:
    """GP reconstruction of a ``(2, rows, cols)`` snapshot (sklearn estimator contract).

    Hyper-parameters (keyword-only, stored unchanged):
        grid_xy: ``(X, Y)`` each ``(rows, cols)`` metres - the cell centres to predict at
            (e.g. ``grid.centres_xy()``). Required.
        kernel: "matern52" (default), "matern32" or "rbf".
        length_scale: initial length scale in metres (default: 3 mean cell sizes);
            bounds are [0.5 cell, min(max_length_cells cells, half the grid's diagonal)].
        max_length_cells: upper bound of the length scale in cells (default 6).
        max_fit_points: at most this many samples (evenly spread) enter a
            hyper-parameter fit (default :data:`MAX_FIT_POINTS`, 60); reconstruction uses all.
        space_time: when sample times are given, the kernel also spans time
            (anisotropic Matern/RBF over east, north, time) and the snapshot is
            predicted at the query time, so a residual seen early in a leg counts
            less than a fresh one when the flow moves on within the leg.
        forward_validation: with a space-time kernel, choose its length scales among the fitted ones and
            shorter ones by how well the leg's earlier samples predict its last third
            (:meth:`_forward_validate_time_scale`; default True).
        max_time_scale: with a space-time kernel, the longest time length scale the GP may keep (field
            time units; None = no cap): a residual is not carried longer than the current itself stays
            correlated (:meth:`~passt_mav.fields.field.FlowField.decorrelation_time`, which
            :class:`~passt_mav.loop.legstep.LegStep` passes by default). Applied after the
            likelihood's fit, before forward validation.
        noise_std: initial sensor-noise std (velocity units) of the WhiteKernel.
        alpha: jitter added to the kernel diagonal (raise it if Cholesky fails).
        prior: "forecast" (GP on residuals vs the forecast) or "none".
        n_restarts: optimizer restarts for the one hyper-parameter fit.
        seed: seed of those restarts.
        solver: "sklearn" (default: a ``GaussianProcessRegressor`` per component and
            leg) or "cholesky" (the same posterior with the fitted kernel held fixed,
            computed directly with scipy's Cholesky and triangular solves: no
            estimator object, no validation, no thread-pool switching per leg; agrees
            with "sklearn" to ~1e-12, tested to 1e-6). The campaign engine uses it.
        background: ``None`` (default) or (m, 2, rows, cols) modes of a low-rank
            background covariance of the residual (field units; NaN = land, taken as 0),
            see the module docstring. With it every reconstruction is one joint u/v
            posterior computed as the "cholesky" solver does (either solver). A sample
            takes the modes' value at its nearest cell centre; the modes do not vary
            over a leg's time.
        background_scale: the factor on ``B``: a number, or "ml" (default): chosen at
            every :meth:`reconstruct` from a log grid (0 and 1e-4 .. 10) by the joint
            marginal likelihood of that call's samples under ``B`` plus the fitted sensor
            noise (type-II maximum likelihood, as for any kernel hyper-parameter; ~10
            Choleskys of the 2n x 2n sample matrix). A residual that is only sensor noise
            then gets a factor ~0, a drift shaped like the modes a large one, whatever
            the stationary kernels' schedule (the model's error grows over a campaign).

        bias: with ``prior="forecast"``, the residual may carry a constant offset over the region
            (one per component: the current sped up or turned as a whole, as a tide does) and a
            rescaling of the forecast's anomaly: factors ``b ~ N(0, s^2)`` on two modes of ones and
            on the anomaly, beside the background's (ordinary kriging's unknown mean, as a prior term
            that a gate can refuse). Each ``s^2`` is chosen at every :meth:`reconstruct` from a log
            grid (and 0) by the samples' joint marginal likelihood under the prior the posterior uses
            (kernels, background, noise), kept only when it gains the information criterion's
            ``0.5 ln(2n)``, and fitted at all only when the samples see half of the region
            (:func:`~passt_mav.reconstruction.lowrank.sample_coverage`: a corner's samples cannot tell
            a local error from a global one). A right forecast keeps ``s^2 = 0``; a stale forecast
            of a field that moved as a whole is shifted everywhere, not only within a length scale
            of the samples. Default False. Modes, fits and gate: :mod:`~passt_mav.reconstruction.lowrank`.

        nugget: "state" (default) or "noise": what the fitted white variance above the sensor's
            ``noise_std**2`` is (see the module docstring).
        std_calibration: "forward" (default) or "off": the std :meth:`reconstruct` returns is the map's
            (with a background, ``unresolved_share`` of its variance kept; widened when the leg's
            later samples fall outside it more often than it says, or its residuals grow over the leg:
            :meth:`forward_std_factor`), or "off" the GP posterior's alone.
        unresolved_share: with a background and ``std_calibration="forward"``, the share of the
            background's variance (factor x diag B, per cell) that stays in the map's std whatever the
            samples say: the modes are the model roll-out's variability, not the error's own structure, so
            samples that pin the modes' amplitudes leave an error off their span that the posterior would
            otherwise drop everywhere at once. "estimate" (default): estimated on every reconstruction from
            the leg's own held-out samples (:meth:`forward_std_factor`, :func:`unresolved_share`; the last
            estimate, or 0 before any, when the check cannot run); or a number in [0, 1] held fixed.

    Learned state: ``kernels_`` (fitted kernel per component), ``nugget_var_`` (per component, the
    state part of the white variance: field units^2, 0 = none), ``cell_m_``,
    ``n_inputs_`` (2 = space, 3 = space-time), ``std_inflation_`` (the factor the last std was
    widened by, 1 = none; ``std_check_``: its record), ``unresolved_share_`` (the last share estimated
    with ``unresolved_share="estimate"``), ``background_scale_`` (the last factor chosen
    with a background and ``background_scale="ml"``), ``bias_var_`` (the last offset variance
    chosen with ``bias``; field units^2).
    """

    def __init__(
        self,
        *,
        grid_xy,
        kernel: str = "matern52",
        length_scale: float | None = None,
        noise_std: float = 0.02,
        alpha: float = 1e-8,
        prior: str = "forecast",
        max_length_cells: float = 6.0,
        max_fit_points: int = MAX_FIT_POINTS,
        space_time: bool = True,
        forward_validation: bool = True,
        max_time_scale: float | None = None,
        n_restarts: int = 0,
        seed: int = 0,
        solver: str = "sklearn",
        background=None,
        background_scale="ml",
        bias: bool = False,
        nugget: str = "state",
        std_calibration: str = "forward",
        unresolved_share="estimate",
    ):
        self.grid_xy = grid_xy
        self.unresolved_share = unresolved_share
        self.nugget = nugget
        self.std_calibration = std_calibration
        self.bias = bias
        self.background = background
        self.background_scale = background_scale
        self.solver = solver
        self.space_time = space_time
        self.forward_validation = forward_validation
        self.max_time_scale = max_time_scale
        self.max_fit_points = max_fit_points
        self.max_length_cells = max_length_cells
        self.kernel = kernel
        self.length_scale = length_scale
        self.noise_std = noise_std
        self.alpha = alpha
        self.prior = prior
        self.n_restarts = n_restarts
        self.seed = seed

    # -- validation -------------------------------------------------------------
    def grid_coords(self) -> tuple[np.ndarray, np.ndarray]:
        """(X, Y): the grid's cell-centre east and north coordinates, each (rows, cols) float64 (local metres)."""
        X, Y = (np.asarray(a, dtype=np.float64) for a in self.grid_xy)
        if X.shape != Y.shape or X.ndim != 2:
            raise ReconstructionError(f"grid_xy must be two (rows, cols) arrays, got {X.shape} and {Y.shape}")
        return X, Y

    def _check(self, samples_xy, samples_uv, forecast_at_samples, samples_t=None, *, with_mask: bool = False):
        if self.prior not in _PRIORS:
            raise ReconstructionError(f"unknown GP prior {self.prior!r}; choose one of {', '.join(_PRIORS)}")
        if self.kernel not in _KERNELS:
            raise ReconstructionError(f"unknown GP kernel {self.kernel!r}; choose one of {', '.join(_KERNELS)}")
        if getattr(self, "nugget", "noise") not in _NUGGETS:
            raise ReconstructionError(f"unknown GP nugget {self.nugget!r}; choose one of {', '.join(_NUGGETS)}")
        xy = np.asarray(samples_xy, dtype=np.float64).reshape(-1, 2)
        uv = np.asarray(samples_uv, dtype=np.float64).reshape(-1, 2)
        if xy.shape != uv.shape:
            raise ReconstructionError(f"{len(xy)} sample positions for {len(uv)} velocity samples")
        fa = None
        if self.prior == "forecast":
            if forecast_at_samples is None:
                raise ReconstructionError(
                    "prior='forecast' needs the forecast at the sample positions (forecast_at_samples)"
                )
            fa = np.asarray(forecast_at_samples, dtype=np.float64).reshape(-1, 2)
            if fa.shape != uv.shape:
                raise ReconstructionError("forecast_at_samples must have one (u, v) per sample")
        if samples_t is not None:
            t = np.asarray(samples_t, dtype=np.float64).reshape(-1)
            if t.size != len(xy):
                raise ReconstructionError(f"{t.size} sample times for {len(xy)} samples")
            xy = np.column_stack([xy, t])
        ok = np.isfinite(xy).all(1) & np.isfinite(uv).all(1)
        if fa is not None:
            ok &= np.isfinite(fa).all(1)
        if ok.sum() < 2:
            raise ReconstructionError(f"need at least 2 valid samples to reconstruct, got {int(ok.sum())}")
        target = uv[ok] - (fa[ok] if fa is not None else 0.0)
        return (xy[ok], target, ok) if with_mask else (xy[ok], target)

    @staticmethod
    def _nearest_cells(xy, X, Y) -> np.ndarray:
        """Flat index of the nearest cell centre of each (east, north) position in ``xy`` (n, 2)."""
        d2 = (xy[:, 0, None] - X.ravel()[None]) ** 2 + (xy[:, 1, None] - Y.ravel()[None]) ** 2
        return np.argmin(d2, axis=1)

    def start_kernel(self, t_span: float | None = None):
        """The kernel a fit starts from and the cell size (metres): see
        :func:`~passt_mav.reconstruction.kernels.base_kernel`."""
        X, Y = self.grid_coords()
        return base_kernel(X, Y, self.kernel, self.length_scale, self.max_length_cells, self.noise_std, t_span)

    def _regressor(self, kernel, optimize: bool):
        from sklearn.gaussian_process import GaussianProcessRegressor

        return GaussianProcessRegressor(
            kernel=kernel,
            alpha=float(self.alpha),
            optimizer="fmin_l_bfgs_b" if optimize else None,
            n_restarts_optimizer=int(self.n_restarts) if optimize else 0,
            # kernels stay in physical units: the caller removes the prior mean itself
            normalize_y=False,
            random_state=int(self.seed),
        )

    def fit_regressor(self, kernel, xy, y, optimize: bool):
        from threadpoolctl import threadpool_limits

        try:
            # one BLAS thread: these matrices are small (n <= a few hundred) and a
            # multi-threaded BLAS on a busy machine was measured 25x slower (290 vs 11 ms
            # per hyper-parameter fit of 51 samples on 2 shared cores)
            with threadpool_limits(1):
                return self._regressor(kernel, optimize).fit(xy, y)
        except np.linalg.LinAlgError as exc:
            raise ReconstructionError(
                f"GP fit failed (Cholesky: {exc}); increase the noise level: alpha (now {self.alpha:g}) or noise_std"
            ) from None
        except ValueError as exc:
            if "alpha" in str(exc) or "positive definite" in str(exc):
                raise ReconstructionError(
                    f"GP fit failed ({str(exc).splitlines()[0]}); increase the noise level: alpha (now {self.alpha:g}) or noise_std"
                ) from None
            raise

    def _posterior_fixed(
        self, kernel, xy, y, grid_pts, with_std: bool = True, comp: int = 0
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Posterior mean and std at ``grid_pts`` for a fixed kernel, as sklearn computes them.

        Same algebra as ``GaussianProcessRegressor(optimizer=None, normalize_y=False)``:
        ``K = k(X) + alpha I`` (k's WhiteKernel adds the noise on the diagonal),
        ``L = chol(K)``, mean ``k(X*, X) K^-1 y``, variance ``k.diag(X*) - |L^-1 k(X, X*)|^2``
        clipped at 0 (sklearn clips negative variances the same way). ``k(X*, X)``
        comes from the column cache of component ``comp`` (:meth:`cross_cov`, the
        same numbers). ``with_std=False`` skips the variance (returns ``(mean, None)``).
        """
        from scipy.linalg import cho_solve, solve_triangular

        K = kernel(xy)
        K[np.diag_indices_from(K)] += float(self.alpha)
        Lc = lowrank.cholesky_or_error(K, self.alpha)
        a = cho_solve((Lc, True), y, check_finite=False)
        Ks = self.cross_cov(comp, kernel, xy, grid_pts)
        mean = Ks @ a
        if not with_std:
            return mean, None
        V = solve_triangular(Lc, Ks.T, lower=True, check_finite=False)
        var = kernel.diag(grid_pts) - np.einsum("ij,ij->j", V, V)
        return mean, np.sqrt(np.maximum(var, 0.0))

    def cross_cov(self, comp: int, kernel, xy: np.ndarray, grid_pts: np.ndarray) -> np.ndarray:
        """``kernel(grid_pts, xy)`` ((n_cells, n) float64), its columns cached by sample position
        (:class:`~passt_mav.reconstruction.kernels.CrossCovCache`, one per reconstructor)."""
        if getattr(self, "_col_cache", None) is None:
            self._col_cache = CrossCovCache()
        return self._col_cache(comp, kernel, xy, grid_pts)

    # -- public -----------------------------------------------------------------
    def _inputs(self, xy, samples_t, n_ok_mask=None):
        if samples_t is None or not self.space_time:
            return xy, None
        t = np.asarray(samples_t, dtype=np.float64).reshape(-1)
        span = float(np.ptp(t)) if t.size else 0.0
        return np.column_stack([xy, t]), (span if span > 0 else None)

    def fit(self, samples_xy, samples_uv, forecast_at_samples=None, *, samples_t=None) -> GPReconstructor:
        """Fit the kernel hyper-parameters (marginal likelihood) on one set of samples.

        samples_xy: (n, 2) east/north metres; samples_uv: (n, 2) u/v;
        forecast_at_samples: (n, 2), required for ``prior="forecast"``;
        samples_t: (n,) sample times (field time units) for a space-time kernel.
        """
        import warnings

        xy, target = self._check(samples_xy, samples_uv, forecast_at_samples, samples_t)
        xy, t_span = self._inputs(xy[:, :2], xy[:, 2] if xy.shape[1] == 3 else None)
        if t_span is None:
            xy = xy[:, :2]
        if self.prior == "none":
            target = target - target.mean(axis=0)
        if len(xy) > int(self.max_fit_points):
            # hyper-parameters from an evenly spread subset (in sample order = along the
            # track): the likelihood's gradient costs O(n^3) per iteration, and 60 points
            # pin three hyper-parameters well; the reconstruction still uses every sample
            keep = np.unique(np.linspace(0, len(xy) - 1, int(self.max_fit_points)).round().astype(int))
            xy, target = xy[keep], target[keep]
        base, cell = self.start_kernel(t_span)
        kernels = []
        with warnings.catch_warnings():
            # a length scale at its bound is a legitimate answer for a smooth residual
            warnings.simplefilter("ignore", category=UserWarning)
            from sklearn.exceptions import ConvergenceWarning

            warnings.simplefilter("ignore", category=ConvergenceWarning)
            prev = getattr(self, "kernels_", None)
            for k in range(2):
                # Start the signal variance at the targets' own variance (a residual that
                # was ~0 on the first leg must not leave it stuck at its lower bound) and
                # the length scale at the last fit's (fewer iterations when re-fitting).
                init = base.clone_with_theta(base.theta)
                init.set_params(k1__k1__constant_value=float(np.clip(np.var(target[:, k]), 1e-6, 1e2)))
                if prev is not None and np.size(prev[k].k1.k2.length_scale) == np.size(init.k1.k2.length_scale):
                    init.set_params(k1__k2__length_scale=prev[k].k1.k2.length_scale)
                gp = self.fit_regressor(init, xy, target[:, k], optimize=True)
                kernels.append(self._evidence_gate(gp, target[:, k], k))
        self.kernels_ = kernels
        self.cell_m_ = cell
        self.n_inputs_ = xy.shape[1]
        self.time_scale_factor_ = [1.0, 1.0]
        self.space_scale_factor_ = [1.0, 1.0]
        if self.n_inputs_ == 3:
            self._cap_time_scale()
        if self.n_inputs_ == 3 and self.forward_validation:
            self._forward_validate_time_scale(xy, target)
        return self

    fit_hyperparameters = fit

    def _cap_time_scale(self) -> None:
        """Shorten each space-time kernel's time length scale to :attr:`max_time_scale` (field time
        units) where it is longer. Along one track the likelihood cannot tell a residual that changes in
        time from one that changes in space, and often takes it as steady for days; the cap is the prior
        that a forecast's error does not stay correlated longer than the current itself does.
        Records ``time_scale_capped_`` per component (True where the cap acted)."""
        self.time_scale_capped_ = [False, False]
        cap = self.max_time_scale
        if cap is None or not np.isfinite(cap) or cap <= 0:
            return
        for k, kern in enumerate(self.kernels_):
            ls = np.array(kern.k1.k2.length_scale, float)
            if ls.size == 3 and ls[2] > cap:
                ls[2] = float(cap)
                kern.set_params(k1__k2__length_scale=ls)
                self.time_scale_capped_[k] = True

    def _forward_validate_time_scale(self, xyt: np.ndarray, target: np.ndarray) -> None:
        """Shorten each space-time kernel's time length scale when the leg's own samples say that an
        older residual does not carry forward: the samples of the leg's last third (in time) are
        predicted from the earlier ones (the fitted kernel held fixed, its time length scale the
        fitted one or each of :data:`TIME_SCALE_SPANS` times the samples' time span that is shorter)
        and the length scales with the smallest squared error are kept (the longest on a tie) when they
        cut it below :data:`FORWARD_GAIN` of the fitted ones'. A residual seen early in a leg is applied at the leg's end through
        this length scale; along a track, space and time are confounded and the likelihood often
        takes the residual as steady (hours to months where a tide turns it in six hours), so the
        hyper-parameter is chosen here by how well it forecasts the leg's own later samples (forward
        validation, as for a time series). ``xyt``: (n, 3) east, north (m), time; ``target``: (n, 2)
        residuals. Records ``time_scale_factor_`` per component (kept / fitted time length scale; 1 =
        the likelihood's)."""
        t = xyt[:, 2]
        span = float(np.ptp(t))
        if span <= 0:
            return
        late = t >= t.min() + span * (2.0 / 3.0)
        if late.sum() < 3 or (~late).sum() < 3:
            return
        for k, kern in enumerate(self.kernels_):
            ls = np.asarray(kern.k1.k2.length_scale, float)
            if ls.size != 3:
                continue
            scales = [ls[2]] + [span * f for f in TIME_SCALE_SPANS if span * f < ls[2]]
            cands = [np.array([ls[0] * g, ls[1] * g, lt]) for g in SPACE_SCALE_FACTORS for lt in scales]
            errs = []
            for c in cands:
                kk = kern.clone_with_theta(kern.theta)
                kk.set_params(k1__k2__length_scale=c)
                K = kk(xyt[~late]) + self.alpha * np.eye(int((~late).sum()))
                pred = kk(xyt[late], xyt[~late]) @ np.linalg.solve(K, target[~late, k])
                errs.append(float(np.sum((target[late, k] - pred) ** 2)))
            best = int(np.argmin(errs))  # the first (the fitted, then the longest) on a tie
            if best and errs[best] < FORWARD_GAIN * errs[0]:  # only a clear gain moves off the likelihood's
                kern.set_params(k1__k2__length_scale=cands[best])
                self.time_scale_factor_[k] = float(cands[best][2] / ls[2])
                self.space_scale_factor_[k] = float(cands[best][0] / ls[0])

    def innovation_loglik(self, samples_xy, residual_uv, *, samples_t=None, modes: bool = True) -> float:
        """Log density (nats, up to a constant shared by every residual at these positions) of
        residuals ``residual_uv`` (n, 2; m/s east/north) at ``samples_xy`` (n, 2 metres) under
        this GP's own prior covariance as it stands: the fitted kernels of u and v (sensor
        noise included; the initial kernels before any fit, scaled as :meth:`prior_factors`
        scales them) plus the background modes times the factor in use, u and v jointly.
        ``-0.5 r^T K^-1 r`` with ``K = L L^T``; the ``log |K|`` term is the same for every
        forecast scored at the same samples and is left out. How well a forecast explains a
        leg's samples, before the GP adapts to them: the score of
        :class:`passt_mav.loop.passt.PasstLoop`'s prior weighting. ``samples_t``: sample times for a
        space-time kernel (only their differences matter). ``modes=False``: the stationary kernels
        and the noise alone, without the background and offset modes (how the loop scores its
        candidate priors, see ``PasstLoop(prior_blend=...)``)."""
        X, Y = self.grid_coords()
        xy = np.asarray(samples_xy, dtype=np.float64).reshape(-1, 2)
        r = np.asarray(residual_uv, dtype=np.float64).reshape(-1, 2)
        n = len(xy)
        Bg = self.background_modes(X.shape) * np.sqrt(self.background_factor()) if self.background is not None else None
        kernels, fitted = self.prior_kernels(Bg)
        Bg = self.with_offset_modes(Bg, X.size) if modes else None
        if not fitted:
            inputs = xy
        else:
            use_t = getattr(self, "n_inputs_", 2) == 3 and samples_t is not None
            inputs = np.column_stack([xy, np.asarray(samples_t, dtype=np.float64).reshape(-1)]) if use_t else xy
            if getattr(self, "n_inputs_", 2) == 3 and not use_t:
                inputs = np.column_stack([xy, np.zeros(n)])
        nug = self.nugget_vars() if fitted else np.zeros(2)
        cells = self._nearest_cells(xy, X, Y) if Bg is not None or nug.any() else None
        if nug.any():
            kernels, Bg = self.with_cell_nugget(kernels, Bg, cells, nug, X.size)
        return lowrank.innovation_quadratic(kernels, inputs, Bg, cells, r, self.alpha)

    def _evidence_gate(self, gp, y, comp: int):
        """The fitted kernel of component ``comp``, or the kernel with its signal switched off when
        the samples show no signal beyond the sensor noise (:func:`~passt_mav.reconstruction.kernels.evidence_gate`).
        Records ``evidence_[comp]`` = (likelihood gain, penalty)."""
        kernel, evidence = evidence_gate(gp, y, self.noise_std)
        ev = getattr(self, "evidence_", None) or [None, None]
        ev[comp] = evidence
        self.evidence_ = ev
        nug = list(getattr(self, "nugget_var_", None) or [0.0, 0.0])
        nug[comp] = self._state_nugget(gp, kernel, y)
        self.nugget_var_ = nug
        return kernel

    def _state_nugget(self, gp, kernel, y) -> float:
        """The part of ``kernel``'s white variance above the sensor's that is the field's grid-scale
        error (``nugget="state"``): the excess, when the log marginal likelihood of the fitted ``gp``
        beats the same kernel with the sensor's variance alone by 0.5 ln n; else 0."""
        if getattr(self, "nugget", "noise") != "state":
            return 0.0
        s2 = max(float(self.noise_std) ** 2, 1e-10)
        excess = float(kernel.k2.noise_level) - s2
        if excess <= 1e-12 * s2:
            return 0.0
        n = np.size(y)
        if kernel is gp.kernel_:  # the fitted kernel, against itself with the sensor's variance
            k_s = kernel.clone_with_theta(kernel.theta)
            k_s.set_params(k2__noise_level=s2)
            try:
                gain = float(gp.log_marginal_likelihood_value_) - float(gp.log_marginal_likelihood(k_s.theta))
            except (np.linalg.LinAlgError, ValueError):
                return excess
        else:  # no signal kept: white noise of the residuals' variance against the sensor's
            ms, v = float(np.mean(np.square(y))), s2 + excess
            gain = -0.5 * n * (np.log(v / s2) + ms / v - ms / s2)
        return excess if gain >= 0.5 * np.log(max(n, 2)) else 0.0

    def nugget_vars(self) -> np.ndarray:
        """(2,) the state nugget of u and v in use (field units^2; zeros before a fit or with
        ``nugget="noise"``)."""
        nug = getattr(self, "nugget_var_", None)
        if nug is None or not hasattr(self, "kernels_") or getattr(self, "nugget", "noise") != "state":
            return np.zeros(2)
        return np.asarray(nug, dtype=np.float64)

    @staticmethod
    def with_cell_nugget(kernels, Bg, cells, nug, N: int):
        """The prior with the state nugget ``nug`` (2,) in place: ``kernels`` with it taken out of their
        white variance (the sensor's part stays), and ``Bg`` (m, 2, N) or None with one mode per
        sampled cell appended (:func:`~passt_mav.reconstruction.lowrank.cell_modes`: samples in one
        cell share it). Returns (kernels, modes)."""
        out = []
        for k, v in zip(kernels, nug):
            if v > 0:
                k = k.clone_with_theta(k.theta)
                k.set_params(k2__noise_level=max(float(k.k2.noise_level) - float(v), 1e-10))
            out.append(k)
        ind = lowrank.cell_modes(cells, nug, N)
        return out, (ind if Bg is None else np.concatenate([Bg, ind]))

    #: candidate factors on the background covariance for ``background_scale="ml"``
    BACKGROUND_SCALES = (0.0,) + tuple(float(x) for x in np.logspace(-4, 1, 11))

    def fit_background_scale(self, target, cells, Bg) -> float:
        """The factor in :data:`BACKGROUND_SCALES` that maximises the joint log marginal likelihood
        of the samples' targets (n, 2) (u and v; zero-mean) under factor x ``B`` + the fitted
        sensor noise; ``cells``: each sample's flat cell index, ``Bg``: (m, 2, R*C) modes.
        The modes are weighed against the sensor noise alone: how much of the residual do they
        explain? (with the stationary kernels included, a fitted stationary kernel has already
        taken a smooth drift's variance and the likelihood then under-weights the modes; a factor
        fixed at 1 spoils a leg where the model is right)."""
        return lowrank.gp_mode_variance(self, target, cells, np.zeros((0,) + Bg.shape[1:]), Bg, self.BACKGROUND_SCALES)

    def background_factor(self) -> float:
        """The factor on the background covariance now in use (see ``background_scale``)."""
        if self.background_scale == "ml":
            return float(getattr(self, "background_scale_", 1.0))
        try:
            f = float(self.background_scale)
        except (TypeError, ValueError):
            raise ReconstructionError(
                f"background_scale must be a number >= 0 or 'ml', got {self.background_scale!r}"
            ) from None
        if not f >= 0:
            raise ReconstructionError(f"background_scale must be a number >= 0 or 'ml', got {self.background_scale!r}")
        return f

    #: the stationary kernels' low-rank part for :meth:`prior_factors`: at most this many
    #: eigenpairs per component, fewer when they already carry ``PRIOR_KERNEL_ENERGY`` of the
    #: kernel's trace (a Matern of 3 cells on 30 x 30 needs ~100 for 95 %; the rest stays exact
    #: on the diagonal, see :meth:`prior_factors`)
    PRIOR_KERNEL_RANK = 48
    PRIOR_KERNEL_ENERGY = 0.95

    def prior_kernels(self, Bg) -> tuple[list, bool]:
        """(the fitted kernels of u and v, True), or before any fit (the initial kernel: length scale
        3 cells, noise ``noise_std``, signal variance = the background's mean variance in ``Bg``
        (m, 2, N), or ``noise_std**2`` without one; False)."""
        from sklearn.gaussian_process.kernels import ConstantKernel, WhiteKernel

        kernels = getattr(self, "kernels_", None)
        if kernels is not None:
            return kernels, True
        base, _ = self.start_kernel()
        amp = float(np.mean(np.sum(Bg**2, axis=0))) if Bg is not None and Bg.size else 0.0
        amp = amp if amp > 0 else max(float(self.noise_std) ** 2, 1e-10)
        k = ConstantKernel(amp, "fixed") * base.k1.k2 + WhiteKernel(max(float(self.noise_std) ** 2, 1e-10), "fixed")
        return [k, k], False

    def prior_factors(
        self,
        land=None,
        *,
        kernel_rank: int | None = None,
        kernel_energy: float | None = None,
        with_mode_count: bool = False,
    ):
        """The prior covariance of the next reconstruction's error over the grid, factored:
        ``(F (2N, r), d (2N,), noise (2N,))`` with ``Sigma = F F^T + diag(d)`` (field velocity units
        squared; land rows 0); see :func:`passt_mav.reconstruction.lowrank.prior_factors`."""
        return lowrank.prior_factors(
            self, land, kernel_rank=kernel_rank, kernel_energy=kernel_energy, with_mode_count=with_mode_count
        )

    def fit_field(self, snapshot, *, max_points: int = 150) -> GPReconstructor:
        """Fit the signal variance and length scale on a gridded snapshot ``(2, R, C)``: the preferred
        once-per-campaign fit (:func:`passt_mav.reconstruction.kernels.fit_on_field`)."""
        self.kernels_, self.cell_m_ = fit_on_field(self, snapshot, max_points)
        self.n_inputs_ = 2
        self.nugget_var_ = None
        return self

    def reconstruct(
        self,
        samples_xy,
        samples_uv,
        forecast=None,
        *,
        forecast_at_samples=None,
        mask=None,
        samples_t=None,
        t=None,
        with_std: bool = True,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Posterior mean and std on the grid, with the fitted kernels held fixed.

        forecast: (2, rows, cols) prior mean on the grid (required for
        ``prior="forecast"``; NaN there = land). ``forecast_at_samples`` (n, 2):
        the forecast at each sample's position and time; if omitted it is taken
        from ``forecast`` at the nearest cell centre. mask: (rows, cols) bool,
        True = water (optional). Fits the hyper-parameters first if :meth:`fit`
        was never called. ``samples_t`` (n,) and ``t`` (the snapshot's time) switch on
        the space-time kernel (see ``space_time``). Returns ``(mean (2, R, C)
        float32, std (2, R, C) float32)``; with ``with_std=False`` (cholesky solver
        only) the std is not computed and ``None`` is returned in its place (its triangular
        solve against every grid cell is most of a leg's GP time; only a std reward reads it).
        """
        factor = 1.0
        cal = getattr(self, "std_calibration", "off")
        if cal not in _STD_CALIBRATIONS:
            raise ReconstructionError(
                f"unknown GP std_calibration {cal!r}; choose one of {', '.join(_STD_CALIBRATIONS)}"
            )
        if cal == "forward":
            self.share_in_use()  # a bad unresolved_share fails here, before any work
        if with_std and cal == "forward":
            factor = self.forward_std_factor(
                samples_xy,
                samples_uv,
                forecast,
                forecast_at_samples=forecast_at_samples,
                mask=mask,
                samples_t=samples_t,
                t=t,
            )
        mean, std = self._reconstruct(
            samples_xy, samples_uv, forecast, forecast_at_samples, mask, samples_t, t, with_std
        )
        if std is not None and cal == "forward":
            std = self._map_std(std, factor)
        elif std is not None and factor != 1.0:
            std = (std * np.float32(factor)).astype(np.float32)
        return mean, std

    def share_in_use(self) -> float:
        """The share of the background's variance the map's std keeps (dimensionless, [0, 1]): the fixed
        ``unresolved_share``, or with "estimate" the last :meth:`forward_std_factor` estimate (0 before one)."""
        u = getattr(self, "unresolved_share", "estimate")
        if u == "estimate":
            return float(getattr(self, "unresolved_share_", 0.0))
        try:
            f = float(u)
        except (TypeError, ValueError):
            f = np.nan
        if not 0.0 <= f <= 1.0:
            raise ReconstructionError(f"unresolved_share must be 'estimate' or a number in [0, 1], got {u!r}")
        return f

    def _map_std(self, std, factor: float):
        """The map's std (2, R, C) float32 (m/s) from the GP posterior's ``std``: with a background,
        :meth:`share_in_use` of its variance added back (:meth:`background_var`), then times ``factor``."""
        var = np.square(std, dtype=np.float64)
        if self.background is not None:
            var = var + self.share_in_use() * self.background_var().reshape(var.shape)
        return (np.sqrt(var) * float(factor)).astype(np.float32)

    def background_var(self) -> np.ndarray:
        """(2, R*C) float64: the background's variance per component and cell, factor x diag B ((m/s)^2)."""
        X, _ = self.grid_coords()
        return self.background_factor() * np.sum(self.background_modes(X.shape) ** 2, axis=0)

    def forward_std_factor(
        self, samples_xy, samples_uv, forecast=None, *, forecast_at_samples=None, mask=None, samples_t=None, t=None
    ) -> float:
        """The factor (>= 1) :meth:`reconstruct` widens its std by: the map's std checked against data it has.

        The latest :data:`STD_HOLDOUT` of the samples (by time; by order without times) are held out; the
        earlier ones reconstruct the field, at the held-out samples' median time, with the kernels as they
        stand; each held-out residual (sample minus prior) is then compared with the predicted residual at
        its cell, in units of the predicted std there (which carries the sensor noise and the state nugget:
        the std of one sample). The RMS of those standardised errors ``z_rms`` is ~1 when the std is right;
        above 1 the GP is overconfident where it extrapolates (a nugget or background that its
        samples had collapsed, a time scale too long, a forecast error larger away from the samples) and the
        factor is ``z_rms``; below 1 the std is left alone (a std the check finds too wide is not narrowed on
        a few dozen samples). With a forecast prior and sample times, the factor is at least the square root
        of :func:`lead_growth` (the residuals' variance growing over the leg, extrapolated to the map's time
        ``t``). At most :data:`STD_INFLATION_MAX`. Never reads the truth. 1 with fewer than
        :data:`STD_CHECK_MIN_SAMPLES` valid samples or when the check cannot be computed. With a background,
        the same held-out errors first estimate the share of its variance the map keeps (``unresolved_share``,
        :meth:`_held_out_factor`), and ``z_rms`` is taken with it. Records ``std_inflation_`` and ``std_check_``
        (``z_rms``, ``n`` held-out samples, ``lead_growth``, with a background ``unresolved_share``)."""
        self.std_inflation_, self.std_check_ = 1.0, None
        X, Y = self.grid_coords()
        try:
            fc, _, f_at = self._prior_mean(samples_xy, forecast, forecast_at_samples, mask)
            if not hasattr(self, "kernels_"):
                self.fit(samples_xy, samples_uv, f_at, samples_t=samples_t)
            xy = np.asarray(samples_xy, np.float64).reshape(-1, 2)
            uv = np.asarray(samples_uv, np.float64).reshape(-1, 2)
            fa = None if f_at is None else np.asarray(f_at, np.float64).reshape(-1, 2)
            use_t = getattr(self, "n_inputs_", 2) == 3 and samples_t is not None and t is not None
            st = None if samples_t is None else np.asarray(samples_t, np.float64).reshape(-1)
            ok = np.isfinite(xy).all(1) & np.isfinite(uv).all(1)
            if fa is not None:
                ok &= np.isfinite(fa).all(1)
            if st is not None:
                ok &= np.isfinite(st)
            idx = np.flatnonzero(ok)
            if idx.size < STD_CHECK_MIN_SAMPLES:
                return 1.0
            if st is not None:
                idx = idx[np.argsort(st[idx], kind="stable")]
            n_late = max(int(np.ceil(idx.size * STD_HOLDOUT)), 2)
            early, late = idx[:-n_late], idx[-n_late:]
            t_q = float(np.median(st[late])) if use_t else t
            fa_early, st_early = None if fa is None else fa[early], st[early] if use_t else None
            mean, std = self._reconstruct(xy[early], uv[early], forecast, fa_early, mask, st_early, t_q, True)
        except (ReconstructionError, np.linalg.LinAlgError, ValueError):
            return 1.0
        cells = self._nearest_cells(xy[late], X, Y)
        pred = mean.reshape(2, -1)[:, cells].T.astype(np.float64)
        sd = std.reshape(2, -1)[:, cells].T.astype(np.float64)
        obs = uv[late]
        if self.prior == "forecast":  # residuals: the held-out samples against their own forecast
            pred = pred - fc.reshape(2, -1)[:, cells].T
            obs = obs - fa[late]
        growth = 1.0
        if self.prior == "forecast" and use_t:
            growth = lead_growth(st[idx], np.sum((uv[idx] - fa[idx]) ** 2, axis=1) / 2.0, float(t))
        return self._held_out_factor(obs - pred, sd, cells, growth)

    def _held_out_factor(self, err, sd, cells, growth: float) -> float:
        """:meth:`forward_std_factor`'s verdict from the held-out errors ``err`` (n, 2; m/s), the posterior
        std ``sd`` (n, 2; m/s) of the map made without them at their ``cells`` (n,) and the lead growth.
        With a background and ``unresolved_share="estimate"``, first the share of the background's variance
        those errors say the map should keep (:func:`unresolved_share`; set as ``unresolved_share_``),
        taken into their std before ``z_rms`` (the factor then widens only what the share did not cover)."""
        var = sd**2
        if self.background is not None:
            bvar = self.background_var()[:, cells].T
            if getattr(self, "unresolved_share", "estimate") == "estimate":
                share = unresolved_share(err, var, bvar)
                if share is not None:
                    self.unresolved_share_ = share
            var = var + self.share_in_use() * bvar
        z = err / np.sqrt(var)
        z = z[np.isfinite(z) & (var > 0)]
        if z.size < 2:
            return 1.0
        zr = float(np.sqrt(np.mean(z**2)))
        self.std_check_ = {"z_rms": zr, "n": int(len(cells)), "lead_growth": growth}
        if self.background is not None:
            self.std_check_["unresolved_share"] = self.share_in_use()
        self.std_inflation_ = float(min(max(zr, np.sqrt(growth), 1.0), STD_INFLATION_MAX))
        return self.std_inflation_

    def _reconstruct(self, samples_xy, samples_uv, forecast, forecast_at_samples, mask, samples_t, t, with_std):
        """:meth:`reconstruct` without the std's forward check."""
        X, Y = self.grid_coords()
        fc, land, forecast_at_samples = self._prior_mean(samples_xy, forecast, forecast_at_samples, mask)
        if not hasattr(self, "kernels_"):
            self.fit(samples_xy, samples_uv, forecast_at_samples, samples_t=samples_t)
        use_t = getattr(self, "n_inputs_", 2) == 3
        if use_t and (samples_t is None or t is None):
            raise ReconstructionError("this GP was fitted over space and time: pass samples_t and t")
        xy, target, ok = self._check(
            samples_xy, samples_uv, forecast_at_samples, samples_t if use_t else None, with_mask=True
        )
        offset = np.zeros(2) if self.prior == "forecast" else target.mean(axis=0)  # constant prior mean
        target = target - offset
        if use_t:
            # time measured from the reconstructed snapshot (the kernel is stationary):
            # samples at the same offset from it then share cached covariance columns
            xy = np.column_stack([xy[:, :2], xy[:, 2] - float(t)])
        grid_pts = np.column_stack([X.ravel(), Y.ravel()] + ([np.zeros(X.size)] if use_t else []))
        if self.solver not in _SOLVERS:
            raise ReconstructionError(f"unknown GP solver {self.solver!r}; choose one of {', '.join(_SOLVERS)}")
        modes, nug = None, self.nugget_vars()
        with_modes = self.background is not None or self.bias_on()
        if with_modes or nug.any():
            cells = self._nearest_cells(np.asarray(samples_xy, dtype=np.float64).reshape(-1, 2)[ok], X, Y)
            modes = lowrank.fit_prior_modes(self, target, cells, X.shape, fc, xy) if with_modes else None
            if modes is None and nug.any():  # the joint posterior carries the nugget's cell modes
                modes = np.zeros((0, 2, X.size))
        if modes is not None:
            mean, std = lowrank.joint_posterior(self, xy, target, grid_pts, cells, modes, with_std, nugget=nug)
            mean = mean + offset[:, None, None]
        else:
            mean, std = self._posterior_components(xy, target, offset, grid_pts, X.shape, with_std)
        if self.prior == "forecast":
            mean = mean + fc
        mean[:, land] = np.nan
        if std is None:
            return mean.astype(np.float32), None
        std[:, land] = np.nan
        return mean.astype(np.float32), std.astype(np.float32)

    def _prior_mean(self, samples_xy, forecast, forecast_at_samples, mask):
        """The forecast (2, R, C) float64 or None, the land mask (R, C; ``mask`` False or a NaN
        forecast) and the forecast at the samples (n, 2; from the nearest cell centre when not
        given) of a :meth:`reconstruct` call."""
        X, Y = self.grid_coords()
        land = np.zeros(X.shape, bool)
        if mask is not None:
            land |= ~np.asarray(mask, bool)
        fc = None
        if forecast is not None:
            fc = np.asarray(forecast, dtype=np.float64)
            if fc.shape != (2,) + X.shape:
                raise ReconstructionError(f"forecast must have shape {(2,) + X.shape}, got {fc.shape}")
            land |= ~np.isfinite(fc).all(axis=0)
        if self.prior == "forecast":
            if fc is None:
                raise ReconstructionError("prior='forecast' needs the forecast field (forecast=...)")
            if forecast_at_samples is None:
                idx = self._nearest_cells(np.asarray(samples_xy, dtype=np.float64).reshape(-1, 2), X, Y)
                forecast_at_samples = fc.reshape(2, -1)[:, idx].T
        return fc, land, forecast_at_samples

    def _posterior_components(self, xy, target, offset, grid_pts, shape, with_std: bool):
        """Independent u and v posteriors (no background): mean (2, R, C) and std or None."""
        mean = np.empty((2,) + shape)
        with_std = bool(with_std) or self.solver != "cholesky"
        std = np.empty((2,) + shape) if with_std else None
        for k in range(2):
            if self.solver == "cholesky":
                m, s = self._posterior_fixed(self.kernels_[k], xy, target[:, k], grid_pts, with_std=with_std, comp=k)
            else:
                gp = self.fit_regressor(self.kernels_[k], xy, target[:, k], optimize=False)
                from threadpoolctl import threadpool_limits

                with threadpool_limits(1):
                    m, s = gp.predict(grid_pts, return_std=True)
            mean[k] = m.reshape(shape) + offset[k]
            if with_std:
                std[k] = s.reshape(shape)
        return mean, std

    def bias_on(self) -> bool:
        """Whether the ``bias`` fits run: ``bias`` set and the prior is the forecast (residual GP)."""
        return bool(getattr(self, "bias", False)) and self.prior == "forecast"

    #: variances tried by the ``bias`` fits, as multiples of a reference variance (the offset:
    #: the residuals' mean square; the forecast-anomaly factor: 1)
    BIAS_FRACTIONS = tuple(float(x) for x in np.logspace(-2, 1, 10))

    def bias_candidates(self, v0: float) -> tuple[float, ...]:
        """The variances a ``bias`` fit tries: 0, then ``v0`` x :data:`BIAS_FRACTIONS`."""
        return (0.0,) + tuple(v0 * f for f in self.BIAS_FRACTIONS)

    def with_offset_modes(self, Bg, N: int, water=None):
        """``Bg`` (m, 2, N) or None, with the offset modes of the last ``bias`` fit appended (when one
        was kept after a fit): the prior as the next reconstruction will start it."""
        var = float(getattr(self, "bias_var_", 0.0)) if self.bias_on() and hasattr(self, "kernels_") else 0.0
        if var <= 0:
            return Bg
        Bb = lowrank.offset_modes(N, water) * np.sqrt(var)
        return Bb if Bg is None else np.concatenate([Bg, Bb])

    def background_modes(self, shape) -> np.ndarray:
        """The background modes as (m, 2, R*C) float64, land (NaN) as 0."""
        b = np.asarray(self.background, dtype=np.float64)
        if b.ndim != 4 or b.shape[1:] != (2,) + tuple(shape):
            raise ReconstructionError(f"background modes must have shape (m, 2, {shape[0]}, {shape[1]}), got {b.shape}")
        return np.nan_to_num(b, nan=0.0).reshape(b.shape[0], 2, -1)
