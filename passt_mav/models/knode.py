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

With ``knowledge="dmd"`` the right-hand side gains a known linear term,
``dz/dt = L z + K N(z; phi)``: DMD's operator fitted on the training part of the window,
in continuous time (:mod:`passt_mav.models.knowledge`), integrated exactly while the
correction ``K N`` takes Euler sub-steps.

Time is counted in snapshot intervals: one ``predict`` step advances the ODE by 1,
integrated with ``substeps`` (default 6) explicit Euler steps (or RK4). Training
minimises the mean squared one-step-ahead error over all snapshot pairs of the
window (in scaled units, water cells only), back-propagating through the sub-steps,
with Adam and zero-mean Gaussian input noise (variance ``noise_var``) for stability.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from passt_mav.errors import ModelError
from passt_mav.models.base import Predictor, load_state_dict, read_metadata, write_checkpoint

__all__ = [
    "KnodePredictor",
    "KnodeNet",
    "gaussian_kernel",
    "ode_step",
    "odeint_fixed",
    "conv_output_shape",
    "INTEGRATORS",
]

CHANNELS = (32, 64, 128, 128, 128)
#: the known part of the right-hand side besides the smoothing K: none (the paper) or DMD's linear operator
KNOWLEDGE = ("none", "dmd")
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


def shift_field_rows(a: np.ndarray, s: int) -> np.ndarray:
    """``a`` (``(..., rows, cols)``) moved by ``s`` rows toward higher row index (``s < 0``:
    lower), the rows that enter copying the nearest edge row (replicate padding); ``s = 0``
    returns ``a`` itself. Rows are the grid's y / north axis (row 0 = southernmost)."""
    s = int(s)
    if s == 0:
        return a
    R = a.shape[-2]
    return np.take(a, np.clip(np.arange(R) - s, 0, R - 1), axis=-2)


def _torch():
    import torch

    return torch


def _build_net_class():
    torch = _torch()
    nn = torch.nn

    class _KnodeNet(nn.Module):
        """The vector field N(z) followed by the smoothing K: (B, 2, R, C) -> (B, 2, R, C)."""

        def __init__(
            self,
            rows: int,
            cols: int,
            *,
            channels=CHANNELS,
            hidden: int = 128,
            kernel_size: int = 5,
            kernel_variance: float = 0.1,
        ):
            super().__init__()
            fr, fc = conv_output_shape(rows, cols)
            if fr < 1 or fc < 1:
                raise ModelError(f"grid {rows}x{cols} is too small for KNODE's convolutions (at least 13x13)")
            self.rows, self.cols = rows, cols
            chans = (2, *channels)
            self.convs = nn.ModuleList(
                nn.Conv2d(chans[i], chans[i + 1], k, stride=s, padding=p) for i, (k, s, p) in enumerate(CONV_SPEC)
            )
            self.fc1 = nn.Linear(channels[-1] * fr * fc, hidden)
            self.fc2 = nn.Linear(hidden, 2 * rows * cols)
            # fixed (not trained, but saved so a checkpoint is self-contained)
            self.register_buffer(
                "smooth", torch.from_numpy(gaussian_kernel(kernel_size, kernel_variance))[None, None].repeat(2, 1, 1, 1)
            )

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
            # replicate padding (a constant field stays constant at the edges too), built from
            # slices and torch.cat: the same values as F.pad(mode="replicate"), but torch.compile
            # can differentiate it (inductor has no replication_pad2d_backward)
            n = torch.cat([n[:, :, :1]] * pad + [n] + [n[:, :, -1:]] * pad, dim=2)
            n = torch.cat([n[:, :, :, :1]] * pad + [n] + [n[:, :, :, -1:]] * pad, dim=3)
            return torch.nn.functional.conv2d(n, self.smooth, groups=2)

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


@dataclass(eq=False, repr=False, kw_only=True)
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
        progress: progress of the epochs with the loss (:mod:`passt_mav.progress`: a bar on a TTY, plain
            lines otherwise).
        batch_size: initial conditions per forward pass in ``predict``.
        loss: ``"one_step"`` (the paper: MSE one snapshot ahead over all pairs) or
            ``"rollout"``: mean MSE over an unrolled roll-out of ``horizon`` snapshots (a
            PASST leg), back-propagated through every step, with a curriculum that grows
            the roll-out from 1 to ``horizon`` over the first ``curriculum`` fraction of epochs.
        noise: ``"white"`` (the paper: variance ``noise_var``) or ``"gp"``: noise whose
            per-pixel size and spatial correlation are measured from GP reconstructions
            of the training window (``noise_samples`` of them, ``noise_path_length``-move
            random paths, sensor noise ``noise_sensor_std`` field units), times
            ``noise_scale``, plus the white part; see :mod:`passt_mav.models.noise`.
        val_frac: last fraction of the window held out for validation (0 = none); the
            epoch with the lowest validation roll-out loss (from true and from GP-
            reconstructed states) is kept. ``val_every``: epochs between validations;
            ``patience``: stop after this many epochs without improvement (0 = never).
        train_batch: initial conditions per optimiser step (when ``n_batches`` is 1);
            ``max_ics``: initial conditions drawn per epoch (0 = all).
        clip_grad: gradient-norm clip (0 = off); roll-outs through many Euler steps can spike.
        zero_init: start the last layer at zero, i.e. from persistence (dz/dt = 0).
        compile: train through ``torch.compile`` when it works here (falls back to eager).
        fast_predict: predict through ``torch.compile`` with inductor freezing (weights as
            constants, pre-packed convolutions; 1.6x on 2-core CPUs, fp32 rounding of the
            eager result; each new batch shape compiles for a few seconds, so it pays on
            long roll-out work such as a campaign). A run-time switch, not saved.
        init: a KNODE checkpoint (``.pt``/``.json`` path or ``builtin:NAME``) to start from
            (fine-tuning): its weights AND its scaler are taken, so the weights keep their
            meaning; its architecture and grid must match. ``zero_init`` is then ignored, and
            the starting weights compete as epoch 0 in the best-epoch selection.
        select: which weights are kept: ``"best"`` (the epoch with the lowest validation
            loss, default) or ``"last"`` (the last epoch; for a roll-out horizon longer than
            the validation window, whose short roll-outs cannot see long-horizon drift -
            the validation curve is still recorded).
        shift_rows: augmentation (0 = off): every training initial condition and its
            roll-out targets are moved together by a random whole number of rows in
            ``[-shift_rows, shift_rows]`` (drawn per initial condition and epoch; rows are
            the grid's y / north axis), the rows that enter at the edge copying the edge row.
            For a wake crop this says the flow's dynamics do not depend on where the wake
            sits across the stream: a cylinder that moves sideways sheds the same street,
            displaced. Validation then covers every shift too, and the per-pixel scaler is
            taken over the shifted copies (a fine-tuning run keeps its start model's scaler).
            Needs a field without land.
        shift_fraction: with ``shift_rows``, the share of training initial conditions that are
            shifted (each drawn uniformly from the ``2 * shift_rows`` non-zero shifts; the rest
            stay unshifted), and the weight of the shifted copies in the validation loss (the
            unshifted window weighs ``1 - shift_fraction``). ``None`` (default) keeps the
            original draw: uniform over all ``2 * shift_rows + 1`` shifts, 0 included, every
            shift weighing the same in validation.
        knowledge: the known linear term of the right-hand side: ``"none"`` (the paper:
            ``dz/dt = K N(z)``) or ``"dmd"`` (``dz/dt = L z + K N(z)``, ``L`` DMD's operator
            fitted on the training part, in continuous time; see :mod:`passt_mav.models.knowledge`).
            With ``zero_init`` the untrained model is then DMD (in the ``"drop"`` complement) or
            DMD inside its subspace and persistence outside it (``"keep"``). Needs ``method="euler"``.
        knowledge_rank, knowledge_energy: DMD's truncation (rank, or the smallest rank reaching
            that share of the snapshots' energy).
        knowledge_complement: the linear term outside DMD's subspace: ``"keep"`` (persists,
            default), ``"drop"`` (DMD's projection) or a decay rate >= 0 per snapshot interval.
    """

    name = "knode"

    epochs: int = 100
    lr: float = 1e-3
    noise_var: float = 1e-3
    n_batches: int = 1
    substeps: int = 6
    method: str = "euler"
    channels: tuple = CHANNELS
    hidden: int = 128
    kernel_size: int = 5
    kernel_variance: float = 0.1
    seed: int = 0
    device: str = "cpu"
    progress: bool = True
    batch_size: int = 256
    loss: str = "one_step"
    horizon: int = 10
    curriculum: float = 0.5
    noise: str = "white"
    noise_scale: float = 1.0
    noise_samples: int = 12
    noise_path_length: int = 50
    noise_sensor_std: float = 0.02
    val_frac: float = 0.0
    val_every: int = 1
    patience: int = 0
    train_batch: int = 64
    max_ics: int = 0
    clip_grad: float = 1.0
    zero_init: bool = False
    compile: bool = False
    init: str | None = None
    select: str = "best"
    fast_predict: bool = False
    shift_rows: int = 0
    shift_fraction: float | None = None
    knowledge: str = "none"
    knowledge_rank: int | None = None
    knowledge_energy: float = 0.999
    knowledge_complement: str | float = "keep"

    def __post_init__(self) -> None:
        """Normalise the hyper-parameters' types (the model starts unfitted)."""
        self.channels = tuple(self.channels)
        self.init = None if self.init is None else str(self.init)
        self.fast_predict = bool(self.fast_predict)
        self.shift_fraction = None if self.shift_fraction is None else float(self.shift_fraction)
        if isinstance(self.knowledge_complement, str) and self.knowledge_complement not in ("keep", "drop"):
            try:  # a rate given as text (the command line) is stored as a number
                self.knowledge_complement = float(self.knowledge_complement)
            except ValueError:
                pass  # refused with its message by _check_params
        self.grid_shape_ = None

    def __getstate__(self) -> dict:
        # the compiled prediction step is per process (joblib / Dask workers compile their own)
        d = self.__dict__.copy()
        d.pop("_fast_step", None)
        return d

    # -- hyper-parameters that define the model (saved) --------------------------------
    def _arch(self) -> dict:
        return {
            "channels": list(self.channels),
            "hidden": self.hidden,
            "kernel_size": self.kernel_size,
            "kernel_variance": self.kernel_variance,
            "substeps": self.substeps,
            "method": self.method,
            "knowledge": self.knowledge,
            "knowledge_rank": self.knowledge_rank,
            "knowledge_energy": self.knowledge_energy,
            "knowledge_complement": self.knowledge_complement,
        }

    def _train_params(self) -> dict:
        keys = (
            "loss",
            "horizon",
            "curriculum",
            "noise",
            "noise_scale",
            "noise_samples",
            "noise_path_length",
            "noise_sensor_std",
            "val_frac",
            "val_every",
            "patience",
            "train_batch",
            "max_ics",
            "clip_grad",
            "zero_init",
            "init",
            "select",
            "shift_rows",
            "shift_fraction",
        )
        return {k: getattr(self, k, None) for k in keys}

    def _check_params(self) -> None:
        if self.method not in INTEGRATORS:
            raise ModelError(f"unknown integrator {self.method!r}; choose one of {', '.join(INTEGRATORS)}")
        for k in ("epochs", "substeps", "n_batches", "hidden", "batch_size"):
            v = getattr(self, k)
            if int(v) != v or v < (0 if k == "epochs" else 1):
                raise ModelError(f"{k} must be a {'non-negative' if k == 'epochs' else 'positive'} integer, got {v!r}")
        if self.loss not in ("one_step", "rollout"):
            raise ModelError(f"unknown loss {self.loss!r}; choose one_step or rollout")
        if self.noise not in ("white", "gp"):
            raise ModelError(f"unknown noise {self.noise!r}; choose white or gp")
        if int(self.horizon) != self.horizon or self.horizon < 1:
            raise ModelError(f"horizon must be a positive integer, got {self.horizon!r}")
        if self.select not in ("best", "last"):
            raise ModelError(f"unknown weight selection {self.select!r}; choose best or last")
        if not 0 <= float(self.val_frac) < 0.9:
            raise ModelError(f"val_frac must be in [0, 0.9), got {self.val_frac!r}")
        if int(self.shift_rows) != self.shift_rows or self.shift_rows < 0:
            raise ModelError(f"shift_rows must be a non-negative integer, got {self.shift_rows!r}")
        frac = getattr(self, "shift_fraction", None)
        if frac is not None and not (0.0 <= frac <= 1.0 and self.shift_rows > 0):
            raise ModelError(
                f"shift_fraction must be in [0, 1] and needs shift_rows > 0, got {frac!r} with shift_rows {self.shift_rows}"
            )
        self._check_knowledge()
        if len(self.channels) != len(CONV_SPEC):
            raise ModelError(f"channels must list {len(CONV_SPEC)} widths, got {self.channels}")

    def _check_knowledge(self) -> None:
        from passt_mav.models.knowledge import complement_rate

        if self.knowledge not in KNOWLEDGE:
            raise ModelError(f"unknown knowledge {self.knowledge!r}; choose one of {', '.join(KNOWLEDGE)}")
        complement_rate(self.knowledge_complement)
        if self.knowledge == "dmd" and self.method != "euler":
            raise ModelError(
                f"knowledge 'dmd' integrates its linear term exactly and the correction with Euler sub-steps; method {self.method!r} is not available with it (use euler)"
            )

    def _vf(self, net):
        return lambda z: net(z)

    def _advance(self, net, z):
        kn = getattr(net, "knowledge", None)
        if kn is not None:  # dz/dt = L z + K N(z): the linear part exactly, see models/knowledge.py
            return kn.step(net, z, int(self.substeps))
        return ode_step(net, z, 1.0, int(self.substeps), self.method)

    # -- fit ------------------------------------------------------------------------
    def _split(self, n: int) -> int:
        """Snapshots of an ``n``-snapshot window used for training (the rest validates)."""
        if not self.val_frac:
            return n
        n_val = max(
            int(round(n * float(self.val_frac))), 2 if self.loss == "one_step" else min(int(self.horizon), 10) + 1
        )
        if n - n_val < 3:
            raise ModelError(
                f"window of {n} snapshots is too short for a validation part of {n_val}; give more data or val_frac=0"
            )
        return n - n_val

    def _horizon_at(self, ep: int, n_ep: int) -> int:
        """Roll-out length of epoch ``ep``: 1 for the one-step loss, else a linear curriculum 1 -> horizon."""
        if self.loss == "one_step":
            return 1
        if self.curriculum <= 0:
            return int(self.horizon)
        ramp = max(1, int(round(n_ep * float(self.curriculum))))
        return int(min(self.horizon, 1 + (self.horizon - 1) * ep // ramp)) if ep < ramp else int(self.horizon)

    def _rollout_loss(self, net, z0, target, w, n_w):
        """Mean over the ``H = target.shape[1]`` steps of the water-masked MSE (scaled units)."""
        z, tot = z0, 0.0
        H = target.shape[1]
        for k in range(H):
            z = self._step(z)
            tot = tot + (((z - target[:, k]) ** 2) * w).sum() / (n_w * len(z0))
        return tot / H

    def fit(
        self, field, *, start: int | None = None, stop: int | None = None, epochs: int | None = None, callback=None
    ) -> KnodePredictor:
        """Train on snapshots ``start..stop-1`` of ``field`` (a FlowField or ``(T,2,R,C)`` array).

        The last ``val_frac`` of the window is held out for validation (early stopping,
        best-epoch selection); the rest trains. ``epochs`` overrides the constructor's.
        ``callback(epoch, loss)`` is called after every epoch. Sets ``net_``, ``mean_``,
        ``std_``, ``water_``, ``loss_curve_`` (training), ``val_curve_`` (validation
        roll-out loss from GP-reconstructed states, or ``[]``), ``best_epoch_``,
        ``noise_info_``, ``final_loss_`` (noise-free one-step, scaled units),
        ``train_seconds_``, ``data_hash_``, ``dt_``. The machinery is in :mod:`passt_mav.models.knode_fit`.
        """
        from passt_mav.models.knode_fit import fit_knode

        return fit_knode(self, field, start, stop, epochs, callback)

    def _shifts(self) -> list[int]:
        """Row shifts of the ``shift_rows`` augmentation, 0 first: ``[0, -n, .., -1, 1, .., n]``."""
        n = int(self.shift_rows)
        return [0] + [s for s in range(-n, n + 1) if s != 0]

    def _draw_shifts(self, rng, n_shifts: int, n: int) -> np.ndarray:
        """Indices into ``_shifts()`` for ``n`` initial conditions (see ``shift_fraction``)."""
        frac = getattr(self, "shift_fraction", None)
        if frac is None or n_shifts == 1:
            return rng.integers(n_shifts, size=n)  # the original draw (bit-for-bit as before the option)
        shifted = rng.random(n) < frac
        return np.where(shifted, rng.integers(1, n_shifts, size=n), 0)

    def _shift_weight(self, shift: int, n_shifts: int) -> float:
        """Weight of one shift's validation sets in the validation loss (see ``shift_fraction``)."""
        frac = getattr(self, "shift_fraction", None)
        if frac is None or n_shifts == 1:
            return 1.0
        return 1.0 - frac if shift == 0 else frac / (n_shifts - 1)

    def _init_checkpoint(self, grid_shape) -> KnodePredictor:
        """The start model of a fine-tuning run (``init``), checked against this model's shape."""
        from passt_mav.models.base import load_predictor

        p = load_predictor(self.init)
        if not isinstance(p, KnodePredictor):
            raise ModelError(f"--init {self.init}: not a KNODE checkpoint")
        if tuple(p.grid_shape_) != tuple(grid_shape) or p._arch() != self._arch():
            raise ModelError(
                f"--init {self.init}: grid {tuple(p.grid_shape_)} / architecture {p._arch()} do not match this model's {tuple(grid_shape)} / {self._arch()}"
            )
        return p

    def _stepper(self, net):
        """One snapshot step ``z -> z(t+1)`` for training: compiled when asked and it works, else eager."""
        eager = lambda z: self._advance(net, z)
        if not self.compile:
            return eager
        from passt_mav.models.fast import compiled_or_eager

        return compiled_or_eager(eager, net)

    # -- predict ----------------------------------------------------------------------
    def _predict_step(self):
        """The snapshot step used by ``predict``: eager, or compiled with freezing (``fast_predict``)."""
        net = self.net_
        if not self.fast_predict:
            return lambda z: self._advance(net, z)
        fn = self.__dict__.get("_fast_step")
        if fn is None or fn.module is not net:  # compiled for another network (refit / reload)
            from passt_mav.models.fast import compiled_or_eager

            fn = compiled_or_eager(lambda z: self._advance(net, z), net, options={"freezing": True})
            self._fast_step = fn
        return fn

    def _predict_batch(self, states: np.ndarray, steps: int) -> np.ndarray:
        torch = _torch()
        dev = next(self.net_.parameters()).device
        mean, std, water = self.mean_, self.std_, self.water_
        out = np.empty((states.shape[0], steps, *states.shape[1:]), np.float32)
        step = self._predict_step()
        with torch.no_grad():
            for a in range(0, states.shape[0], self.batch_size):
                s = states[a : a + self.batch_size]
                z = torch.from_numpy(((s - mean) / std * water).astype(np.float32)).to(dev)
                for k in range(steps):
                    z = step(z)
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
        state.update(
            {
                "scaler.mean": torch.from_numpy(self.mean_),
                "scaler.std": torch.from_numpy(self.std_),
                "water": torch.from_numpy(self.water_.astype(np.uint8)),
            }
        )
        meta = {
            "predictor": self.name,
            "format": 1,
            "architecture": dict(
                self._arch(),
                conv_spec=[list(c) for c in CONV_SPEC],
                flatten=int(self.channels[-1] * np.prod(conv_output_shape(*self.grid_shape_))),
                n_params=self.n_params(),
                time_unit="one snapshot interval per predict step",
            ),
            "params": {
                "epochs": self.epochs_trained_,
                "lr": self.lr,
                "noise_var": self.noise_var,
                "n_batches": self.n_batches,
                "seed": self.seed,
                **self._train_params(),
                **self._arch(),
            },
            "grid_shape": list(self.grid_shape_),
            "dt": self.dt_,
            "scaler": "per-pixel standard scaling over the training window (tensors scaler.mean/scaler.std in the .pt)",
            "data_hash": self.data_hash_,
            "train_window": self.train_window_,
            "epochs": self.epochs_trained_,
            "seed": self.seed,
            "final_loss": self.final_loss_,
            "val_window": getattr(self, "val_window_", None),
            "best_epoch": getattr(self, "best_epoch_", None),
            "val_curve": [float(f"{x:.6g}") for x in getattr(self, "val_curve_", [])],
            "noise_info": getattr(self, "noise_info_", None),
            "knowledge_info": getattr(self, "knowledge_info_", None),
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
    def load(cls, path, *, device: str = "cpu") -> KnodePredictor:
        """Rebuild from a checkpoint written by :meth:`save` (``weights_only=True``)."""
        import torch

        meta = read_metadata(path)
        sd = load_state_dict(path)
        p = dict(meta["params"])
        p["channels"] = tuple(p["channels"])
        self = cls(**p, device=device, progress=False)
        R, C = meta["grid_shape"]
        net = KnodeNet(
            R,
            C,
            channels=self.channels,
            hidden=self.hidden,
            kernel_size=self.kernel_size,
            kernel_variance=self.kernel_variance,
        )
        try:
            if self.knowledge == "dmd":
                from passt_mav.models.knowledge import LinearKnowledge

                net.knowledge = LinearKnowledge(
                    *(sd[f"net.knowledge.{k}"].numpy() for k in ("U", "Ac", "scale", "offset")),
                    self.knowledge_complement,
                )
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
        self.val_window_ = meta.get("val_window")
        self.best_epoch_ = meta.get("best_epoch")
        self.val_curve_ = meta.get("val_curve", [])
        self.noise_info_ = meta.get("noise_info")
        self.knowledge_info_ = meta.get("knowledge_info")
        self.metadata_ = meta
        return self
