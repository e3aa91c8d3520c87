"""The predictor interface, its registry, and checkpoint loading.

A predictor forecasts a flow field from one snapshot:

* ``fit(field, *, start=None, stop=None) -> self`` learns from snapshots
  ``start .. stop-1`` of a :class:`~passt_mav.fields.field.FlowField`;
* ``predict(state, steps)``: ``state`` float32 ``(2, rows, cols)`` (u east, v
  north; row 0 south) -> ``(steps, 2, rows, cols)``, the snapshots 1 .. steps
  intervals after it; a batch ``(B, 2, rows, cols)`` -> ``(B, steps, 2, rows, cols)``.
  NaN is rejected (callers fill land cells before predicting, see ``loop/passt.py``).
* ``save(path)`` writes ``PATH.pt`` (a ``state_dict`` of tensors) and
  ``PATH.json`` (metadata); :func:`load_predictor` reads it back with
  ``torch.load(..., weights_only=True)``. Nothing is pickled.

``PREDICTORS`` maps a name to ``"module:Class"``; classes are imported on first use
so that importing this module costs no torch import.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from passt_mav.errors import ModelError

__all__ = [
    "PREDICTORS",
    "Predictor",
    "make_predictor",
    "load_predictor",
    "predictor_class",
    "read_metadata",
    "SHIPPED",
    "shipped_model",
]

#: name -> "module:Class". Room for "lstm", "transformer", ... later.
PREDICTORS: dict[str, str] = {
    "knode": "passt_mav.models.knode:KnodePredictor",
    "dmd": "passt_mav.models.dmd:DMDPredictor",
    "persistence": "passt_mav.models.persistence:PersistencePredictor",
}

MODELS_DIR = Path(__file__).resolve().parent.parent / "assets" / "models"
#: shipped default checkpoints (without suffix), see passt_mav/assets/README.md
SHIPPED: dict[str, Path] = {
    "cylinder": MODELS_DIR / "knode_cylinder",
    "ocean": MODELS_DIR / "knode_ocean",
    # an alternative for the cylinder wakes: the KNODE with DMD's operator as knowledge (docs/knode-dmd.md)
    "cylinder-dmd": MODELS_DIR / "knode_cylinder_dmd",
}


def shipped_model(name: str) -> Path:
    """Path (``.pt``; metadata beside it as ``.json``) of a shipped KNODE: a key of :data:`SHIPPED`."""
    if name not in SHIPPED:
        raise ModelError(f"no shipped model {name!r}; choose one of {', '.join(SHIPPED)}")
    p = SHIPPED[name].with_suffix(".pt")
    if not p.exists():
        raise ModelError(
            f"shipped model {p} is missing; train it with the command recorded in passt_mav/assets/README.md (--out {SHIPPED[name]})"
        )
    return p


def predictor_class(name: str) -> type:
    """The class registered under ``name`` (unknown names raise :class:`ModelError` listing the valid ones)."""
    if name not in PREDICTORS:
        raise ModelError(f"unknown predictor {name!r}; choose one of {', '.join(PREDICTORS)}")
    mod, cls = PREDICTORS[name].split(":")
    return getattr(importlib.import_module(mod), cls)


def make_predictor(name: str, **kw: Any) -> Predictor:
    """An unfitted predictor ``name`` with keyword hyper-parameters ``kw``."""
    cls = predictor_class(name)
    try:
        return cls(**kw)
    except TypeError as exc:
        raise ModelError(f"bad option for predictor {name!r}: {exc}") from None


def _paths(path: str | Path) -> tuple[Path, Path]:
    p = Path(path)
    if not p.name:  # '' or '/': a folder, no file name to add .pt / .json to
        raise ModelError(f"{str(path)!r} is no checkpoint path (a checkpoint is PATH.pt + PATH.json)")
    if p.suffix in (".pt", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".pt"), p.with_name(p.name + ".json")


def read_metadata(path: str | Path) -> dict:
    """The JSON metadata of a checkpoint (``PATH``, ``PATH.pt`` or ``PATH.json``)."""
    _, jp = _paths(path)
    if not jp.exists():
        raise ModelError(f"checkpoint metadata {jp} not found (a checkpoint is PATH.pt + PATH.json)")
    try:
        return json.loads(jp.read_text())
    except (OSError, ValueError, RecursionError) as exc:
        why = "nested too deep" if isinstance(exc, RecursionError) else exc
        raise ModelError(f"cannot read checkpoint metadata {jp}: {why}") from None


def load_predictor(spec: str | Path) -> Predictor:
    """A fitted predictor from a checkpoint path or ``builtin:NAME``.

    ``NAME`` is a key of :data:`SHIPPED` (the shipped KNODE checkpoints: ``cylinder``, ``ocean``,
    ``cylinder-dmd``). ``shipped:NAME``
    is the old spelling, still accepted (deprecated; one spelling everywhere: ``builtin:``,
    as in mission files and ``passt-mav evaluate``).
    """
    s = str(spec)
    for prefix in ("shipped:", "builtin:"):
        if s.startswith(prefix):
            s = str(shipped_model(s[len(prefix) :]))
            break
    meta = read_metadata(s)
    name = meta.get("predictor")
    cls = predictor_class(name) if name in PREDICTORS else None
    if cls is None:
        raise ModelError(f"checkpoint {s} names no known predictor ({name!r}); choose one of {', '.join(PREDICTORS)}")
    return cls.load(s)


def load_state_dict(path: str | Path) -> dict:
    """``torch.load(PATH.pt, weights_only=True)`` with errors turned into :class:`ModelError`."""
    import torch

    pt, _ = _paths(path)
    if not pt.exists():
        raise ModelError(f"checkpoint {pt} not found")
    try:
        return torch.load(pt, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is the user's file
        raise ModelError(f"cannot read checkpoint {pt}: {exc}") from None


def write_checkpoint(path: str | Path, state: dict, meta: dict) -> Path:
    """Write ``PATH.pt`` (tensors only) and ``PATH.json``; returns the ``.pt`` path."""
    import torch

    pt, jp = _paths(path)
    pt.parent.mkdir(parents=True, exist_ok=True)
    torch.save({k: torch.as_tensor(v).detach().cpu().contiguous() for k, v in state.items()}, pt)
    jp.write_text(json.dumps(meta, indent=1) + "\n")
    return pt


class Predictor:
    """Base class: input checks and single/batch handling; subclasses implement ``_predict_batch``.

    Subclasses set ``name`` (their registry key) and the learned ``grid_shape_``.
    """

    name = "base"

    # -- the edge: validate once ---------------------------------------------------
    def _check_fitted(self) -> None:
        if getattr(self, "grid_shape_", None) is None:
            raise ModelError(f"{type(self).__name__} is not fitted; call fit(field) or load a checkpoint")

    def _training_window(self, field, start, stop) -> np.ndarray:
        """``(T, 2, R, C)`` float32 snapshots ``start..stop-1`` of ``field`` (checked)."""
        data = field.data if hasattr(field, "data") else np.asarray(field, np.float32)
        if data.ndim != 4 or data.shape[1] != 2:
            raise ModelError(f"training data must be (time, 2, rows, cols), got {data.shape}")
        n = data.shape[0]
        a = 0 if start is None else int(start)
        b = n if stop is None else int(stop)
        if not (0 <= a < b <= n) or b - a < 2:
            raise ModelError(
                f"training window {a}..{b} invalid for {n} snapshots (need 0 <= start < stop <= {n}, at least 2 snapshots)"
            )
        return np.asarray(data[a:b], dtype=np.float32)

    def predict(self, state, steps: int) -> np.ndarray:
        """``(2,R,C)`` -> ``(steps,2,R,C)``; ``(B,2,R,C)`` -> ``(B,steps,2,R,C)``; float32."""
        self._check_fitted()
        if isinstance(steps, bool) or int(steps) != steps or int(steps) < 1:
            raise ModelError(f"steps must be a positive integer, got {steps!r}")
        s = np.asarray(state, dtype=np.float32)
        single = s.ndim == 3
        if single:
            s = s[None]
        if s.ndim != 4 or s.shape[1:] != (2, *self.grid_shape_):
            raise ModelError(
                f"state must be (2, {self.grid_shape_[0]}, {self.grid_shape_[1]}) or a batch of those, got {np.shape(state)}"
            )
        if not np.isfinite(s).all():
            raise ModelError(
                "state holds NaN/inf: land is masked by the loop, and a field's gaps that come and go are filled "
                "by FlowField.state_at (never with 0)"
            )
        out = np.asarray(self._predict_batch(s, int(steps)), dtype=np.float32)
        return out[0] if single else out

    def _predict_batch(self, states: np.ndarray, steps: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self) -> str:
        kw = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if not k.endswith("_") and not k.startswith("_"))
        return f"{type(self).__name__}({kw})"
