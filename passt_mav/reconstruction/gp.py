"""Gaussian-process reconstruction of one field snapshot from scattered samples.

Frames and units: sample and grid positions are local east/north metres
(``grid.centres_xy()``, ``grid.latlon_to_xy``); velocities in the field's units
(m/s). One scikit-learn ``GaussianProcessRegressor`` per velocity component.

Kernel: ``ConstantKernel * Matern(nu) + WhiteKernel`` (or RBF). Hyper-parameters
are fitted once per campaign (:meth:`GPReconstructor.fit`, normally on the first
leg's samples) and then held fixed (``optimizer=None``), so every later leg's fit
is one Cholesky of an n x n matrix - milliseconds for the few hundred samples of
a leg.

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

Land / missing cells (NaN in the forecast, or ``mask`` False) stay NaN.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import ReconstructionError

__all__ = ["GPReconstructor"]

_PRIORS = ("forecast", "none")
_KERNELS = ("matern32", "matern52", "rbf")
_SOLVERS = ("sklearn", "cholesky")


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
            hyper-parameter fit (default 60); reconstruction uses all.
        space_time: when sample times are given, the kernel also spans time
            (anisotropic Matern/RBF over east, north, time) and the snapshot is
            predicted at the query time, so a residual seen early in a leg counts
            less than a fresh one when the flow moves on within the leg.
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

        bias: with ``prior="forecast"``, the residual may carry a constant offset over the
            region (one per component: the whole current sped up or turned since the forecast,
            as a tide does), a factor ``b`` with ``b ~ N(0, s^2 I_2)`` on two modes of ones
            (u, v) beside the background's: ordinary kriging's unknown constant mean, here as a
            prior term so that the gate below can refuse it. ``s^2`` is chosen at every
            :meth:`reconstruct` from a log grid (``mean(y^2)`` x 1e-2 .. 10, and 0) by the joint
            marginal likelihood of the samples' residuals under the offset plus the background
            (factor in use) plus the fitted sensor noise, and kept only when it raises that
            likelihood by more than the information criterion's ``0.5 ln(2n)`` (one parameter).
            A forecast that is right (residual = noise) then keeps ``s^2 = 0`` and nothing
            changes; a stale forecast of a field that moved as a whole is shifted everywhere,
            not only within a length scale of the samples. Default False.

    Learned state: ``kernels_`` (fitted kernel per component), ``cell_m_``,
    ``n_inputs_`` (2 = space, 3 = space-time), ``background_scale_`` (the last factor chosen
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
        max_fit_points: int = 60,
        space_time: bool = True,
        n_restarts: int = 0,
        seed: int = 0,
        solver: str = "sklearn",
        background=None,
        background_scale="ml",
        bias: bool = False,
    ):
        self.grid_xy = grid_xy
        self.bias = bias
        self.background = background
        self.background_scale = background_scale
        self.solver = solver
        self.space_time = space_time
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
    def _grid(self) -> tuple[np.ndarray, np.ndarray]:
        X, Y = (np.asarray(a, dtype=np.float64) for a in self.grid_xy)
        if X.shape != Y.shape or X.ndim != 2:
            raise ReconstructionError(f"grid_xy must be two (rows, cols) arrays, got {X.shape} and {Y.shape}")
        return X, Y

    def _check(self, samples_xy, samples_uv, forecast_at_samples, samples_t=None, *, with_mask: bool = False):
        if self.prior not in _PRIORS:
            raise ReconstructionError(f"unknown GP prior {self.prior!r}; choose one of {', '.join(_PRIORS)}")
        if self.kernel not in _KERNELS:
            raise ReconstructionError(f"unknown GP kernel {self.kernel!r}; choose one of {', '.join(_KERNELS)}")
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

    def _base_kernel(self, t_span: float | None = None):
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel, Matern, WhiteKernel

        X, Y = self._grid()
        R, C = X.shape
        # mean spacing of neighbouring centres, metres
        dx = np.nanmean(np.hypot(np.diff(X, axis=1), np.diff(Y, axis=1))) if C > 1 else 1.0
        dy = np.nanmean(np.hypot(np.diff(X, axis=0), np.diff(Y, axis=0))) if R > 1 else 1.0
        cell = float(np.sqrt(dx * dy))
        diag = float(np.hypot(np.ptp(X), np.ptp(Y)))
        ls = float(self.length_scale) if self.length_scale is not None else 3.0 * cell
        # An upper bound of a few cells keeps a correction local: fitted on samples
        # along one leg (a line), the likelihood often prefers a length scale as long
        # as allowed, and the GP then extrapolates the residual across the region
        # (measured on a drifting-model test: the estimate's RMSE tripled in one leg).
        bounds = (0.5 * cell, max(min(float(self.max_length_cells) * cell, 0.5 * diag), 1.0 * cell))
        ls = float(np.clip(ls, *bounds))
        if t_span is not None:  # anisotropic over (east, north, time)
            ls = [ls, ls, float(t_span)]
            bounds = [bounds, bounds, (t_span / 50.0, t_span * 1e3)]
        if self.kernel == "rbf":
            k = RBF(ls, bounds)
        else:
            k = Matern(ls, bounds, nu=1.5 if self.kernel == "matern32" else 2.5)
        nl = max(float(self.noise_std) ** 2, 1e-10)
        # the noise never drops below the sensor's own (noise_std): a residual cannot be less
        # noisy than the instrument, and a fit allowed below it (it was (noise_std/2)^2) turns
        # sensor noise into "signal" that drags the estimate off a good forecast (measured:
        # a forecast within 0.005 of the truth, 51 samples with noise 0.05, 20 seeds: the
        # estimate's RMSE was 1.26 x the forecast's; 1.60 x with background modes)
        return ConstantKernel(1.0, (1e-8, 1e3)) * k + WhiteKernel(nl, (nl, max(nl * 100, 1.0))), cell

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

    def _fit_gp(self, kernel, xy, y, optimize: bool):
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
        comes from the column cache of component ``comp`` (:meth:`_cross_cov`, the
        same numbers). ``with_std=False`` skips the variance (returns ``(mean, None)``).
        """
        from scipy.linalg import cho_solve, cholesky, solve_triangular

        K = kernel(xy)
        K[np.diag_indices_from(K)] += float(self.alpha)
        try:
            Lc = cholesky(K, lower=True, check_finite=False)
        except np.linalg.LinAlgError as exc:
            raise ReconstructionError(
                f"GP fit failed (Cholesky: {exc}); increase the noise level: alpha (now {self.alpha:g}) or noise_std"
            ) from None
        a = cho_solve((Lc, True), y, check_finite=False)
        Ks = self._cross_cov(comp, kernel, xy, grid_pts)
        mean = Ks @ a
        if not with_std:
            return mean, None
        V = solve_triangular(Lc, Ks.T, lower=True, check_finite=False)
        var = kernel.diag(grid_pts) - np.einsum("ij,ij->j", V, V)
        return mean, np.sqrt(np.maximum(var, 0.0))

    #: at most this many cached grid-to-sample covariance columns per component
    #: (30 x 30 grid: 900 columns = 6.5 MB)
    max_cached_columns = 2048

    def _cross_cov(self, comp: int, kernel, xy: np.ndarray, grid_pts: np.ndarray) -> np.ndarray:
        """``kernel(grid_pts, xy)`` ((n_cells, n) float64), its columns cached by sample position.

        A leg's samples sit where earlier legs' did (cell centres along a path, times
        at the same offset from the reconstructed time), so the same columns are
        evaluated leg after leg; evaluating them is most of a leg's GP time (5 ms of
        the 18 ms of a 201-sample, 900-cell space-time reconstruction; numpy's float64
        ``exp`` is not vectorised here). Written by hand because sklearn has no
        such cache. A column is computed once by the kernel itself, from the very
        same inputs, so the result is bit-identical to ``kernel(grid_pts, xy)``. The
        cache belongs to one kernel object and one set of grid points; a refit or
        another grid starts a new one.
        """
        state = getattr(self, "_col_cache", None)
        if state is None:
            state = self._col_cache = [None, None]
        entry = state[comp]
        if entry is None or entry[0] is not kernel or not np.array_equal(entry[1], grid_pts):
            # [kernel, grid points, sample position -> row of the buffer, buffer (capacity, n_cells):
            # column j of kernel(grid_pts, xy) stored as a contiguous row]
            entry = state[comp] = [kernel, grid_pts, {}, np.empty((0, len(grid_pts)))]
        where = entry[2]
        keys = [row.tobytes() for row in xy]
        missing = list(dict.fromkeys(k for k in keys if k not in where))
        if missing:
            n_old = len(where)
            if n_old + len(missing) > self.max_cached_columns:
                return kernel(grid_pts, xy)
            new = np.frombuffer(b"".join(missing), dtype=np.float64).reshape(len(missing), xy.shape[1])
            if n_old + len(missing) > entry[3].shape[0]:  # grow by doubling
                grown = np.empty((min(max(2 * (n_old + len(missing)), 64), self.max_cached_columns), len(grid_pts)))
                grown[:n_old] = entry[3][:n_old]
                entry[3] = grown
            entry[3][n_old : n_old + len(missing)] = kernel(grid_pts, new).T
            where.update((k, n_old + j) for j, k in enumerate(missing))
        # one gather of contiguous rows, transposed into the (n_cells, n) C-ordered layout the
        # kernel returns (the same values and layout, so the same BLAS path downstream):
        # 0.22 ms for 200 of 900 cells, against 0.36 ms for a stack of per-column arrays
        # and 0.46 ms for a column gather (np.take on axis 1)
        return np.ascontiguousarray(entry[3][[where[k] for k in keys]].T)

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
        base, cell = self._base_kernel(t_span)
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
                gp = self._fit_gp(init, xy, target[:, k], optimize=True)
                kernels.append(self._evidence_gate(gp, target[:, k], k))
        self.kernels_ = kernels
        self.cell_m_ = cell
        self.n_inputs_ = xy.shape[1]
        return self

    fit_hyperparameters = fit

    def innovation_loglik(self, samples_xy, residual_uv, *, samples_t=None) -> float:
        """Log density (nats, up to a constant shared by every residual at these positions) of
        residuals ``residual_uv`` (n, 2; m/s east/north) at ``samples_xy`` (n, 2 metres) under
        this GP's own prior covariance as it stands: the fitted kernels of u and v (sensor
        noise included; the initial kernels before any fit, scaled as :meth:`prior_factors`
        scales them) plus the background modes times the factor in use, u and v jointly.
        ``-0.5 r^T K^-1 r`` with ``K = L L^T``; the ``log |K|`` term is the same for every
        forecast scored at the same samples and is left out. How well a forecast explains a
        leg's samples, before the GP adapts to them: the score of
        :class:`passt_mav.loop.passt.PasstLoop`'s prior weighting. ``samples_t``: sample times for a
        space-time kernel (only their differences matter)."""
        from scipy.linalg import cho_solve, cholesky

        X, Y = self._grid()
        xy = np.asarray(samples_xy, dtype=np.float64).reshape(-1, 2)
        r = np.asarray(residual_uv, dtype=np.float64).reshape(-1, 2)
        n = len(xy)
        Bg = (
            self._background_modes(X.shape) * np.sqrt(self._background_factor())
            if self.background is not None
            else None
        )
        kernels, fitted = self._prior_kernels(Bg)
        Bg = self._with_offset_modes(Bg, X.size)
        if not fitted:
            inputs = xy
        else:
            use_t = getattr(self, "n_inputs_", 2) == 3 and samples_t is not None
            inputs = np.column_stack([xy, np.asarray(samples_t, dtype=np.float64).reshape(-1)]) if use_t else xy
            if getattr(self, "n_inputs_", 2) == 3 and not use_t:
                inputs = np.column_stack([xy, np.zeros(n)])
        K = np.zeros((2 * n, 2 * n))
        for k in range(2):
            K[k * n : (k + 1) * n, k * n : (k + 1) * n] = kernels[k](inputs)
        if Bg is not None:
            cells = self._nearest_cells(xy, X, Y)
            Hb = np.concatenate([Bg[:, 0, cells], Bg[:, 1, cells]], axis=1)
            K += Hb.T @ Hb
        K[np.diag_indices_from(K)] += float(self.alpha)
        y = np.concatenate([r[:, 0], r[:, 1]])
        try:
            Lc = cholesky(K, lower=True, check_finite=False)
        except np.linalg.LinAlgError as exc:
            raise ReconstructionError(
                f"innovation likelihood: Cholesky failed ({exc}); increase alpha (now {self.alpha:g}) or noise_std"
            ) from None
        return -0.5 * float(y @ cho_solve((Lc, True), y, check_finite=False))

    def _evidence_gate(self, gp, y, comp: int):
        """The fitted kernel of component ``comp``, or, when the samples do not show a signal
        beyond the sensor noise, the kernel with its signal switched off.

        The stationary kernel is kept only when it raises the log marginal likelihood of the
        targets ``y`` over white noise alone (variance ``max(noise_std^2, mean y^2)``, itself
        fitted) by more than the Bayesian information criterion's penalty for its extra
        parameters, ``0.5 k ln n`` (Schwarz 1978; k = signal variance + length scales). A
        maximum-likelihood fit on pure noise finds some "signal" in one seed out of two (the
        sample variance exceeds the noise's), and a correction fitted to noise only adds
        error where the model was right. A real drift of the model raises the likelihood by
        orders more than the penalty. Records ``evidence_[comp]`` = (likelihood gain, penalty).
        """
        from sklearn.gaussian_process.kernels import ConstantKernel, WhiteKernel

        y = np.asarray(y, dtype=np.float64)
        n = y.size
        floor = max(float(self.noise_std) ** 2, 1e-10)
        s0 = max(floor, float(np.mean(y**2)))
        lml0 = -0.5 * n * (np.log(2 * np.pi * s0) + float(np.mean(y**2)) / s0)
        k_sig = gp.kernel_.k1
        penalty = 0.5 * (k_sig.theta.size) * np.log(max(n, 2))
        gain = float(gp.log_marginal_likelihood_value_) - lml0
        ev = getattr(self, "evidence_", None) or [None, None]
        ev[comp] = (gain, float(penalty))
        self.evidence_ = ev
        if gain >= penalty:
            return gp.kernel_
        off = ConstantKernel(1e-8, "fixed") * k_sig.k2
        return off + WhiteKernel(s0, "fixed")

    #: candidate factors on the background covariance for ``background_scale="ml"``
    BACKGROUND_SCALES = (0.0,) + tuple(float(x) for x in np.logspace(-4, 1, 11))

    def _fit_background_scale(self, target, cells, Bg) -> float:
        """The factor in :data:`BACKGROUND_SCALES` that maximises the joint log marginal likelihood
        of the samples' targets (n, 2) (u and v; zero-mean) under factor x ``B`` + the fitted
        sensor noise; ``cells``: each sample's flat cell index, ``Bg``: (m, 2, R*C) modes.
        The modes are weighed against the sensor noise alone: how much of the residual do they
        explain? (with the stationary kernels included, a fitted stationary kernel has already
        taken a smooth drift's variance and the likelihood then under-weights the modes: measured
        on the ocean default, 6 trials, L=50, final RMSE 0.0678 that way, 0.0627 this way, 0.0564
        with the factor fixed at 1, which however spoils a leg where the model is right)."""
        return self._fit_factor(target, cells, np.zeros((0,) + Bg.shape[1:]), Bg, self.BACKGROUND_SCALES)

    def _fit_factor(self, target, cells, Bg, modes, candidates) -> float:
        """The variance in ``candidates`` (0 first) on ``modes`` (m, 2, N; unit factor) that maximises
        the joint log marginal likelihood of the residuals ``target`` (n, 2) under those modes + the
        modes ``Bg`` already in (factors applied) + the fitted sensor noise; 0 unless it raises it
        over 0 by the information criterion's 0.5 ln(2n) (one fitted parameter; see
        :meth:`_evidence_gate`: a factor fitted to noise drags a right forecast off). The
        stationary kernels are left out (see :meth:`_fit_background_scale`)."""
        from scipy.linalg import cho_solve, cholesky

        n = len(target)
        y = np.concatenate([target[:, 0], target[:, 1]])
        noise = np.concatenate([np.full(n, float(self.kernels_[k].k2.noise_level)) for k in range(2)])
        Hb = np.concatenate([Bg[:, 0, cells], Bg[:, 1, cells]], axis=1)
        K0 = Hb.T @ Hb + np.diag(noise + float(self.alpha))
        Hm = np.concatenate([modes[:, 0, cells], modes[:, 1, cells]], axis=1)
        J = Hm.T @ Hm
        best, best_ll, ll0 = 1.0, -np.inf, None
        for a in candidates:
            try:
                Lc = cholesky(K0 + a * J, lower=True, check_finite=False)
            except np.linalg.LinAlgError:
                continue
            ll = -0.5 * float(y @ cho_solve((Lc, True), y, check_finite=False)) - float(np.log(np.diag(Lc)).sum())
            if a == 0.0:
                ll0 = ll
            if ll > best_ll:
                best, best_ll = a, ll
        if ll0 is not None and best > 0 and best_ll - ll0 < 0.5 * np.log(max(2 * n, 2)):
            return 0.0
        return float(best)

    def _background_factor(self) -> float:
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

    def _prior_kernels(self, Bg) -> tuple[list, bool]:
        """(the fitted kernels of u and v, True), or before any fit (the initial kernel: length scale
        3 cells, noise ``noise_std``, signal variance = the background's mean variance in ``Bg``
        (m, 2, N), or ``noise_std**2`` without one; False)."""
        from sklearn.gaussian_process.kernels import ConstantKernel, WhiteKernel

        kernels = getattr(self, "kernels_", None)
        if kernels is not None:
            return kernels, True
        base, _ = self._base_kernel()
        amp = float(np.mean(np.sum(Bg**2, axis=0))) if Bg is not None and Bg.size else 0.0
        amp = amp if amp > 0 else max(float(self.noise_std) ** 2, 1e-10)
        k = ConstantKernel(amp, "fixed") * base.k1.k2 + WhiteKernel(max(float(self.noise_std) ** 2, 1e-10), "fixed")
        return [k, k], False

    def prior_factors(self, land=None, *, kernel_rank: int | None = None, kernel_energy: float | None = None):
        """The prior covariance of the next reconstruction's error over the grid, factored.

        Returns ``(F (2N, r), d (2N,), noise (2N,))`` with ``Sigma = F F^T + diag(d)``: rows
        ``k * N + cell`` (k = 0 u east, 1 v north; flat cell = row * C + col), in (field
        velocity units)^2. F holds the background modes times the square root of the factor
        in use (:meth:`_background_factor`: the last one fitted), then each component's
        stationary signal kernel (the fitted ``k1``, at zero time lag for a space-time
        kernel) on the water cells by its leading eigenpairs; ``d`` is what the dropped
        eigenpairs leave on the diagonal (exactly the kernel's variance minus the kept
        part); ``noise`` the fitted sensor-noise variance (the WhiteKernel). Land cells
        (``land`` True) get zero rows. Before any fit the kernels are the initial ones
        (length scale 3 cells, noise ``noise_std``) with a signal variance equal to the
        background's mean variance (or ``noise_std**2`` without one): the leg is planned on
        the structure of the prior, whose scale no sample has fixed yet.
        """
        from scipy.linalg import eigh

        X, Y = self._grid()
        R, C = X.shape
        N = R * C
        water = np.ones(N, bool) if land is None else ~np.asarray(land, bool).reshape(-1)
        wi = np.flatnonzero(water)
        Bg = None
        if self.background is not None:
            Bg = self._background_modes(X.shape) * np.sqrt(self._background_factor())  # (m, 2, N)
            Bg[:, :, ~water] = 0.0
        kernels, fitted = self._prior_kernels(Bg)
        Bg = self._with_offset_modes(Bg, N, water)
        n_in = getattr(self, "n_inputs_", 2) if fitted else 2
        pts = np.column_stack([X.ravel()[wi], Y.ravel()[wi]] + ([np.zeros(wi.size)] if n_in == 3 else []))
        rank_cap = int(self.PRIOR_KERNEL_RANK if kernel_rank is None else kernel_rank)
        energy = float(self.PRIOR_KERNEL_ENERGY if kernel_energy is None else kernel_energy)
        cols = [] if Bg is None else [Bg.reshape(Bg.shape[0], 2 * N).T]
        d = np.zeros(2 * N)
        noise = np.ones(2 * N)
        for k in range(2):
            K = kernels[k].k1(pts)
            top = min(rank_cap, wi.size)
            lam, U = eigh(K, subset_by_index=[wi.size - top, wi.size - 1], check_finite=False)
            lam, U = np.clip(lam[::-1], 0.0, None), U[:, ::-1]
            tr = float(np.trace(K))
            keep = int(np.searchsorted(np.cumsum(lam) / tr, energy) + 1) if tr > 0 else 0
            keep = min(keep, top)
            Fk = np.zeros((2 * N, keep))
            Fk[k * N + wi] = U[:, :keep] * np.sqrt(lam[:keep])
            cols.append(Fk)
            d[k * N + wi] = np.clip(np.diag(K) - np.einsum("ij,ij->i", Fk[k * N + wi], Fk[k * N + wi]), 0.0, None)
            noise[k * N : (k + 1) * N] = float(kernels[k].k2.noise_level) + float(self.alpha)
        return np.hstack(cols) if cols else np.zeros((2 * N, 0)), d, noise

    def fit_field(self, snapshot, *, max_points: int = 150) -> GPReconstructor:
        """Fit the signal variance and length scale on a gridded snapshot ``(2, R, C)``.

        The preferred once-per-campaign fit: the model's initial state shows the
        field's full 2-D structure, whereas one leg's samples lie along a line
        (and, in residual mode, are ~0 on the first leg). Up to ``max_points``
        water cells (seeded subsample) minus their mean are used; the WhiteKernel
        is held at ``noise_std**2`` since a gridded state carries no sensor noise.
        """
        import warnings

        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process.kernels import WhiteKernel

        X, Y = self._grid()
        a = np.asarray(snapshot, dtype=np.float64)
        if a.shape != (2,) + X.shape:
            raise ReconstructionError(f"snapshot must have shape {(2,) + X.shape}, got {a.shape}")
        ok = np.isfinite(a).all(axis=0).ravel()
        idx = np.flatnonzero(ok)
        if idx.size < 4:
            raise ReconstructionError("snapshot has fewer than 4 water cells to fit the GP on")
        rng = np.random.default_rng(self.seed)
        if idx.size > max_points:
            idx = np.sort(rng.choice(idx, max_points, replace=False))
        xy = np.column_stack([X.ravel()[idx], Y.ravel()[idx]])
        base, cell = self._base_kernel()
        base = base.k1 + WhiteKernel(max(float(self.noise_std) ** 2, 1e-10), "fixed")
        kernels = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", category=ConvergenceWarning)
            for k in range(2):
                y = a[k].ravel()[idx]
                gp = self._fit_gp(base, xy, y - y.mean(), optimize=True)
                kernels.append(gp.kernel_)
        self.kernels_ = kernels
        self.cell_m_ = cell
        self.n_inputs_ = 2
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
        only) the std is not computed and ``None`` is returned in its place (the
        variance's triangular solve against every grid cell is most of the rest of
        a leg's GP time, and only a std-based reward reads it).
        """
        X, Y = self._grid()
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
        modes = None
        if self.background is not None or self._bias_on():
            cells = self._nearest_cells(np.asarray(samples_xy, dtype=np.float64).reshape(-1, 2)[ok], X, Y)
            modes = self._fitted_modes(target, cells, X.shape, fc)
        if modes is not None:
            mean, std = self._posterior_joint(xy, target, grid_pts, cells, modes, with_std)
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

    def _posterior_components(self, xy, target, offset, grid_pts, shape, with_std: bool):
        """Independent u and v posteriors (no background): mean (2, R, C) and std or None."""
        mean = np.empty((2,) + shape)
        with_std = bool(with_std) or self.solver != "cholesky"
        std = np.empty((2,) + shape) if with_std else None
        for k in range(2):
            if self.solver == "cholesky":
                m, s = self._posterior_fixed(self.kernels_[k], xy, target[:, k], grid_pts, with_std=with_std, comp=k)
            else:
                gp = self._fit_gp(self.kernels_[k], xy, target[:, k], optimize=False)
                from threadpoolctl import threadpool_limits

                with threadpool_limits(1):
                    m, s = gp.predict(grid_pts, return_std=True)
            mean[k] = m.reshape(shape) + offset[k]
            if with_std:
                std[k] = s.reshape(shape)
        return mean, std

    def _bias_on(self) -> bool:
        return bool(getattr(self, "bias", False)) and self.prior == "forecast"

    def _fitted_modes(self, target, cells, shape, fc=None) -> np.ndarray | None:
        """The low-rank prior modes of this reconstruction, (m, 2, R*C) with their factors applied:
        the background modes (factor refitted when ``background_scale="ml"``), then with ``bias``
        the two offset modes and the forecast's own anomaly (``fc`` (2, R, C) minus its water
        mean) where the samples keep them (``bias_var_``, ``scale_var_`` refitted); None when
        there are none."""
        N = int(np.prod(shape))
        Bg = np.zeros((0, 2, N))
        if self.background is not None:
            Bg = self._background_modes(shape)
            if self.background_scale == "ml":
                self.background_scale_ = self._fit_background_scale(target, cells, Bg)
            Bg = Bg * np.sqrt(self._background_factor())
        if self._bias_on():
            v0 = max(float(np.mean(target**2)), float(self.noise_std) ** 2, 1e-12)
            self.bias_var_ = self._fit_factor(target, cells, Bg, self._bias_modes(N), self._bias_candidates(v0))
            if self.bias_var_ > 0:
                Bg = np.concatenate([Bg, self._bias_modes(N) * np.sqrt(self.bias_var_)])
            self.scale_var_ = 0.0
            anom = self._anomaly_mode(fc)
            if anom is not None:
                self.scale_var_ = self._fit_factor(target, cells, Bg, anom, self._bias_candidates(1.0))
                if self.scale_var_ > 0:
                    Bg = np.concatenate([Bg, anom * np.sqrt(self.scale_var_)])
        return Bg if Bg.shape[0] or self.background is not None else None

    @staticmethod
    def _anomaly_mode(fc) -> np.ndarray | None:
        """The forecast's anomaly as one joint u/v mode (1, 2, N): ``fc`` minus its mean over the
        water cells per component, land 0; None without a forecast or with a flat one. A factor
        ``c ~ N(0, s^2)`` on it lets the samples say the forecast's structure is too strong
        (c < 0: c = -1 removes it, the stale pattern of a rotating tide) or too weak (c > 0)."""
        if fc is None:
            return None
        a = np.asarray(fc, np.float64).reshape(2, -1)
        water = np.isfinite(a).all(axis=0)
        if water.sum() < 2:
            return None
        a = np.where(water, a - np.nanmean(a[:, water], axis=1, keepdims=True), 0.0)
        return a[None] if float(np.abs(a).max()) > 0 else None

    @staticmethod
    def _bias_modes(N: int, water=None) -> np.ndarray:
        """The two offset modes (2, 2, N): ones on u, ones on v (zero off ``water`` when given)."""
        m = np.zeros((2, 2, N))
        m[0, 0] = m[1, 1] = 1.0 if water is None else np.asarray(water, np.float64)
        return m

    #: variances tried by the ``bias`` fits, as multiples of a reference variance (the offset:
    #: the residuals' mean square; the forecast-anomaly factor: 1)
    BIAS_FRACTIONS = tuple(float(x) for x in np.logspace(-2, 1, 10))

    def _bias_candidates(self, v0: float) -> tuple[float, ...]:
        """The variances a ``bias`` fit tries: 0, then ``v0`` x :data:`BIAS_FRACTIONS`."""
        return (0.0,) + tuple(v0 * f for f in self.BIAS_FRACTIONS)

    def _with_offset_modes(self, Bg, N: int, water=None):
        """``Bg`` (m, 2, N) or None, with the offset modes of the last ``bias`` fit appended (when one
        was kept after a fit): the prior as the next reconstruction will start it."""
        var = float(getattr(self, "bias_var_", 0.0)) if self._bias_on() and hasattr(self, "kernels_") else 0.0
        if var <= 0:
            return Bg
        Bb = self._bias_modes(N, water) * np.sqrt(var)
        return Bb if Bg is None else np.concatenate([Bg, Bb])

    def _background_modes(self, shape) -> np.ndarray:
        """The background modes as (m, 2, R*C) float64, land (NaN) as 0."""
        b = np.asarray(self.background, dtype=np.float64)
        if b.ndim != 4 or b.shape[1:] != (2,) + tuple(shape):
            raise ReconstructionError(f"background modes must have shape (m, 2, {shape[0]}, {shape[1]}), got {b.shape}")
        return np.nan_to_num(b, nan=0.0).reshape(b.shape[0], 2, -1)

    def _posterior_joint(self, xy, target, grid_pts, cells, Bg, with_std: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Joint u/v posterior with the background modes plus the fitted stationary kernels.

        Observations ``y = [u residuals; v residuals]`` (2n). Prior covariance between
        component a at point p and component b at point q:
        ``sum_j b_j[a, p] b_j[b, q] + [a == b] k_a(p, q)`` (k_a includes the sensor-noise
        WhiteKernel on the samples). Mean ``C_* K^-1 y`` and variance ``diag C_** - |L^-1 C_*^T|^2``
        with ``K = C(samples) + alpha I = L L^T``, written out with scipy's Cholesky
        because no library GP takes a low-rank cross-component covariance.
        """
        from scipy.linalg import cho_solve, cholesky, solve_triangular

        shape = self._grid()[0].shape
        n = len(xy)  # Bg: (m, 2, N) modes with the factor applied
        Hb = np.concatenate([Bg[:, 0, cells], Bg[:, 1, cells]], axis=1)  # (m, 2n)
        K = Hb.T @ Hb
        for k in range(2):
            K[k * n : (k + 1) * n, k * n : (k + 1) * n] += self.kernels_[k](xy)
        K[np.diag_indices_from(K)] += float(self.alpha)
        try:
            Lc = cholesky(K, lower=True, check_finite=False)
        except np.linalg.LinAlgError as exc:
            raise ReconstructionError(
                f"GP fit failed (Cholesky: {exc}); increase the noise level: alpha (now {self.alpha:g}) or noise_std"
            ) from None
        y = np.concatenate([target[:, 0], target[:, 1]])
        a = cho_solve((Lc, True), y, check_finite=False)
        w = Hb @ a  # (m,)
        mean = np.empty((2,) + shape)
        std = np.empty((2,) + shape) if with_std else None
        for k in range(2):
            Ks = self._cross_cov(k, self.kernels_[k], xy, grid_pts)  # (N, n)
            mean[k] = (Bg[:, k, :].T @ w + Ks @ a[k * n : (k + 1) * n]).reshape(shape)
            if with_std:
                C = Bg[:, k, :].T @ Hb  # (N, 2n)
                C[:, k * n : (k + 1) * n] += Ks
                V = solve_triangular(Lc, C.T, lower=True, check_finite=False)
                var = (
                    np.einsum("ij,ij->j", Bg[:, k, :], Bg[:, k, :])
                    + self.kernels_[k].diag(grid_pts)
                    - np.einsum("ij,ij->j", V, V)
                )
                std[k] = np.sqrt(np.maximum(var, 0.0)).reshape(shape)
        return mean, std
