"""A leg's map scored against the truth where it is known: calibration of its std and the trivial maps.

What a run records beside a leg's RMSE (``leg.json`` ``calibration`` and ``baselines``; the campaign's
``results.json``): the figures of :func:`passt_mav.models.calibration.calibration` (``coverage95``,
``nlpd``, ``z_rms``, ``n``, ``reliability``) of the estimate and its posterior std, and the RMSE of the
trivial maps a scientist compares with (:func:`passt_mav.models.calibration.trivial_scores`: no current,
the time mean of the model's forecast), with ``beaten_by`` naming those at least as good as the map.
Pure (no I/O).
"""

from __future__ import annotations

import numpy as np

from passt_mav.models.calibration import beaten_by, calibration, trivial_scores

__all__ = ["leg_scores", "beaten_message", "TRIVIAL_LABELS"]

#: how a line names each trivial map
TRIVIAL_LABELS = {"zero": "zero current", "forecast_mean": "the forecast's time mean"}


def leg_scores(state, std, truth, forecast_mean=None) -> tuple[dict | None, dict | None]:
    """(calibration of ``state`` (2, R, C) with ``std`` (2, R, C) or None vs ``truth`` (2, R, C) or None,
    the trivial maps' RMSE with ``map`` and ``beaten_by``); field units; (None, None) without a truth."""
    if truth is None:
        return None, None
    cal = None if std is None else calibration(state, std, truth)
    fm = None if forecast_mean is None else np.asarray(forecast_mean, np.float64)
    base = trivial_scores(state, truth, fm)
    if base is not None:
        base["beaten_by"] = beaten_by(base)
    return cal, base


def beaten_message(base: dict | None, label: str, unit_text=str) -> str | None:
    """One line when the map of ``label`` does not beat a trivial map (``base``: :func:`leg_scores`'s second
    value; ``unit_text``: field units -> text), else None."""
    if not base or not base.get("beaten_by"):
        return None
    names = " or ".join(f"{TRIVIAL_LABELS.get(k, k)} (RMSE {unit_text(base[k])})" for k in base["beaten_by"])
    return f"{label}: the map (RMSE {unit_text(base['map'])}) does not beat {names}"
