"""The low-rank part of the GP's prior: modes, their fitted variances, the joint u/v posterior.

:class:`passt_mav.reconstruction.GPReconstructor` writes the prior covariance of a forecast's
residual as fitted stationary kernels (one per velocity component, sensor noise included) plus
low-rank modes over BOTH components: the model's background modes, and with ``bias`` a constant
offset per component and the forecast's own anomaly. This module holds the array algebra of
that prior, free of the estimator's state:

* the modes (:func:`offset_modes`, :func:`anomaly_mode`) and their rows at the samples
  (:func:`sample_rows`);
* the variance of a mode by type-II maximum likelihood behind an information-criterion gate
  (:func:`fit_mode_variance`);
* the joint posterior mean and std on the grid (:func:`joint_posterior`), the factored prior
  covariance for the planners (:func:`kernel_factors`) and the innovation log-likelihood
  (:func:`innovation_quadratic`).

Frames and units: a mode is (m, 2, N) with N = rows * cols flat cells (row-major), component 0 =
u (east), 1 = v (north), in field velocity units (m/s); ``cells`` are the samples' flat cell
indices; observation vectors stack the n u residuals, then the n v residuals (2n). Written with
scipy's Cholesky because no library GP takes a low-rank covariance shared across outputs.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import ReconstructionError

__all__ = [
    "anomaly_mode",
    "cell_modes",
    "cholesky_or_error",
    "fit_mode_variance",
    "fit_prior_modes",
    "gp_mode_variance",
    "innovation_quadratic",
    "joint_posterior",
    "kernel_blocks",
    "kernel_factors",
    "offset_modes",
    "prior_factors",
    "sample_coverage",
    "sample_rows",
]


def sample_rows(Bg: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The modes ``Bg`` (m, 2, N) at the samples' cells, as rows over the stacked u/v
    observations: (m, 2n)."""
    return np.concatenate([Bg[:, 0, cells], Bg[:, 1, cells]], axis=1)


def offset_modes(N: int, water=None) -> np.ndarray:
    """The two offset modes (2, 2, N): ones on u, ones on v (zero off ``water`` when given)."""
    m = np.zeros((2, 2, N))
    m[0, 0] = m[1, 1] = 1.0 if water is None else np.asarray(water, np.float64)
    return m


def anomaly_mode(fc) -> np.ndarray | None:
    """The forecast's anomaly as one joint u/v mode (1, 2, N): ``fc`` (2, R, C) minus its mean
    over the water cells per component, land 0; None without a forecast or with a flat one. A
    factor ``c ~ N(0, s^2)`` on it lets the samples say the forecast's structure is too strong
    (c < 0: c = -1 removes it, the stale pattern of a rotating tide) or too weak (c > 0)."""
    if fc is None:
        return None
    a = np.asarray(fc, np.float64).reshape(2, -1)
    water = np.isfinite(a).all(axis=0)
    if water.sum() < 2:
        return None
    a = np.where(water, a - np.nanmean(a[:, water], axis=1, keepdims=True), 0.0)
    return a[None] if float(np.abs(a).max()) > 0 else None


def cell_modes(cells, nug, N: int) -> np.ndarray:
    """The state nugget as modes: one per distinct cell in ``cells`` and component with
    ``nug[k] > 0``, ``sqrt(nug[k])`` at that cell and component, 0 elsewhere; (m, 2, N). Samples in
    one cell share its mode (see :class:`~passt_mav.reconstruction.GPReconstructor`'s ``nugget``)."""
    uc = np.unique(np.asarray(cells, dtype=np.int64))
    comps = [k for k in range(2) if nug[k] > 0]
    out = np.zeros((len(comps) * uc.size, 2, N))
    for j, k in enumerate(comps):
        out[j * uc.size + np.arange(uc.size), k, uc] = np.sqrt(float(nug[k]))
    return out


def kernel_blocks(kernels, inputs) -> np.ndarray:
    """The stationary part of the prior at the samples, (2n, 2n): ``kernels[0](inputs)`` in the u
    block, ``kernels[1](inputs)`` in the v block (sensor-noise WhiteKernel included), 0 between."""
    n = len(inputs)
    K = np.zeros((2 * n, 2 * n))
    for k in range(2):
        K[k * n : (k + 1) * n, k * n : (k + 1) * n] = kernels[k](inputs)
    return K


def fit_mode_variance(target, cells, Bg, modes, candidates, base_cov) -> float:
    """The variance in ``candidates`` (0 first) on ``modes`` (m, 2, N; unit factor) that maximises
    the joint log marginal likelihood of the residuals ``target`` (n, 2) under those modes + the
    modes ``Bg`` already in (factors applied) + ``base_cov`` (2n, 2n: the rest of the prior at the
    samples, sensor noise and jitter included); 0 unless it raises the likelihood over 0 by the
    information criterion's 0.5 ln(2n) (one fitted parameter; Schwarz 1978: a factor fitted to
    noise drags a right forecast off)."""
    from scipy.linalg import cho_solve, cholesky

    n = len(target)
    y = np.concatenate([target[:, 0], target[:, 1]])
    Hb = sample_rows(Bg, cells)
    K0 = Hb.T @ Hb + base_cov
    Hm = sample_rows(modes, cells)
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


def cholesky_or_error(K, alpha: float, what: str = "GP fit"):
    """The lower Cholesky factor of ``K``, or a :class:`ReconstructionError` that says to raise the
    noise level (``alpha``, ``noise_std``)."""
    from scipy.linalg import cholesky

    try:
        return cholesky(K, lower=True, check_finite=False)
    except np.linalg.LinAlgError as exc:
        raise ReconstructionError(
            f"{what} failed (Cholesky: {exc}); increase the noise level: alpha (now {alpha:g}) or noise_std"
        ) from None


def joint_posterior(
    gp, xy, target, grid_pts, cells, Bg, with_std: bool, nugget=None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Joint u/v posterior of the residual on the grid with the modes ``Bg`` plus the fitted
    stationary kernels of ``gp`` (a fitted :class:`~passt_mav.reconstruction.GPReconstructor`).

    Observations ``y = [u residuals; v residuals]`` (2n). Prior covariance between
    component a at point p and component b at point q:
    ``sum_j b_j[a, p] b_j[b, q] + [a == b] k_a(p, q)`` (k_a includes the sensor-noise
    WhiteKernel on the samples). Mean ``C_* K^-1 y`` and variance ``diag C_** - |L^-1 C_*^T|^2``
    with ``K = C(samples) + alpha I = L L^T``. ``nugget`` (2,) or None: the state nugget of u and v
    (field units^2), taken out of the kernels' white variance and put on the sampled cells
    (:func:`cell_modes`): a sample corrects its own cell by it. Returns mean (2, R, C) and std
    (2, R, C) or None (the prior variance on the grid: modes + kernel, white variance included).
    """
    from scipy.linalg import cho_solve, solve_triangular

    shape = gp.grid_coords()[0].shape
    n = len(xy)  # Bg: (m, 2, N) modes with the factor applied
    kernels, m0 = gp.kernels_, Bg.shape[0]
    if nugget is not None and np.any(nugget):
        kernels, Bg = gp.with_cell_nugget(kernels, Bg, cells, nugget, Bg.shape[2])
    Hb = sample_rows(Bg, cells)  # (m, 2n)
    K = Hb.T @ Hb + kernel_blocks(kernels, xy)
    K[np.diag_indices_from(K)] += float(gp.alpha)
    Lc = cholesky_or_error(K, gp.alpha)
    y = np.concatenate([target[:, 0], target[:, 1]])
    a = cho_solve((Lc, True), y, check_finite=False)
    w = Hb @ a  # (m,)
    mean = np.empty((2,) + shape)
    std = np.empty((2,) + shape) if with_std else None
    for k in range(2):
        Ks = gp.cross_cov(k, gp.kernels_[k], xy, grid_pts)  # (N, n)
        mean[k] = (Bg[:, k, :].T @ w + Ks @ a[k * n : (k + 1) * n]).reshape(shape)
        if with_std:
            C = Bg[:, k, :].T @ Hb  # (N, 2n)
            C[:, k * n : (k + 1) * n] += Ks
            V = solve_triangular(Lc, C.T, lower=True, check_finite=False)
            var = (
                np.einsum("ij,ij->j", Bg[:m0, k, :], Bg[:m0, k, :])  # the nugget is in the kernel's diag
                + gp.kernels_[k].diag(grid_pts)
                - np.einsum("ij,ij->j", V, V)
            )
            std[k] = np.sqrt(np.maximum(var, 0.0)).reshape(shape)
    return mean, std


def kernel_factors(kernels, pts, wi, N: int, rank_cap: int, energy: float, alpha: float):
    """Each component's stationary signal kernel (``kernels[k].k1``) on the water cells ``wi``
    (flat indices, points ``pts``) by its leading eigenpairs: the columns F_k (2N, keep) with
    ``keep`` the fewest of at most ``rank_cap`` eigenpairs carrying ``energy`` of the trace, the
    diagonal ``d`` (2N,) the dropped ones leave (the kernel's variance minus the kept part) and
    the sensor-noise variance ``noise`` (2N,; the WhiteKernel + ``alpha``). Rows ``k * N + cell``."""
    from scipy.linalg import eigh

    cols = []
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
        noise[k * N : (k + 1) * N] = float(kernels[k].k2.noise_level) + float(alpha)
    return cols, d, noise


def innovation_quadratic(kernels, inputs, Bg, cells, r, alpha: float) -> float:
    """``-0.5 r^T K^-1 r`` for residuals ``r`` (n, 2) under the kernels of u and v at ``inputs``
    plus the modes ``Bg`` (m, 2, N) or None at the samples' ``cells``, jitter ``alpha``."""
    from scipy.linalg import cho_solve, cholesky

    K = kernel_blocks(kernels, inputs)
    if Bg is not None:
        Hb = sample_rows(Bg, cells)
        K += Hb.T @ Hb
    K[np.diag_indices_from(K)] += float(alpha)
    y = np.concatenate([r[:, 0], r[:, 1]])
    try:
        Lc = cholesky(K, lower=True, check_finite=False)
    except np.linalg.LinAlgError as exc:
        raise ReconstructionError(
            f"innovation likelihood: Cholesky failed ({exc}); increase alpha (now {alpha:g}) or noise_std"
        ) from None
    return -0.5 * float(y @ cho_solve((Lc, True), y, check_finite=False))


def prior_factors(
    gp,
    land=None,
    *,
    kernel_rank: int | None = None,
    kernel_energy: float | None = None,
    with_mode_count: bool = False,
):
    """The prior covariance of the next reconstruction's error over the grid, factored.

    Returns ``(F (2N, r), d (2N,), noise (2N,))`` with ``Sigma = F F^T + diag(d)``: rows
    ``k * N + cell`` (k = 0 u east, 1 v north; flat cell = row * C + col), in (field
    velocity units)^2. F holds the background modes times the square root of the factor
    in use (:meth:`GPReconstructor.background_factor`: the last one fitted), then each component's
    stationary signal kernel (the fitted ``k1``, at zero time lag for a space-time
    kernel) on the water cells by its leading eigenpairs; ``d`` is what the dropped
    eigenpairs leave on the diagonal (exactly the kernel's variance minus the kept
    part) plus the state nugget (``gp.nugget_var_``); ``noise`` the fitted white variance less
    that nugget (the sensor's part). Land cells
    (``land`` True) get zero rows. Before any fit the kernels are the initial ones
    (length scale 3 cells, noise ``noise_std``) with a signal variance equal to the
    background's mean variance (or ``noise_std**2`` without one): the leg is planned on
    the structure of the prior, whose scale no sample has fixed yet.
    """
    X, Y = gp.grid_coords()
    R, C = X.shape
    N = R * C
    water = np.ones(N, bool) if land is None else ~np.asarray(land, bool).reshape(-1)
    wi = np.flatnonzero(water)
    Bg = None
    if gp.background is not None:
        Bg = gp.background_modes(X.shape) * np.sqrt(gp.background_factor())  # (m, 2, N)
        Bg[:, :, ~water] = 0.0
    kernels, fitted = gp.prior_kernels(Bg)
    Bg = gp.with_offset_modes(Bg, N, water)
    n_in = getattr(gp, "n_inputs_", 2) if fitted else 2
    pts = np.column_stack([X.ravel()[wi], Y.ravel()[wi]] + ([np.zeros(wi.size)] if n_in == 3 else []))
    rank_cap = int(gp.PRIOR_KERNEL_RANK if kernel_rank is None else kernel_rank)
    energy = float(gp.PRIOR_KERNEL_ENERGY if kernel_energy is None else kernel_energy)
    cols = [] if Bg is None else [Bg.reshape(Bg.shape[0], 2 * N).T]
    kcols, d, noise = kernel_factors(kernels, pts, wi, N, rank_cap, energy, gp.alpha)
    nug = gp.nugget_vars() if fitted else np.zeros(2)
    for k in range(2):  # the state nugget: the cell's own error, not the sensor's noise
        d[k * N + wi] += nug[k]
        noise[k * N : (k + 1) * N] -= nug[k]
    m = cols[0].shape[1] if cols else 0
    cols += kcols
    F = np.hstack(cols) if cols else np.zeros((2 * N, 0))
    return (F, d, noise, m) if with_mode_count else (F, d, noise)


def gp_mode_variance(gp, target, cells, Bg, modes, candidates, xy=None) -> float:
    """:func:`fit_mode_variance` under the prior of ``gp`` (a fitted
    :class:`~passt_mav.reconstruction.GPReconstructor`): its modes ``Bg`` (factors applied) and
    the fitted sensor noise, 0 unless the information criterion's 0.5 ln(2n) is paid (a factor
    fitted to noise drags a right forecast off). Without the samples' inputs ``xy`` the
    stationary kernels are left out (the background factor: see
    ``GPReconstructor.fit_background_scale``); with them (the ``bias`` fits) the prior is the one
    the posterior uses, kernels included, so that a mode spread over the whole region must explain
    what a local correction cannot: samples bunched in one corner show a local error, which
    against noise alone looks like an offset of the whole field."""
    n = len(target)
    if xy is None:
        base = np.diag(np.concatenate([np.full(n, float(gp.kernels_[k].k2.noise_level)) for k in range(2)]))
    else:
        base = kernel_blocks(gp.kernels_, xy)
    base[np.diag_indices_from(base)] += float(gp.alpha)
    return fit_mode_variance(target, cells, Bg, modes, candidates, base)


#: the share of the water region that must lie within the GP's longest correction reach of a
#: sample (:func:`sample_coverage`) before the ``bias`` modes, which change every cell, are fitted
#: at all: most of what they change must be where the GP itself would correct, not extrapolated
BIAS_MIN_COVERAGE = 0.5


def sample_coverage(gp, cells, shape, fc=None) -> float:
    """The share of the water cells (finite in the forecast ``fc`` (2, R, C); all without one) within
    the GP's longest correction reach of a sample's cell centre (``cells``: flat indices): the
    upper bound of its kernels' length scale (``max_length_cells`` cells, at most half the grid's
    diagonal; metres), beyond which no stationary correction of the GP reaches.

    Why it gates the ``bias`` modes: an offset or a rescaled forecast anomaly changes every cell,
    and samples bunched in one corner, as a random walk leaves them, cannot tell a local error
    from a global one (a local correction explains their residual as well as a global mode does;
    no likelihood can decide what happens where nothing was sampled). Fitted anyway, the global
    mode carries a corner's error over the region."""
    X, Y = gp.grid_coords()
    water = np.ones(int(np.prod(shape)), bool) if fc is None else np.isfinite(np.asarray(fc).reshape(2, -1)).all(0)
    if not water.any():
        return 0.0
    from passt_mav.reconstruction.kernels import length_bounds

    reach = length_bounds(X, Y, gp.max_length_cells)[1][1]
    idx = np.unique(cells)
    d2 = (X.ravel()[water][:, None] - X.ravel()[idx][None]) ** 2 + (
        Y.ravel()[water][:, None] - Y.ravel()[idx][None]
    ) ** 2
    return float(np.mean(d2.min(axis=1) <= reach**2))


def _fit_bias_modes(gp, target, cells, Bg, N: int, fc, xy) -> np.ndarray:
    """``Bg`` with the ``bias`` modes the samples keep appended: the offsets (``bias_var_``), then
    the forecast's anomaly (``scale_var_``), each fitted by :func:`gp_mode_variance`."""
    v0 = max(float(np.mean(target**2)), float(gp.noise_std) ** 2, 1e-12)
    gp.bias_var_ = gp_mode_variance(gp, target, cells, Bg, offset_modes(N), gp.bias_candidates(v0), xy)
    if gp.bias_var_ > 0:
        Bg = np.concatenate([Bg, offset_modes(N) * np.sqrt(gp.bias_var_)])
    anom = anomaly_mode(fc)
    if anom is not None:
        gp.scale_var_ = gp_mode_variance(gp, target, cells, Bg, anom, gp.bias_candidates(1.0), xy)
        if gp.scale_var_ > 0:
            Bg = np.concatenate([Bg, anom * np.sqrt(gp.scale_var_)])
    return Bg


def fit_prior_modes(gp, target, cells, shape, fc=None, xy=None) -> np.ndarray | None:
    """The low-rank prior modes of ``gp``'s next reconstruction, (m, 2, R*C) with their factors applied:
    the background modes (factor refitted when ``background_scale="ml"``), then with ``bias``
    the two offset modes and the forecast's own anomaly (``fc`` (2, R, C) minus its water
    mean) where the samples keep them (``bias_var_``, ``scale_var_`` refitted; both 0 when the
    samples see less than :data:`BIAS_MIN_COVERAGE` of the region, ``bias_coverage_``: see
    :func:`sample_coverage`); None when there are none."""
    N = int(np.prod(shape))
    Bg = np.zeros((0, 2, N))
    if gp.background is not None:
        Bg = gp.background_modes(shape)
        if gp.background_scale == "ml":
            gp.background_scale_ = gp.fit_background_scale(target, cells, Bg)
        Bg = Bg * np.sqrt(gp.background_factor())
    if gp.bias_on():
        gp.bias_coverage_ = sample_coverage(gp, cells, shape, fc)
        gp.bias_var_ = gp.scale_var_ = 0.0
        if gp.bias_coverage_ >= BIAS_MIN_COVERAGE:
            Bg = _fit_bias_modes(gp, target, cells, Bg, N, fc, xy)
    return Bg if Bg.shape[0] or gp.background is not None else None
