"""KNODE: a knowledge-based neural ODE for the flow field (the PASST paper's predictor).

The state is the whole grid snapshot ``u`` (2, R, C), standard-scaled per pixel
(``z = (u - mean) / std`` with mean/std over the training window, stored with the
model). Its time derivative is

    dz/dt = K N(z; phi)

* ``N`` (:class:`KnodeNet`), as in the paper and the authors' code: Conv 2->32
  (3x3, stride 1, pad 0, tanh) -> Conv 32->64 (3x3, 1, 0, tanh) -> Conv 64->128
  (3x3, 2, 1, tanh) -> Conv 128->128 (3x3, 2, 1, tanh) -> Conv 128->128 (3x3, 2, 0)
  -> flatten (1152 for 30x30) -> Linear ->128 (ReLU) -> Linear 128 -> 2*R*C ->
  reshape. The flatten width is computed from the grid, so other grids work
  (at least 13x13).
* ``K``: a fixed per-channel Gaussian smoothing, ``kernel_size`` 5, variance
  ``kernel_variance`` in **cell^2** (replicate padding, weights normalised so a
  constant field is unchanged). The paper's variance 0.1 means sigma = 0.32 cells:
  the neighbours' weights are exp(-1/0.2) ~ 0.7 % of the centre's, so ``K`` is then
  almost the identity. It is kept as in the paper by default and configurable
  (``kernel_variance=1.0`` smooths over about one cell).

Time is counted in snapshot intervals: one ``predict`` step advances the ODE by 1,
integrated with ``substeps`` (default 6) explicit Euler steps (or RK4). Training
minimises the mean squared one-step-ahead error over all snapshot pairs of the
window (in scaled units, water cells only), back-propagating through the sub-steps,
with Adam and zero-mean Gaussian input noise (variance ``noise_var``) for stability.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Callable

import numpy as np

from passt_mav.errors import ModelError
from passt_mav.models.base import Predictor, load_state_dict, read_metadata, write_checkpoint

__all__ = ["KnodePredictor", "KnodeNet", "gaussian_kernel", "ode_step", "odeint_fixed", "conv_output_shape", "INTEGRATORS"]

CHANNELS = (32, 64, 128, 128, 128)
# (kernel, stride, padding) of the five convolutions, as in the authors' code
CONV_SPEC = ((3, 1, 0), (3, 1, 0), (3, 2, 1), (3, 2, 1), (3, 2, 0))


def conv_output_shape(rows: int, cols: int) -> tuple[int, int]:
    """Spatial size after the five convolutions of :class:`KnodeNet` (3x3 for 30x30)."""
    r, c = rows, cols
    for k, s, p in CONV_SPEC:
        r, c = (r + 2 * p - k) // s + 1, (c + 2 * p - k) // s + 1
    return r, c


def gaussian_kernel(size: int = 5, variance: float = 0.1) -> np.ndarray:
    """``(size, size)`` normalised Gaussian, ``variance`` in cell^2 (per axis)."""
    if size < 1 or size % 2 == 0:
        raise ModelError(f"kernel_size must be a positive odd integer, got {size}")
    if not variance > 0:
        raise ModelError(f"kernel_variance must be > 0 (cell^2), got {variance}")
    x = np.arange(size) - size // 2
    g = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2.0 * variance))
    return (g / g.sum()).astype(np.float32)


def _torch():
    import torch

    return torch


def _build_net_class():
    torch = _torch()
    nn = torch.nn

    class _KnodeNet(nn.Module):
        """The vector field N(z) followed by the smoothing K: (B, 2, R, C) -> (B, 2, R, C)."""

        def __init__(self, rows: int, cols: int, *, channels=CHANNELS, hidden: int = 128, kernel_size: int = 5, kernel_variance: float = 0.1):
            super().__init__()
            fr, fc = conv_output_shape(rows, cols)
            if fr < 1 or fc < 1:
                raise ModelError(f"grid {rows}x{cols} is too small for KNODE's convolutions (at least 13x13)")
            self.rows, self.cols = rows, cols
            chans = (2, *channels)
            self.convs = nn.ModuleList(nn.Conv2d(chans[i], chans[i + 1], k, stride=s, padding=p) for i, (k, s, p) in enumerate(CONV_SPEC))
            self.fc1 = nn.Linear(channels[-1] * fr * fc, hidden)
            self.fc2 = nn.Linear(hidden, 2 * rows * cols)
            # fixed (not trained, but saved so a checkpoint is self-contained)
            self.register_buffer("smooth", torch.from_numpy(gaussian_kernel(kernel_size, kernel_variance))[None, None].repeat(2, 1, 1, 1))

        def vector_field(self, z):
            h = z
            for i, conv in enumerate(self.convs):
                h = conv(h)
                if i < len(self.convs) - 1:  # the last convolution is linear, as in the authors' code
                    h = torch.tanh(h)
            h = torch.relu(self.fc1(h.flatten(1)))
            return self.fc2(h).view(-1, 2, self.rows, self.cols)

        def forward(self, z):
            n = self.vector_field(z)
            pad = self.smooth.shape[-1] // 2
            # replicate padding: a constant field stays constant at the edges too
            return torch.nn.functional.conv2d(torch.nn.functional.pad(n, (pad, pad, pad, pad), mode="replicate"), self.smooth, groups=2)

    return _KnodeNet


_NET_CLASS = None


def KnodeNet(rows: int, cols: int, **kw):
    """Build the network (a ``torch.nn.Module``) for a ``rows x cols`` grid; see module docstring."""
    global _NET_CLASS
    if _NET_CLASS is None:
        _NET_CLASS = _build_net_class()
    return _NET_CLASS(rows, cols, **kw)


# -- fixed-step integrators (work on numpy-like or torch tensors) ---------------------


def _euler(f: Callable, u, h: float):
    return u + h * f(u)


def _rk4(f: Callable, u, h: float):
    k1 = f(u)
    k2 = f(u + (0.5 * h) * k1)
    k3 = f(u + (0.5 * h) * k2)
    k4 = f(u + h * k3)
    return u + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)


INTEGRATORS: dict[str, Callable] = {"euler": _euler, "rk4": _rk4}


def ode_step(f: Callable, u, dt: float, substeps: int, method: str = "euler"):
    """Advance ``du/dt = f(u)`` by ``dt`` with ``substeps`` equal fixed steps of ``method``."""
    if method not in INTEGRATORS:
        raise ModelError(f"unknown integrator {method!r}; choose one of {', '.join(INTEGRATORS)}")
    step = INTEGRATORS[method]
    h = dt / substeps
    for _ in range(substeps):
        u = step(f, u, h)
    return u


def odeint_fixed(f: Callable, u0, t_end: float, n_steps: int, method: str = "euler"):
    """``u(t_end)`` of ``du/dt = f(u)``, ``u(0) = u0``, with ``n_steps`` fixed steps (global error O(h) Euler, O(h^4) RK4)."""
    return ode_step(f, u0, t_end, n_steps, method)


class KnodePredictor(Predictor):
    """KNODE predictor (sklearn-like; hyper-parameters keyword-only, learned state ends in ``_``).

    Args:
        epochs: training epochs (full passes over the window's snapshot pairs).
        lr: Adam learning rate.
        noise_var: variance of the zero-mean Gaussian noise added to the (scaled)
            inputs during training.
        n_batches: 1 = full batch; n > 1 splits the pairs by ``i mod n`` (memory).
        substeps: integrator steps per snapshot interval (paper: 6).
        method: ``"euler"`` (paper) or ``"rk4"``.
        channels, hidden: layer widths (paper: (32, 64, 128, 128, 128), 128).
        kernel_size, kernel_variance: the smoothing K (cells, cell^2).
        seed: seeds the weights' initialisation and the input noise.
        device: torch device for training and prediction (``"cpu"`` default).
        progress: tqdm bar with the loss (shown only on a TTY).
        batch_size: initial conditions per forward pass in ``predict``.
    """

    name = "knode"

    def __init__(self, *, epochs: int = 100, lr: float = 1e-3, noise_var: float = 1e-3, n_batches: int = 1, substeps: int = 6, method: str = "euler", channels: tuple = CHANNELS, hidden: int = 128, kernel_size: int = 5, kernel_variance: float = 0.1, seed: int = 0, device: str = "cpu", progress: bool = True, batch_size: int = 256):
        self.epochs = epochs
        self.lr = lr
        self.noise_var = noise_var
        self.n_batches = n_batches
        self.substeps = substeps
        self.method = method
        self.channels = tuple(channels)
        self.hidden = hidden
        self.kernel_size = kernel_size
        self.kernel_variance = kernel_variance
        self.seed = seed
        self.device = device
        self.progress = progress
        self.batch_size = batch_size
        self.grid_shape_ = None

    # -- hyper-parameters that define the model (saved) --------------------------------
    def _arch(self) -> dict:
        return {"channels": list(self.channels), "hidden": self.hidden, "kernel_size": self.kernel_size, "kernel_variance": self.kernel_variance, "substeps": self.substeps, "method": self.method}

    def _check_params(self) -> None:
        if self.method not in INTEGRATORS:
            raise ModelError(f"unknown integrator {self.method!r}; choose one of {', '.join(INTEGRATORS)}")
        for k in ("epochs", "substeps", "n_batches", "hidden", "batch_size"):
            v = getattr(self, k)
            if int(v) != v or v < (0 if k == "epochs" else 1):
                raise ModelError(f"{k} must be a {'non-negative' if k == 'epochs' else 'positive'} integer, got {v!r}")
        if len(self.channels) != len(CONV_SPEC):
            raise ModelError(f"channels must list {len(CONV_SPEC)} widths, got {self.channels}")

    def _vf(self, net):
        return lambda z: net(z)

    def _advance(self, net, z):
        return ode_step(net, z, 1.0, int(self.substeps), self.method)

    # -- fit ------------------------------------------------------------------------
    def fit(self, field, *, start: int | None = None, stop: int | None = None, epochs: int | None = None, callback=None) -> "KnodePredictor":
        """Train on snapshots ``start..stop-1`` of ``field`` (a FlowField or ``(T,2,R,C)`` array).

        ``epochs`` overrides the constructor's. ``callback(epoch, loss)`` is called after
        every epoch. Sets ``net_``, ``mean_``, ``std_``, ``water_``, ``loss_curve_``,
        ``final_loss_`` (noise-free, scaled units), ``train_seconds_``, ``data_hash_``, ``dt_``.
        """
        torch = _torch()
        self._check_params()
        data = self._training_window(field, start, stop)
        n_ep = int(self.epochs if epochs is None else epochs)
        T, _, R, C = data.shape
        water = np.isfinite(data).all(axis=(0, 1))  # (R, C): cells with data at every training time
        if not water.any():
            raise ModelError("training window has no cell with data at every time")
        filled = np.where(np.isfinite(data), data, np.float32(0))
        mean = np.where(water, filled.mean(axis=0), 0).astype(np.float32)
        std = filled.std(axis=0)
        # land and constant cells get std 1 so scaling stays finite
        std = np.where(water & (std > 1e-8), std, 1.0).astype(np.float32)
        z = ((filled - mean) / std) * water
        dev = torch.device(self.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(self.seed))
            net = KnodeNet(R, C, channels=self.channels, hidden=self.hidden, kernel_size=self.kernel_size, kernel_variance=self.kernel_variance).to(dev)
        gen = torch.Generator(device=dev).manual_seed(int(self.seed) + 1)
        X = torch.from_numpy(z[:-1].astype(np.float32)).to(dev)
        Y = torch.from_numpy(z[1:].astype(np.float32)).to(dev)
        w = torch.from_numpy(water.astype(np.float32)).to(dev)
        n_w = float(water.sum()) * 2
        opt = torch.optim.Adam(net.parameters(), lr=self.lr)
        idx_all = np.arange(T - 1)
        batches = [idx_all[idx_all % self.n_batches == k] for k in range(self.n_batches)]
        batches = [torch.from_numpy(b).to(dev) for b in batches if len(b)]
        sd_noise = math.sqrt(self.noise_var)
        curve: list[float] = []
        from tqdm.auto import tqdm

        bar = tqdm(range(n_ep), desc="KNODE", disable=not (self.progress and sys.stderr.isatty()), leave=False)
        t0 = time.perf_counter()
        net.train()
        for ep in bar:
            tot = 0.0
            for b in batches:
                x = X[b]
                if sd_noise > 0:
                    x = x + sd_noise * torch.randn(x.shape, generator=gen, device=dev)
                pred = self._advance(net, x)
                loss = (((pred - Y[b]) ** 2) * w).sum() / (n_w * len(b))
                opt.zero_grad()
                loss.backward()
                opt.step()
                tot += float(loss.detach()) * len(b)
            curve.append(tot / (T - 1))
            bar.set_postfix(loss=f"{curve[-1]:.3e}")
            if callback is not None:
                callback(ep, curve[-1])
            if not math.isfinite(curve[-1]):
                raise ModelError(f"KNODE training diverged at epoch {ep + 1} (loss {curve[-1]}); lower lr or raise substeps")
        self.train_seconds_ = time.perf_counter() - t0
        net.eval()
        self.net_ = net
        self.mean_, self.std_, self.water_ = mean, std, water
        self.grid_shape_ = (R, C)
        self.loss_curve_ = curve
        with torch.no_grad():
            pred = self._advance(net, X)
            self.final_loss_ = float((((pred - Y) ** 2) * w).sum() / (n_w * (T - 1)))
        self.epochs_trained_ = n_ep
        self.n_train_ = T
        self.data_hash_ = field.data_hash() if hasattr(field, "data_hash") else None
        try:
            self.dt_ = float(field.dt)
        except Exception:  # noqa: BLE001 - a bare array or irregular times: no physical dt
            self.dt_ = None
        self.train_window_ = [0 if start is None else int(start), (field.data.shape[0] if hasattr(field, "data") else len(field)) if stop is None else int(stop)]
        return self

    # -- predict ----------------------------------------------------------------------
    def _predict_batch(self, states: np.ndarray, steps: int) -> np.ndarray:
        torch = _torch()
        dev = next(self.net_.parameters()).device
        mean, std, water = self.mean_, self.std_, self.water_
        out = np.empty((states.shape[0], steps, *states.shape[1:]), np.float32)
        with torch.no_grad():
            for a in range(0, states.shape[0], self.batch_size):
                s = states[a : a + self.batch_size]
                z = torch.from_numpy(((s - mean) / std * water).astype(np.float32)).to(dev)
                for k in range(steps):
                    z = self._advance(self.net_, z)
                    out[a : a + len(s), k] = z.cpu().numpy() * std + mean
        out *= water  # no forecast where there was never data (land)
        return out

    def n_params(self) -> int:
        self._check_fitted()
        return int(sum(p.numel() for p in self.net_.parameters()))

    # -- checkpoints ------------------------------------------------------------------
    def save(self, path, *, command: str | None = None, extra: dict | None = None):
        """Write ``PATH.pt`` (state_dict + scaler tensors) and ``PATH.json``; returns the ``.pt`` path."""
        import torch

        self._check_fitted()
        state = {f"net.{k}": v for k, v in self.net_.state_dict().items()}
        state.update({"scaler.mean": torch.from_numpy(self.mean_), "scaler.std": torch.from_numpy(self.std_), "water": torch.from_numpy(self.water_.astype(np.uint8))})
        meta = {
            "predictor": self.name,
            "format": 1,
            "architecture": dict(self._arch(), conv_spec=[list(c) for c in CONV_SPEC], flatten=int(self.channels[-1] * np.prod(conv_output_shape(*self.grid_shape_))), n_params=self.n_params(), time_unit="one snapshot interval per predict step"),
            "params": {"epochs": self.epochs_trained_, "lr": self.lr, "noise_var": self.noise_var, "n_batches": self.n_batches, "seed": self.seed, **self._arch()},
            "grid_shape": list(self.grid_shape_),
            "dt": self.dt_,
            "scaler": "per-pixel standard scaling over the training window (tensors scaler.mean/scaler.std in the .pt)",
            "data_hash": self.data_hash_,
            "train_window": self.train_window_,
            "epochs": self.epochs_trained_,
            "seed": self.seed,
            "final_loss": self.final_loss_,
            "final_epoch_loss": self.loss_curve_[-1] if self.loss_curve_ else None,
            "loss_curve": [float(f"{x:.6g}") for x in self.loss_curve_],
            "train_seconds": round(self.train_seconds_, 2),
            "torch": torch.__version__,
            "command": command,
        }
        if extra:
            meta.update(extra)
        return write_checkpoint(path, state, meta)

    @classmethod
    def load(cls, path, *, device: str = "cpu") -> "KnodePredictor":
        """Rebuild from a checkpoint written by :meth:`save` (``weights_only=True``)."""
        import torch

        meta = read_metadata(path)
        sd = load_state_dict(path)
        p = dict(meta["params"])
        p["channels"] = tuple(p["channels"])
        self = cls(**p, device=device, progress=False)
        R, C = meta["grid_shape"]
        net = KnodeNet(R, C, channels=self.channels, hidden=self.hidden, kernel_size=self.kernel_size, kernel_variance=self.kernel_variance)
        try:
            net.load_state_dict({k[4:]: v for k, v in sd.items() if k.startswith("net.")})
            self.mean_ = sd["scaler.mean"].numpy().astype(np.float32)
            self.std_ = sd["scaler.std"].numpy().astype(np.float32)
            self.water_ = sd["water"].numpy().astype(bool)
        except (KeyError, RuntimeError) as exc:
            raise ModelError(f"checkpoint {path} does not match its metadata: {exc}") from None
        self.net_ = net.to(torch.device(device)).eval()
        self.grid_shape_ = (int(R), int(C))
        self.loss_curve_ = meta.get("loss_curve", [])
        self.final_loss_ = meta.get("final_loss")
        self.epochs_trained_ = meta.get("epochs")
        self.data_hash_ = meta.get("data_hash")
        self.dt_ = meta.get("dt")
        self.train_window_ = meta.get("train_window")
        self.train_seconds_ = meta.get("train_seconds", 0.0)
        self.metadata_ = meta
        return self
