"""Reward maps: what a leg of the PASST loop tries to sample.

Every reward is a function ``f(prediction, *, cell_size_m=(dy, dx), std=None, state=None, info=None)``
returning a ``(rows, cols)`` float32 array in ``[0, 1]``. ``prediction`` is the
model's one-step-ahead field, ``(2, rows, cols)`` (u east, v north; row 0 south).
Cells where the prediction is NaN (land / missing) get reward 0; they are also
not traversable - :func:`traversable` gives that mask and the planners take it.

Registry: :data:`REWARDS`; :func:`compute_reward` is the one entry point.
Pure numpy; no I/O.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from passt_mav.errors import PlannerError

__all__ = [
    "REWARDS",
    "REWARDS_USING_STATE",
    "REWARDS_USING_STD",
    "compute_reward",
    "traversable",
    "speed",
    "vorticity",
    "std",
    "speed_std",
    "change",
    "variance_reduction",
    "REWARDS_USING_PRIOR",
]


def _check(prediction) -> np.ndarray:
    p = np.asarray(prediction, dtype=np.float64)
    if p.ndim != 3 or p.shape[0] != 2:
        raise PlannerError(f"reward needs a (2, rows, cols) prediction, got shape {p.shape}")
    return p


def traversable(prediction) -> np.ndarray:
    """``(rows, cols)`` bool: True where both components of the prediction are finite."""
    return np.isfinite(_check(prediction)).all(axis=0)


def _normalise(a: np.ndarray, valid: np.ndarray) -> np.ndarray:
    a = np.where(valid & np.isfinite(a), np.abs(a), 0.0)
    m = a.max() if a.size else 0.0
    return (a / m if m > 0 else a).astype(np.float32)


def _std_mag(std, shape) -> np.ndarray:
    if std is None:
        raise PlannerError("this reward needs the GP posterior std (std=...); none is available yet")
    s = np.asarray(std, dtype=np.float64)
    if s.ndim == 3 and s.shape[0] == 2:
        s = np.hypot(s[0], s[1])
    if s.shape != shape:
        raise PlannerError(f"std map shape {s.shape} does not match the grid {shape}")
    return s


def speed(prediction, *, cell_size_m=None, std=None, state=None, info=None) -> np.ndarray:
    """Predicted speed magnitude ``|u|`` normalised by its maximum (default reward)."""
    p = _check(prediction)
    return _normalise(np.hypot(p[0], p[1]), traversable(p))


def vorticity(prediction, *, cell_size_m=None, std=None, state=None, info=None) -> np.ndarray:
    """``|dv/dx - du/dy|`` by central differences (one-sided at edges) in metres.

    ``cell_size_m`` = (north-south, east-west) spacing in metres (default 1, 1).
    NaN neighbours make the derivative NaN there (reward 0), never zero-filled.
    """
    p = _check(prediction)
    dy, dx = (1.0, 1.0) if cell_size_m is None else (float(cell_size_m[0]), float(cell_size_m[1]))
    dv_dx = np.gradient(p[1], dx, axis=1)
    du_dy = np.gradient(p[0], dy, axis=0)
    return _normalise(dv_dx - du_dy, traversable(p))


def std(prediction, *, cell_size_m=None, std=None, state=None, info=None) -> np.ndarray:
    """GP posterior standard deviation ``hypot(std_u, std_v)``, normalised."""
    p = _check(prediction)
    return _normalise(_std_mag(std, p.shape[1:]), traversable(p))


def speed_std(prediction, *, cell_size_m=None, std=None, state=None, info=None) -> np.ndarray:
    """Product of the normalised speed and normalised GP std (fast AND uncertain)."""
    p = _check(prediction)
    s = speed(p).astype(np.float64) * _std_mag(std, p.shape[1:])
    return _normalise(s, traversable(p))


def change(prediction, *, cell_size_m=None, std=None, state=None, info=None) -> np.ndarray:
    """Predicted change ``|prediction - state|`` (vector magnitude), normalised.

    ``state``: (2, rows, cols), the field the prediction starts from (the loop passes
    the leg's initial state and its forecast at the leg's end). Why it is a reward: a
    model whose structures drift in phase or position errs by about
    ``|du/dt| x (its timing error)``, so the cells predicted to change most are where
    the forecast - and the reconstruction's prior - is least reliable. On the cylinder
    wakes it does worse than ``speed`` (sampling only where the wake moves leaves the rest
    of the field uncorrected: docs/research/2026-11-28-docstring-history.md); an option for
    other fields.
    """
    p = _check(prediction)
    if state is None:
        raise PlannerError("the 'change' reward needs the state the prediction starts from (state=...)")
    s0 = _check(state)
    if s0.shape != p.shape:
        raise PlannerError(f"state shape {s0.shape} does not match the prediction {p.shape}")
    d = p - s0
    return _normalise(np.hypot(d[0], d[1]), traversable(p) & traversable(s0))


def variance_reduction(prediction, *, cell_size_m=None, std=None, state=None, info=None) -> np.ndarray:
    """The error variance one sample at each cell would remove from the next reconstruction.

    ``info``: a :class:`passt_mav.planning.information.InformationModel` of the prior the
    reconstruction will use (the loop builds it from its GP: background modes, fitted
    kernels, sensor noise; conditioned on cells other boats sample this leg). A-optimal
    design (Krause, Singh & Guestrin 2008); the whole path's value, with the interaction of
    its cells, is what :class:`passt_mav.planning.information.InformationPlanner` scores.
    Normalised by the map's maximum; land 0.
    """
    p = _check(prediction)
    if info is None:
        raise PlannerError("the 'variance_reduction' reward needs the reconstruction's prior (info=...)")
    g = np.asarray(info.gains(), dtype=np.float64)
    if g.shape != p.shape[1:]:
        raise PlannerError(f"information model grid {g.shape} does not match the prediction {p.shape[1:]}")
    return _normalise(g, traversable(p))


#: rewards that read the GP posterior std (the loop computes it only for these)
REWARDS_USING_STD = frozenset({"std", "speed_std"})
#: rewards that compare the prediction with the state it starts from (``state=``)
REWARDS_USING_STATE = frozenset({"change"})
#: rewards that read the reconstruction's prior covariance (``info=``)
REWARDS_USING_PRIOR = frozenset({"variance_reduction"})

#: name -> reward function
REWARDS: dict[str, Callable[..., np.ndarray]] = {
    "speed": speed,
    "vorticity": vorticity,
    "std": std,
    "speed_std": speed_std,
    "change": change,
    "variance_reduction": variance_reduction,
}


def compute_reward(name: str, prediction, *, cell_size_m=None, std=None, state=None, info=None) -> np.ndarray:
    """The reward map ``(rows, cols)`` float32 in [0, 1] named ``name`` (see :data:`REWARDS`).

    ``state``: the field ``prediction`` starts from, for :data:`REWARDS_USING_STATE`;
    ``info``: the reconstruction's prior, for :data:`REWARDS_USING_PRIOR`.
    """
    try:
        fn = REWARDS[name]
    except KeyError:
        raise PlannerError(f"unknown reward {name!r}; choose one of {', '.join(REWARDS)}") from None
    return fn(prediction, cell_size_m=cell_size_m, std=std, state=state, info=info)
