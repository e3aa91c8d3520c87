"""How wrong a map says it is, against how wrong it is: calibration of a Gaussian estimate.

An estimate is a mean ``mu`` and a standard deviation ``s`` per cell and component (u east, v north;
arrays ``(..., 2, rows, cols)``, field units), read as independent Gaussians ``N(mu, s^2)``. Against the
truth ``x`` (where it is known):

* ``coverage95``: the share of the valid (cell, component) pairs with ``|x - mu| <= 1.96 s`` (the central
  95 % interval); 0.95 for a calibrated map, well below it when the map is overconfident;
* ``nlpd``: the mean negative log predictive density, ``0.5 ln(2 pi s^2) + (x - mu)^2 / (2 s^2)``, in nats
  per (cell, component): lower is better, and it punishes both an overconfident map (small ``s``, large
  error) and a timid one (large ``s``). Samples drawn from ``N(mu, s^2)`` give ``0.5 ln(2 pi e s^2)`` on
  average;
* ``z_rms``: the root mean square of the standardised error ``(x - mu) / s`` (1 when calibrated);
* :func:`reliability`: the share of pairs inside the central ``p`` interval for each ``p`` (the
  reliability diagram: the diagonal when calibrated).

A pair is valid where the mean, the std and the truth are all finite and the std is > 0; others
(land, missing) are left out, never counted as zero error. Pure numpy, no I/O.

:func:`trivial_scores`: the RMSE of the maps a scientist compares a map with before trusting it
(zero current, the time mean of the forecast), beside the map's own.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "Z95",
    "RELIABILITY_LEVELS",
    "calibration",
    "coverage",
    "nlpd",
    "reliability",
    "z_rms",
    "trivial_scores",
    "beaten_by",
]

#: the half-width of the central 95 % interval in standard deviations
Z95 = 1.959963984540054
#: the central-interval probabilities a reliability diagram reads (:func:`reliability`)
RELIABILITY_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99)


def _pairs(mean, std, truth) -> tuple[np.ndarray, np.ndarray]:
    """(error x - mu, std) over the valid pairs, float64 1-D."""
    m, s, t = (np.asarray(a, np.float64) for a in (mean, std, truth))
    if not (m.shape == s.shape == t.shape):
        raise ValueError(f"mean {m.shape}, std {s.shape} and truth {t.shape} must have one shape")
    ok = np.isfinite(m) & np.isfinite(s) & np.isfinite(t) & (s > 0)
    return (t - m)[ok], s[ok]


def _z_for(p: float) -> float:
    """Half-width in std of the central ``p`` interval of a Gaussian (``Phi^-1((1 + p) / 2)``)."""
    from scipy.special import ndtri

    return float(ndtri(0.5 * (1.0 + float(p))))


def coverage(mean, std, truth, p: float = 0.95) -> float | None:
    """Share of valid pairs whose truth lies within the central ``p`` interval ``mu +- z_p s`` (None: none valid)."""
    e, s = _pairs(mean, std, truth)
    if e.size == 0:
        return None
    z = Z95 if p == 0.95 else _z_for(p)
    return float(np.mean(np.abs(e) <= z * s))


def nlpd(mean, std, truth) -> float | None:
    """Mean negative log density of the truth under ``N(mu, s^2)`` per valid pair (nats; None: none valid)."""
    e, s = _pairs(mean, std, truth)
    if e.size == 0:
        return None
    return float(np.mean(0.5 * np.log(2.0 * math.pi * s**2) + 0.5 * (e / s) ** 2))


def z_rms(mean, std, truth) -> float | None:
    """RMS of the standardised error ``(x - mu) / s`` over valid pairs (1 when calibrated; None: none valid)."""
    e, s = _pairs(mean, std, truth)
    if e.size == 0:
        return None
    return float(np.sqrt(np.mean((e / s) ** 2)))


def reliability(mean, std, truth, levels=RELIABILITY_LEVELS) -> list[float] | None:
    """For each central-interval probability in ``levels``, the share of valid pairs inside it (None: none valid)."""
    e, s = _pairs(mean, std, truth)
    if e.size == 0:
        return None
    a = np.abs(e) / s
    return [float(np.mean(a <= _z_for(p))) for p in levels]


def calibration(mean, std, truth) -> dict | None:
    """The figures of a map against the truth: ``coverage95``, ``nlpd`` (nats), ``z_rms``, ``n`` (valid
    pairs) and ``reliability`` (share inside each of :data:`RELIABILITY_LEVELS`); None when no pair is
    valid (no std, or no truth)."""
    if mean is None or std is None or truth is None:
        return None
    e, s = _pairs(mean, std, truth)
    if e.size == 0:
        return None
    z = e / s
    a = np.abs(z)
    return {
        "coverage95": float(np.mean(a <= Z95)),
        "nlpd": float(np.mean(0.5 * np.log(2.0 * math.pi * s**2) + 0.5 * z**2)),
        "z_rms": float(np.sqrt(np.mean(z**2))),
        "n": int(e.size),
        "reliability": [float(np.mean(a <= _z_for(p))) for p in RELIABILITY_LEVELS],
    }


def _rmse(a, truth) -> float | None:
    a, t = np.asarray(a, np.float64), np.asarray(truth, np.float64)
    ok = np.isfinite(a).all(axis=-3) & np.isfinite(t).all(axis=-3)
    if not ok.any():
        return None
    d = np.moveaxis(a - t, -3, 0)[:, ok]
    return float(np.sqrt(np.mean(d**2)))


def trivial_scores(estimate, truth, forecast_mean=None) -> dict | None:
    """RMSE (field units, over the cells known in all arrays) of the trivial maps against ``truth``
    ``(2, R, C)``: ``zero`` (no current) and, given ``forecast_mean`` ``(2, R, C)`` (the time mean of
    the forecast), ``forecast_mean``; with ``estimate`` the map's own as ``map``. None without a truth."""
    if truth is None:
        return None
    t = np.asarray(truth, np.float64)
    known = np.isfinite(t).all(axis=0)
    if estimate is not None:
        known &= np.isfinite(np.asarray(estimate, np.float64)).all(axis=0)
    if forecast_mean is not None:
        known &= np.isfinite(np.asarray(forecast_mean, np.float64)).all(axis=0)
    tk = np.where(known, t, np.nan)
    out = {"zero": _rmse(np.where(known, 0.0, np.nan) * np.ones_like(t), tk)}
    if forecast_mean is not None:
        out["forecast_mean"] = _rmse(forecast_mean, tk)
    if estimate is not None:
        out["map"] = _rmse(estimate, tk)
    return out


def beaten_by(scores: dict | None) -> list[str]:
    """The trivial maps in ``scores`` (:func:`trivial_scores`) whose RMSE is at most the map's own."""
    if not scores or scores.get("map") is None:
        return []
    return [k for k, v in scores.items() if k != "map" and v is not None and v <= scores["map"]]
