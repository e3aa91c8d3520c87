"""A low-rank background covariance for the residual GP, from the predictor's own roll-out.

Between legs the loop corrects the model's forecast with a GP fitted to the residuals
``samples - forecast``. A stationary kernel spreads a correction only a few cells from
the track; but a drifting model's error is not arbitrary: a wake whose shedding slips in
phase or grows in amplitude is wrong by a combination of the flow's own dominant
structures. Ensemble optimal interpolation (EnOI; Evensen 2003, Ocean Dynamics 53,
section 4.3; Oke et al. 2002) takes the background covariance from the anomalies of one
long model run. :func:`model_background` does exactly that with the campaign's
predictor, from the campaign's initial state, and returns the modes ``b_j`` with
``B = sum_j b_j b_j^T = A^T A / (n - 1)`` (A: the roll-out's anomalies about its time mean),
truncated to the leading POD modes. :class:`GPReconstructor` adds ``B`` to its stationary
kernels (``background=``), times a factor fitted on each leg's samples by maximum
marginal likelihood (``background_scale="ml"``): the roll-out's variability is the size of
the flow's changes, not of the model's error, which is ~0 while the model is right.

Frames and units: the modes are (m, 2, R, C) in the field's velocity units (channel 0 =
u east, 1 = v north), on the predictor's grid; land cells are NaN.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import ReconstructionError

__all__ = [
    "model_background",
    "background_steps_problem",
    "BACKGROUND_ENERGY",
    "BACKGROUND_MAX_MODES",
    "DEFAULT_BACKGROUND",
]

#: the product's roll-out length (snapshots) for the background (mission files, ``evaluate``,
#: ``paper``): 8 shedding periods of the cylinder wake, 200 h of the ocean default
DEFAULT_BACKGROUND = 200

#: fraction of the roll-out's anomaly energy the kept modes carry
BACKGROUND_ENERGY = 0.99
#: at most this many modes (a few leading modes carry a wake; an ocean needs more)
BACKGROUND_MAX_MODES = 40


def background_steps_problem(steps) -> str | None:
    """Why ``steps`` is not a valid background setting (0 = none, or a roll-out of >= 2
    snapshots), or ``None`` when it is. One rule for every layer that takes the setting
    (loop, campaign, ``paper``, mission file); each raises its own error type with it."""
    if int(steps) == 0 or int(steps) >= 2:
        return None
    return f"a background roll-out needs 0 (none) or at least 2 snapshots, got {steps}"


def model_background(
    predictor, state, steps: int, *, land=None, energy: float = BACKGROUND_ENERGY, max_modes: int = BACKGROUND_MAX_MODES
) -> np.ndarray | None:
    """Background covariance modes from ``steps`` predicted snapshots after ``state``.

    Args:
        predictor: fitted predictor, ``predict((2, R, C), steps) -> (steps, 2, R, C)``.
        state: (2, R, C) initial state (NaN on land: filled with 0 for the predictor).
        steps: roll-out length in snapshots (>= 2).
        land: (R, C) bool, True = land (default: where ``state`` is NaN).
        energy: keep the fewest leading modes that carry this fraction of the anomaly
            energy (the trace of ``B``), at most ``max_modes``.

    Returns (m, 2, R, C) float64 modes (NaN on land), or ``None`` when the roll-out does
    not vary (e.g. persistence): there is then no background to add.
    Raises :class:`ReconstructionError` when the roll-out is not finite.
    """
    s = np.asarray(state, dtype=np.float32)
    if s.ndim != 3 or s.shape[0] != 2:
        raise ReconstructionError(f"state must be (2, R, C), got {s.shape}")
    if int(steps) < 2:
        raise ReconstructionError(f"the background roll-out needs at least 2 steps, got {steps}")
    land = ~np.isfinite(s).all(axis=0) if land is None else np.asarray(land, bool)
    pred = np.asarray(predictor.predict(np.where(land, np.float32(0), np.nan_to_num(s)), int(steps)), dtype=np.float64)
    X = np.concatenate([np.where(land, 0.0, np.nan_to_num(s.astype(np.float64)))[None], pred], axis=0)
    X[:, :, land] = 0.0
    if not np.isfinite(X).all():
        raise ReconstructionError("the predictor's roll-out for the background covariance is not finite")
    n = X.shape[0]
    A = (X - X.mean(axis=0)).reshape(n, -1)
    # snapshot POD (Sirovich 1987): eigenvectors of the small n x n Gram matrix
    lam, V = np.linalg.eigh(A @ A.T)
    lam, V = lam[::-1], V[:, ::-1]
    total = float(lam.clip(min=0).sum())
    if total <= 1e-12 * max(float(np.abs(X).max()) ** 2 * A.size, 1e-30):
        return None
    keep = int(np.searchsorted(np.cumsum(lam.clip(min=0)) / total, float(energy)) + 1)
    keep = max(1, min(keep, int(max_modes), int((lam > 1e-12 * lam[0]).sum())))
    modes = (V[:, :keep].T @ A) * np.sqrt(1.0 / (n - 1))
    modes = modes.reshape((keep,) + X.shape[1:])
    modes[:, :, land] = np.nan
    return modes
