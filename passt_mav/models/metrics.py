"""Forecast error metrics on ``(..., 2, rows, cols)`` velocity arrays (u east, v north).

Cells where the truth is NaN (land, missing) are left out of every average.
"""

from __future__ import annotations

import numpy as np

__all__ = ["mse", "cosine_distance"]


def mse(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean squared error over every finite (time, channel, cell) of ``true`` (units^2)."""
    p = np.asarray(pred, np.float64)
    t = np.asarray(true, np.float64)
    ok = np.isfinite(t) & np.isfinite(p)
    if not ok.any():
        return float("nan")
    return float(np.mean((p[ok] - t[ok]) ** 2))


def cosine_distance(pred: np.ndarray, true: np.ndarray, *, eps: float = 1e-12) -> float:
    """Mean over cells of ``1 - cos(angle)`` between predicted and true velocity vectors.

    0 = same direction everywhere, 1 = orthogonal on average, 2 = opposite. Cells where
    either vector has (near) zero length or the truth is NaN are left out.
    """
    p = np.asarray(pred, np.float64)
    t = np.asarray(true, np.float64)
    ch = p.ndim - 3  # channel axis
    dot = np.sum(p * t, axis=ch)
    n = np.sqrt(np.sum(p * p, axis=ch) * np.sum(t * t, axis=ch))
    ok = np.isfinite(dot) & (n > eps)
    if not ok.any():
        return float("nan")
    return float(np.mean(1.0 - dot[ok] / n[ok]))
