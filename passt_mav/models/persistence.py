"""Persistence: the field stays as it is, u(t + k) = u(t). The baseline every model must beat."""

from __future__ import annotations

import numpy as np

from passt_mav.models.base import Predictor, load_state_dict, read_metadata, write_checkpoint

__all__ = ["PersistencePredictor"]


class PersistencePredictor(Predictor):
    """``predict(state, steps)`` repeats ``state``; ``fit`` only records the grid shape."""

    name = "persistence"

    def __init__(self):
        self.grid_shape_ = None

    def fit(self, field, *, start: int | None = None, stop: int | None = None) -> PersistencePredictor:
        data = self._training_window(field, start, stop)
        self.grid_shape_ = tuple(int(x) for x in data.shape[2:])
        self.data_hash_ = field.data_hash() if hasattr(field, "data_hash") else None
        return self

    def _predict_batch(self, states: np.ndarray, steps: int) -> np.ndarray:
        return np.repeat(states[:, None], steps, axis=1)

    def save(self, path, *, command: str | None = None, extra: dict | None = None):
        import torch

        self._check_fitted()
        meta = {
            "predictor": self.name,
            "format": 1,
            "grid_shape": list(self.grid_shape_),
            "data_hash": self.data_hash_,
            "command": command,
            **(extra or {}),
        }
        return write_checkpoint(path, {"grid_shape": torch.tensor(self.grid_shape_)}, meta)

    @classmethod
    def load(cls, path) -> PersistencePredictor:
        meta = read_metadata(path)
        load_state_dict(path)  # the .pt must be there and readable
        self = cls()
        self.grid_shape_ = tuple(int(x) for x in meta["grid_shape"])
        self.data_hash_ = meta.get("data_hash")
        return self
