"""DMD: dynamic mode decomposition, a linear one-step operator fitted by SVD.

Written by hand with numpy rather than with PyDMD: PyDMD is not a dependency of
this project (not installed), and what is needed is ~20 lines of linear algebra
(Schmid 2010, "projected" DMD) that are easier to check than a wrapper.

With snapshots ``x_0..x_{T-1}`` (water cells of both channels flattened) and the
time mean ``m`` removed (``center=True``; the mean flow is a fixed point, otherwise
DMD has to spend a mode with eigenvalue ~1 on it), ``X = [x_0..x_{T-2}] - m``,
``Y = [x_1..x_{T-1}] - m``, ``X = U S V^T`` truncated to rank ``r`` and

    A_r = U^T Y V S^-1   (r x r),   x_{k+1} = m + U A_r U^T (x_k - m).

The rank is ``rank`` when given, else the smallest reaching ``energy`` of
sum(S^2). With ``stable=True`` eigenvalues of ``A_r`` outside the unit circle are
pulled onto it, so long forecasts do not blow up from a slightly unstable mode
(a limit cycle such as vortex shedding has |lambda| = 1 exactly).
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import ModelError
from passt_mav.models.base import Predictor, load_state_dict, read_metadata, write_checkpoint

__all__ = ["DMDPredictor"]


class DMDPredictor(Predictor):
    """DMD predictor (see module docstring). Learned: ``modes_`` (n, r), ``A_`` (r, r), ``mean_``, ``water_``, ``rank_``, ``eigs_``."""

    name = "dmd"

    def __init__(self, *, rank: int | None = None, energy: float = 0.999, center: bool = True, stable: bool = True):
        self.rank = rank
        self.energy = energy
        self.center = center
        self.stable = stable
        self.grid_shape_ = None

    def fit(self, field, *, start: int | None = None, stop: int | None = None) -> DMDPredictor:
        data = self._training_window(field, start, stop).astype(np.float64)
        T, _, R, C = data.shape
        water = np.isfinite(data).all(axis=(0, 1))
        if not water.any():
            raise ModelError("training window has no cell with data at every time")
        flat = data[:, :, water].reshape(T, -1).T  # (n, T)
        mean = flat.mean(axis=1) if self.center else np.zeros(flat.shape[0])
        X, Y = flat[:, :-1] - mean[:, None], flat[:, 1:] - mean[:, None]
        U, S, Vt = np.linalg.svd(X, full_matrices=False)
        keep = S > S[0] * 1e-10
        U, S, Vt = U[:, keep], S[keep], Vt[keep]
        if self.rank is not None:
            if int(self.rank) < 1:
                raise ModelError(f"rank must be >= 1, got {self.rank}")
            r = min(int(self.rank), len(S))
        else:
            if not 0 < self.energy <= 1:
                raise ModelError(f"energy must be in (0, 1], got {self.energy}")
            r = int(np.searchsorted(np.cumsum(S**2) / np.sum(S**2), self.energy) + 1)
            r = min(r, len(S))
        U, S, Vt = U[:, :r], S[:r], Vt[:r]
        A = U.T @ Y @ Vt.T / S[None, :]
        lam, W = np.linalg.eig(A)
        if self.stable and np.any(np.abs(lam) > 1):
            lam = np.where(np.abs(lam) > 1, lam / np.abs(lam), lam)
            A = np.real(W @ np.diag(lam) @ np.linalg.inv(W))
        self.modes_, self.A_, self.mean_, self.water_ = U, A, mean, water
        self.eigs_ = lam
        self.rank_ = r
        self.grid_shape_ = (R, C)
        self.data_hash_ = field.data_hash() if hasattr(field, "data_hash") else None
        return self

    def _predict_batch(self, states: np.ndarray, steps: int) -> np.ndarray:
        B = states.shape[0]
        x = states[:, :, self.water_].reshape(B, -1).astype(np.float64) - self.mean_
        a = x @ self.modes_  # (B, r) coordinates
        out = np.zeros((B, steps, *states.shape[1:]), np.float32)
        idx = np.broadcast_to(self.water_, states.shape[1:])
        for k in range(steps):
            a = a @ self.A_.T
            xs = a @ self.modes_.T + self.mean_
            out[:, k][:, idx] = xs.astype(np.float32)
        return out

    def save(self, path, *, command: str | None = None, extra: dict | None = None):
        self._check_fitted()
        meta = {
            "predictor": self.name,
            "format": 1,
            "params": {"rank": self.rank, "energy": self.energy, "center": self.center, "stable": self.stable},
            "rank_": self.rank_,
            "grid_shape": list(self.grid_shape_),
            "data_hash": self.data_hash_,
            "command": command,
            **(extra or {}),
        }
        st = {
            "modes": np.ascontiguousarray(self.modes_),
            "A": np.ascontiguousarray(self.A_),
            "mean": self.mean_,
            "water": self.water_.astype(np.uint8),
        }
        import torch

        return write_checkpoint(path, {k: torch.from_numpy(np.asarray(v)) for k, v in st.items()}, meta)

    @classmethod
    def load(cls, path) -> DMDPredictor:
        meta = read_metadata(path)
        sd = load_state_dict(path)
        self = cls(**meta["params"])
        try:
            self.modes_, self.A_, self.mean_ = (sd[k].numpy() for k in ("modes", "A", "mean"))
            self.water_ = sd["water"].numpy().astype(bool)
        except KeyError as exc:
            raise ModelError(f"checkpoint {path} lacks {exc}") from None
        self.rank_ = int(meta["rank_"])
        self.eigs_ = np.linalg.eigvals(self.A_)
        self.grid_shape_ = tuple(int(x) for x in meta["grid_shape"])
        self.data_hash_ = meta.get("data_hash")
        return self
