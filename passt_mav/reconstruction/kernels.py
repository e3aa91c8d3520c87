"""The GP's stationary kernels: the starting kernel, the evidence gate, cached cross-covariances.

Frames and units: positions in local east/north metres (and field time for a space-time
kernel), velocities in field units (m/s). Helpers of
:class:`passt_mav.reconstruction.GPReconstructor`, free of its state.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import ReconstructionError

__all__ = ["CrossCovCache", "base_kernel", "evidence_gate", "fit_on_field", "length_bounds"]


def length_bounds(X, Y, max_length_cells: float) -> tuple[float, tuple[float, float]]:
    """The grid's cell size (metres: the geometric mean spacing of neighbouring centres of ``X, Y``
    (rows, cols)) and the bounds of the kernels' spatial length scale (metres): [0.5 cell,
    min(``max_length_cells`` cells, half the grid's diagonal)], at least one cell at the top."""
    R, C = X.shape
    # mean spacing of neighbouring centres, metres
    dx = np.nanmean(np.hypot(np.diff(X, axis=1), np.diff(Y, axis=1))) if C > 1 else 1.0
    dy = np.nanmean(np.hypot(np.diff(X, axis=0), np.diff(Y, axis=0))) if R > 1 else 1.0
    cell = float(np.sqrt(dx * dy))
    diag = float(np.hypot(np.ptp(X), np.ptp(Y)))
    # An upper bound of a few cells keeps a correction local: fitted on samples
    # along one leg (a line), the likelihood often prefers a length scale as long
    # as allowed, and the GP then extrapolates the residual across the region
    # (measured on a drifting-model test: the estimate's RMSE tripled in one leg).
    return cell, (0.5 * cell, max(min(float(max_length_cells) * cell, 0.5 * diag), 1.0 * cell))


def base_kernel(
    X, Y, kernel: str, length_scale, max_length_cells: float, noise_std: float, t_span: float | None = None
):
    """The kernel a GP's fit starts from and the cell size (metres): ``ConstantKernel * Matern(nu)
    (or RBF) + WhiteKernel`` over (east, north) metres of the grid ``X, Y`` (rows, cols), or over
    (east, north, time) with an anisotropic length scale when ``t_span`` (the samples' time span)
    is given; length scale ``length_scale`` metres (default 3 cells) within [0.5 cell,
    min(``max_length_cells`` cells, half the grid's diagonal)], noise from ``noise_std``."""
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, Matern, WhiteKernel

    cell, bounds = length_bounds(X, Y, max_length_cells)
    ls = float(length_scale) if length_scale is not None else 3.0 * cell
    ls = float(np.clip(ls, *bounds))
    if t_span is not None:  # anisotropic over (east, north, time)
        ls = [ls, ls, float(t_span)]
        bounds = [bounds, bounds, (t_span / 50.0, t_span * 1e3)]
    if kernel == "rbf":
        k = RBF(ls, bounds)
    else:
        k = Matern(ls, bounds, nu=1.5 if kernel == "matern32" else 2.5)
    nl = max(float(noise_std) ** 2, 1e-10)
    # the noise never drops below the sensor's own (noise_std): a residual cannot be less
    # noisy than the instrument, and a fit allowed below it (it was (noise_std/2)^2) turns
    # sensor noise into "signal" that drags the estimate off a good forecast (measured:
    # a forecast within 0.005 of the truth, 51 samples with noise 0.05, 20 seeds: the
    # estimate's RMSE was 1.26 x the forecast's; 1.60 x with background modes)
    return ConstantKernel(1.0, (1e-8, 1e3)) * k + WhiteKernel(nl, (nl, max(nl * 100, 1.0))), cell


def evidence_gate(gp, y, noise_std: float):
    """The fitted kernel of ``gp`` (a fitted sklearn regressor), or, when the samples do not show a signal
    beyond the sensor noise, the kernel with its signal switched off.

    The stationary kernel is kept only when it raises the log marginal likelihood of the
    targets ``y`` over white noise alone (variance ``max(noise_std^2, mean y^2)``, itself
    fitted) by more than the Bayesian information criterion's penalty for its extra
    parameters, ``0.5 k ln n`` (Schwarz 1978; k = signal variance + length scales). A
    maximum-likelihood fit on pure noise finds some "signal" in one seed out of two (the
    sample variance exceeds the noise's), and a correction fitted to noise only adds
    error where the model was right. A real drift of the model raises the likelihood by
    orders more than the penalty. Returns (the kernel, (likelihood gain, penalty)).
    """
    from sklearn.gaussian_process.kernels import ConstantKernel, WhiteKernel

    y = np.asarray(y, dtype=np.float64)
    n = y.size
    floor = max(float(noise_std) ** 2, 1e-10)
    s0 = max(floor, float(np.mean(y**2)))
    lml0 = -0.5 * n * (np.log(2 * np.pi * s0) + float(np.mean(y**2)) / s0)
    k_sig = gp.kernel_.k1
    penalty = 0.5 * (k_sig.theta.size) * np.log(max(n, 2))
    gain = float(gp.log_marginal_likelihood_value_) - lml0
    evidence = (gain, float(penalty))
    if gain >= penalty:
        return gp.kernel_, evidence
    off = ConstantKernel(1e-8, "fixed") * k_sig.k2
    return off + WhiteKernel(s0, "fixed"), evidence


class CrossCovCache:
    """Grid-to-sample covariance columns per velocity component, cached by sample position.

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

    #: at most this many cached grid-to-sample covariance columns per component
    #: (30 x 30 grid: 900 columns = 6.5 MB)
    max_cached_columns = 2048

    def __init__(self):
        # per component: [kernel, grid points, sample position -> row of the buffer, buffer
        # (capacity, n_cells): column j of kernel(grid_pts, xy) stored as a contiguous row]
        self.entries = [None, None]

    def __getitem__(self, comp: int):
        return self.entries[comp]

    def __call__(self, comp: int, kernel, xy: np.ndarray, grid_pts: np.ndarray) -> np.ndarray:
        """``kernel(grid_pts, xy)`` ((n_cells, n) float64) for component ``comp``."""
        entry = self.entries[comp]
        if entry is None or entry[0] is not kernel or not np.array_equal(entry[1], grid_pts):
            entry = self.entries[comp] = [kernel, grid_pts, {}, np.empty((0, len(grid_pts)))]
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


def fit_on_field(gp, snapshot, max_points: int = 150):
    """The kernels of u and v and the cell size (metres) fitted on a gridded snapshot ``(2, R, C)``
    for ``gp`` (a :class:`~passt_mav.reconstruction.GPReconstructor`): signal variance and length scale.

    The preferred once-per-campaign fit: the model's initial state shows the
    field's full 2-D structure, whereas one leg's samples lie along a line
    (and, in residual mode, are ~0 on the first leg). Up to ``max_points``
    water cells (seeded subsample) minus their mean are used; the WhiteKernel
    is held at ``noise_std**2`` since a gridded state carries no sensor noise.
    """
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process.kernels import WhiteKernel

    X, Y = gp.grid_coords()
    a = np.asarray(snapshot, dtype=np.float64)
    if a.shape != (2,) + X.shape:
        raise ReconstructionError(f"snapshot must have shape {(2,) + X.shape}, got {a.shape}")
    ok = np.isfinite(a).all(axis=0).ravel()
    idx = np.flatnonzero(ok)
    if idx.size < 4:
        raise ReconstructionError("snapshot has fewer than 4 water cells to fit the GP on")
    rng = np.random.default_rng(gp.seed)
    if idx.size > max_points:
        idx = np.sort(rng.choice(idx, max_points, replace=False))
    xy = np.column_stack([X.ravel()[idx], Y.ravel()[idx]])
    base, cell = gp.start_kernel()
    base = base.k1 + WhiteKernel(max(float(gp.noise_std) ** 2, 1e-10), "fixed")
    kernels = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=ConvergenceWarning)
        for k in range(2):
            y = a[k].ravel()[idx]
            reg = gp.fit_regressor(base, xy, y - y.mean(), optimize=True)
            kernels.append(reg.kernel_)
    return kernels, cell
