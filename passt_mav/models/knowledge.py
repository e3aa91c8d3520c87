"""Linear knowledge for the KNODE: DMD's operator in continuous time (``knowledge="dmd"``).

The KNODE's right-hand side becomes

    dz/dt = L z + K N(z)

with ``K N`` the learned convolutional correction of :mod:`passt_mav.models.knode` and ``L`` a
fixed linear operator fitted from the training part of the window. ``z`` is the KNODE's scaled
state (``z = (u - mean) / std`` per pixel, land 0), time in snapshot intervals.

``L`` is DMD's: :class:`~passt_mav.models.dmd.DMDPredictor` is fitted on the training snapshots
(field units, time mean ``m`` removed, POD basis ``U`` (n, r), discrete operator ``A`` (r, r),
``x_{k+1} - m = U A U^T (x_k - m)``) and turned into continuous time by the principal matrix
logarithm, ``A_c = log(A) / dt`` with ``dt`` = 1 snapshot interval (``scipy.linalg.logm``). In the
DMD coordinates ``y = x - m = std * z + (mean - m)`` (the scaler's mean and DMD's coincide when
both come from the same snapshots; a fine-tuned model keeps its start model's scaler, so the
offset is kept general), the linear dynamics are

    dy/dt = U A_c U^T y - kappa (I - U U^T) y

``complement`` says what happens to the part of the state outside DMD's r-dimensional subspace
(:func:`complement_rate`): ``"keep"`` (kappa = 0, it persists; the correction may move it),
``"drop"`` (kappa -> infinity, DMD's own projection; the correction's out-of-subspace part is then
dropped too) or a rate kappa >= 0 per snapshot interval (it decays as ``exp(-kappa t)``: a state
DMD's subspace cannot hold, such as a displaced wake, is trusted for about ``1 / kappa`` snapshots).

Integration: the linear part is integrated exactly (integrating-factor or "Lawson" Euler): one
sub-step of length ``h`` is ``z <- E_h (z + h K N(z))`` with ``E_h = exp(h L)``, so with the
correction at zero one snapshot step is ``exp(L) z``, which for ``complement="drop"`` is DMD's
one-step prediction ``U A U^T y`` (to float32 rounding, as ``exp(log A) = A``). Explicit Euler on
``L`` would be unstable for DMD's oscillatory modes (``|1 + i w h| > 1``); :meth:`rhs` gives ``L z``
for checking the continuous-time operator with any integrator.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import ModelError

__all__ = ["COMPLEMENTS", "complement_rate", "continuous_operator", "fit_dmd_knowledge", "LinearKnowledge"]

#: what the linear term does outside DMD's subspace, by name (or a decay rate, see complement_rate)
COMPLEMENTS = {"keep": 0.0, "drop": float("inf")}


def complement_rate(complement) -> float:
    """The decay rate kappa (per snapshot interval) of ``complement``: ``"keep"`` 0, ``"drop"`` infinity,
    or a number >= 0 (also as a string, as the command line gives it)."""
    if isinstance(complement, str) and complement in COMPLEMENTS:
        return COMPLEMENTS[complement]
    try:
        rate = float(complement)
    except (TypeError, ValueError):
        rate = float("nan")
    if isinstance(complement, bool) or not rate >= 0:
        raise ModelError(
            f"knowledge complement must be keep, drop or a decay rate >= 0 per snapshot interval, got {complement!r}"
        )
    return rate


def continuous_operator(A: np.ndarray) -> tuple[np.ndarray, dict]:
    """``(A_c, info)``: the real principal logarithm of the discrete ``(r, r)`` operator ``A`` (per
    snapshot interval), so that ``expm(A_c) = A``. ``info``: ``"logm_imag"`` (the largest imaginary
    part dropped; non-zero only when ``A`` has negative real eigenvalues) and ``"expm_error"``
    (``max |expm(A_c) - A|``: how far the real ``A_c`` is from reproducing ``A``)."""
    from scipy.linalg import expm, logm

    A = np.asarray(A, dtype=np.float64)
    lam = np.linalg.eigvals(A)
    if np.min(np.abs(lam)) < 1e-12:
        raise ModelError(
            "DMD operator has an eigenvalue at 0 (a mode that vanishes in one step has no continuous-time rate); use a lower knowledge rank"
        )
    Ac = logm(A)
    imag = float(np.max(np.abs(np.imag(Ac)))) if np.iscomplexobj(Ac) else 0.0
    Ac = np.real(Ac)
    return Ac, {"logm_imag": imag, "expm_error": float(np.max(np.abs(expm(Ac) - A)))}


def fit_dmd_knowledge(
    train: np.ndarray, water: np.ndarray, mean: np.ndarray, std: np.ndarray, *, rank, energy, complement="keep"
):
    """``(module, info)``: a :class:`LinearKnowledge` from DMD fitted on ``train``, and what the fit found.

    ``train``: ``(T, 2, R, C)`` field units (NaN = land); ``water`` ``(R, C)`` bool; ``mean``/``std``
    ``(2, R, C)``: the KNODE's scaler (field units; std 1 on land). ``rank``/``energy``: DMD's
    truncation (:class:`~passt_mav.models.dmd.DMDPredictor`). ``info``: ``rank``, ``eig_abs_max``,
    ``n_snapshots`` (how many snapshots DMD was fitted on) and :func:`continuous_operator`'s checks.
    """
    from passt_mav.models.dmd import DMDPredictor

    dmd = DMDPredictor(rank=rank, energy=energy).fit(np.where(water, train, np.nan).astype(np.float32))
    Ac, info = continuous_operator(dmd.A_)
    R, C = water.shape
    idx = np.flatnonzero(np.broadcast_to(water, (2, R, C)).ravel())
    U = np.zeros((2 * R * C, dmd.rank_))
    U[idx] = dmd.modes_
    offset = np.zeros(2 * R * C)
    offset[idx] = np.asarray(mean, np.float64).ravel()[idx] - dmd.mean_
    info.update(rank=int(dmd.rank_), eig_abs_max=float(np.max(np.abs(dmd.eigs_))), n_snapshots=int(train.shape[0]))
    return LinearKnowledge(U, Ac, np.asarray(std, np.float64).ravel(), offset, complement), info


def _build_class():
    import torch

    class _LinearKnowledge(torch.nn.Module):
        """``L`` on ``(B, 2, R, C)`` scaled states (see module docstring); buffers: ``U`` (n, r) DMD modes
        (zero rows on land), ``Ac`` (r, r) per snapshot interval, ``scale`` (n,) the scaler's std (1 on
        land), ``offset`` (n,) scaler mean minus DMD mean (field units), ``decay`` the complement's decay
        rate kappa per snapshot interval (``inf``: dropped)."""

        def __init__(self, U, Ac, scale, offset, complement="keep"):
            super().__init__()
            rate = complement_rate(complement)
            f = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
            self.register_buffer("U", f(U))
            self.register_buffer("Ac", f(Ac))
            self.register_buffer("scale", f(scale))
            self.register_buffer("offset", f(offset))
            self.register_buffer("decay", torch.tensor(rate, dtype=torch.float64))
            self._prop: dict = {}

        def _propagator(self, h: float):
            """``(M, d)``: ``exp(h L) y = d y + U M U^T y`` in DMD coordinates, ``M = expm(h Ac) - d I``."""
            key = (float(h), self.U.device, float(self.decay))
            if key not in self._prop:
                r = self.Ac.shape[0]
                d = float(torch.exp(-self.decay * float(h)))
                E = torch.linalg.matrix_exp(self.Ac.double() * float(h))
                self._prop = {key: ((E - d * torch.eye(r, dtype=E.dtype, device=E.device)).float(), d)}
            return self._prop[key]

        def _to_y(self, z):
            return z.flatten(1) * self.scale + self.offset

        def _to_z(self, y, like):
            return ((y - self.offset) / self.scale).view_as(like)

        def propagate(self, z, h: float):
            """``exp(h L) z``: the linear dynamics over ``h`` snapshot intervals, exactly."""
            M, d = self._propagator(h)
            y = self._to_y(z)
            return self._to_z(d * y + (y @ self.U) @ M.T @ self.U.T, z)

        def rhs(self, z):
            """``L z`` (finite decay rates only; ``"drop"`` has an infinite rate off the subspace)."""
            kappa = float(self.decay)
            if kappa == float("inf"):
                raise ModelError("the dropped complement has no finite rate; use a finite complement for L z")
            y = self._to_y(z)
            a = y @ self.U
            return ((a @ self.Ac.T @ self.U.T - kappa * (y - a @ self.U.T)) / self.scale).view_as(z)

        def step(self, net, z, substeps: int):
            """One snapshot interval of ``dz/dt = L z + net(z)``: ``substeps`` integrating-factor Euler steps."""
            h = 1.0 / int(substeps)
            for _ in range(int(substeps)):
                z = self.propagate(z + h * net(z), h)
            return z

    return _LinearKnowledge


_CLASS = None


def LinearKnowledge(U, Ac, scale, offset, complement="keep"):
    """Build the linear knowledge module (a ``torch.nn.Module``); see module docstring for the arguments."""
    global _CLASS
    if _CLASS is None:
        _CLASS = _build_class()
    return _CLASS(U, Ac, scale, offset, complement)
