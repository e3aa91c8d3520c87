"""Predictors of flow fields: KNODE (torch), DMD, persistence; training, checkpoints, evaluation.

Importing this package is cheap (no torch): classes load on first use through
:data:`PREDICTORS` (see :mod:`passt_mav.models.base`).

    from passt_mav.models import make_predictor, load_predictor, shipped_model
    knode = load_predictor("builtin:cylinder")          # or a checkpoint path
    pred = knode.predict(state, 10)                     # (10, 2, R, C) float32
    dmd = make_predictor("dmd").fit(field, start=200, stop=300)
"""

from __future__ import annotations

from passt_mav.models.base import (
    PREDICTORS,
    SHIPPED,
    Predictor,
    load_predictor,
    make_predictor,
    predictor_class,
    read_metadata,
    shipped_model,
)

__all__ = [
    "PREDICTORS",
    "SHIPPED",
    "Predictor",
    "load_predictor",
    "make_predictor",
    "predictor_class",
    "read_metadata",
    "shipped_model",
]
