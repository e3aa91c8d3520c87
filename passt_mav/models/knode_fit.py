"""Training machinery of the KNODE (:meth:`passt_mav.models.knode.KnodePredictor.fit`).

:func:`fit_knode` checks the window, fits the per-pixel scaler, builds the network and
hands the epochs to :class:`KnodeTrainer`: mini-batches of initial conditions (row-shifted
with ``shift_rows``), input noise, the roll-out loss, validation and best-epoch selection.
States are in scaled units (``z = (u - mean) / std`` per pixel, land 0); time in snapshot
intervals.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from passt_mav.errors import ModelError
from passt_mav.models.knode import KnodeNet, _torch, shift_field_rows
from passt_mav.models.noise import CorrelatedNoise, measure_residual, reconstruct_states

__all__ = ["fit_knode", "KnodeTrainer", "Scaler", "BestEpoch"]


@dataclass(frozen=True)
class Scaler:
    """Per-pixel standard scaling ``z = (u - mean) / std`` (field units -> scaled units), land and
    non-finite cells set to 0; ``mean``/``std`` ``(2, R, C)`` float32, ``water`` ``(R, C)`` bool."""

    mean: np.ndarray
    std: np.ndarray
    water: np.ndarray

    def __call__(self, a: np.ndarray) -> np.ndarray:
        """``a`` (``(..., 2, R, C)``, field units) scaled, as float32."""
        return ((np.where(np.isfinite(a), a, np.float32(0)) - self.mean) / self.std * self.water).astype(np.float32)


@dataclass
class BestEpoch:
    """The weights kept so far: validation ``loss`` (scaled units), ``epoch`` (0 = the start
    weights, -1 = none yet) and a copy of the network's ``state`` (``None`` = none kept)."""

    loss: float = math.inf
    epoch: int = -1
    state: dict | None = None


def check_training_window(p, data: np.ndarray, n_tr: int) -> np.ndarray:
    """The water mask ``(R, C)`` (cells with data at every time of ``data``), after checking that
    the training part ``data[:n_tr]`` is long enough for the roll-out and that ``shift_rows``
    fits the grid and its land."""
    T, _, R, _ = data[:n_tr].shape
    H_max = 1 if p.loss == "one_step" else int(p.horizon)
    if T - H_max < 1:
        raise ModelError(
            f"the training part has {T} snapshots, too few for a roll-out of {H_max}: give more data or a shorter --horizon (at most {max(T - 1, 1)})"
        )
    water = np.isfinite(data).all(axis=(0, 1))  # (R, C): cells with data at every time
    if not water.any():
        raise ModelError("training window has no cell with data at every time")
    if p.shift_rows and not water.all():
        raise ModelError(
            f"shift_rows={p.shift_rows} needs a field without land or missing cells ({int((~water).sum())} of {water.size} cells have none at some time)"
        )
    if p.shift_rows >= R:
        raise ModelError(f"shift_rows={p.shift_rows} must be below the grid's {R} rows")
    return water


def fit_scaler(p, train: np.ndarray, water: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ``(mean, std)`` (field units, float32) over the training snapshots ``train`` and,
    with ``shift_rows``, every shifted copy of them; land gets mean 0, land and constant cells std 1."""
    filled = np.where(np.isfinite(train), train, np.float32(0))
    if p.shift_rows:  # the scaler covers what the network is trained on: every shifted copy
        filled = np.concatenate([shift_field_rows(filled, s) for s in p._shifts()])
    mean = np.where(water, filled.mean(axis=0), 0).astype(np.float32)
    std = filled.std(axis=0)
    # land and constant cells get std 1 so scaling stays finite
    std = np.where(water & (std > 1e-8), std, 1.0).astype(np.float32)
    return mean, std


def build_network(p, grid_shape: tuple[int, int], start_from, dev, knowledge=None):
    """The network at its starting weights on ``dev``: seeded initialisation (the global torch RNG
    is left as it was), the linear ``knowledge`` module attached (``None``: none), then the start
    model's weights (``start_from``) or, with ``zero_init``, a zero last layer."""
    torch = _torch()
    R, C = grid_shape
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(p.seed))
        net = KnodeNet(
            R,
            C,
            channels=p.channels,
            hidden=p.hidden,
            kernel_size=p.kernel_size,
            kernel_variance=p.kernel_variance,
        )
        if knowledge is not None:
            net.knowledge = knowledge
        net = net.to(dev)
        if start_from is not None:
            net.load_state_dict(start_from.net_.state_dict())
        elif p.zero_init:
            # dz/dt = 0 at the start: the untrained model is persistence, and training
            # (with best-epoch selection on validation) departs from it only where that helps
            torch.nn.init.zeros_(net.fc2.weight)
            torch.nn.init.zeros_(net.fc2.bias)
    return net


def fit_knowledge(p, window: np.ndarray, water: np.ndarray, mean: np.ndarray, std: np.ndarray, start_from):
    """The linear knowledge module of ``p`` (``None`` for ``knowledge="none"``): DMD fitted on ``window``,
    the training part of the training window only (field units; the untrained model is the DMD that
    ``model train --model dmd`` would fit on those snapshots), in the scaling ``mean``/``std``, or a copy
    of the start model's when fine-tuning; sets ``p.knowledge_info_``. The validation part is never seen by
    the linear term, so the best epoch and the skill report score it out of sample."""
    import copy

    p.knowledge_info_ = None
    if p.knowledge == "none":
        return None
    if start_from is not None:
        p.knowledge_info_ = getattr(start_from, "knowledge_info_", None)
        return copy.deepcopy(start_from.net_.knowledge)
    from passt_mav.models.knowledge import fit_dmd_knowledge

    opts = {"rank": p.knowledge_rank, "energy": p.knowledge_energy, "complement": p.knowledge_complement}
    kn, p.knowledge_info_ = fit_dmd_knowledge(window, water, mean, std, **opts)
    return kn


def make_noise(p, field, data: np.ndarray, s0: int, n_tr: int, dev):
    """The training input-noise sampler ``noise(shape, generator)`` (scaled units; see the ``noise``
    parameter); sets ``p.noise_info_``."""
    torch = _torch()
    sd = math.sqrt(p.noise_var)
    white = (
        (lambda shape, gen: sd * torch.randn(shape, generator=gen, device=dev)) if sd > 0 else (lambda shape, gen: 0.0)
    )
    p.noise_info_ = {"kind": p.noise, "white_var": p.noise_var}
    if p.noise != "gp":
        return white
    grid = getattr(field, "grid", None)
    if grid is None:
        raise ModelError(
            "noise='gp' needs a FlowField (its grid) to measure the GP-reconstruction residual; use noise='white' for a bare array"
        )
    land = ~p.water_
    times = np.asarray(field.times)[s0 : s0 + data.shape[0]]
    m = measure_residual(
        data[:n_tr],
        grid,
        times[:n_tr],
        (0, n_tr),
        p.mean_,
        p.std_,
        n=p.noise_samples,
        path_length=p.noise_path_length,
        lag=1,
        noise_std=p.noise_sensor_std,
        seed=int(p.seed) + 17,
        land=land,
    )
    cn = CorrelatedNoise(m["amplitude"] * float(p.noise_scale), m["corr_cells"], device=dev)
    p.noise_info_.update({k: v for k, v in m.items() if k != "amplitude"}, scale=float(p.noise_scale))
    return lambda shape, gen: cn.sample(shape, gen) + white(shape, gen)


def validation_sets(p, field, data: np.ndarray, s0: int, n_tr: int, scale: Scaler, dev) -> list:
    """``[(z0, targets)]``: validation ICs of ``data[n_tr:]`` from true states and from GP reconstructions."""
    torch = _torch()
    val = data[n_tr:]
    H = 1 if p.loss == "one_step" else int(p.horizon)
    H = min(H, len(val) - 1)
    if H < 1:
        return []
    ics = np.arange(n_tr, data.shape[0] - H)
    tgt = torch.from_numpy(np.stack([scale(data[ics + k]) for k in range(1, H + 1)], axis=1)).to(dev)
    sets = [(torch.from_numpy(scale(data[ics])).to(dev), tgt)]
    grid = getattr(field, "grid", None)
    if grid is not None and p.noise == "gp":
        times = np.asarray(field.times)[s0 : s0 + data.shape[0]]
        rec = reconstruct_states(
            data,
            grid,
            times,
            ics,
            path_length=p.noise_path_length,
            lag=1,
            noise_std=p.noise_sensor_std,
            seed=int(p.seed) + 29,
            land=~p.water_,
        )
        sets.append((torch.from_numpy(scale(rec)).to(dev), tgt))
    return sets


class KnodeTrainer:
    """The epochs of one KNODE fit: holds the scaled training window at every row shift, the
    noise sampler, the validation sets, the optimiser and the network being trained."""

    def __init__(self, p, net, field, data: np.ndarray, s0: int, n_tr: int, scale: Scaler, dev):
        """Prepare training on ``data[:n_tr]`` (field units; ``s0``: its first index in ``field``);
        sets ``p``'s scaler, water mask, grid shape and training step."""
        torch = _torch()
        train = data[:n_tr]
        self.p, self.net, self.dev, self.T = p, net, dev, train.shape[0]
        self.gen = torch.Generator(device=dev).manual_seed(int(p.seed) + 1)
        self.Z = torch.from_numpy(scale(train)).to(dev)
        # the training window at every row shift (shift_rows augmentation; index 0 = unshifted),
        # each scaled after shifting (the scaler is per pixel)
        self.shifts = p._shifts()
        self.Zs = torch.stack(
            [self.Z] + [torch.from_numpy(scale(shift_field_rows(train, s))).to(dev) for s in self.shifts[1:]]
        )
        self.w = torch.from_numpy(scale.water.astype(np.float32)).to(dev)
        self.n_w = float(scale.water.sum()) * 2
        p.mean_, p.std_, p.water_, p.grid_shape_ = scale.mean, scale.std, scale.water, scale.water.shape
        self.noise = make_noise(p, field, data, s0, n_tr, dev)
        self.val_sets, self.val_weights = [], []
        for s in self.shifts:
            sets = validation_sets(p, field, shift_field_rows(data, s), s0, n_tr, scale, dev)
            self.val_sets += sets
            self.val_weights += [p._shift_weight(s, len(self.shifts))] * len(sets)
        self.opt = torch.optim.Adam(net.parameters(), lr=p.lr)
        p._step = p._stepper(net)

    def val_loss(self) -> float:
        """Validation roll-out loss: the mean over the validation sets, weighted by their shift's
        weight when the weights differ."""
        torch = _torch()
        self.net.eval()
        with torch.no_grad():
            losses = [float(self.p._rollout_loss(self.net, z0, tgt, self.w, self.n_w)) for z0, tgt in self.val_sets]
        if len(set(self.val_weights)) <= 1:
            return float(np.mean(losses))
        return float(np.average(losses, weights=self.val_weights))

    def _snapshot(self, loss: float, epoch: int) -> BestEpoch:
        """The network's current weights as the best so far, with their validation ``loss``."""
        return BestEpoch(loss, epoch, {k: t.detach().clone() for k, t in self.net.state_dict().items()})

    def _epoch_ics(self, ep: int, H: int) -> np.ndarray:
        """Epoch ``ep``'s initial conditions (indices into the training window) in training order."""
        p = self.p
        ics = np.arange(self.T - H)
        if p.max_ics and len(ics) > p.max_ics:
            ics = np.sort(np.random.default_rng(int(p.seed) * 7919 + ep).choice(ics, p.max_ics, replace=False))
        if p.n_batches > 1 or p.train_batch < len(ics):
            return np.random.default_rng(int(p.seed) + 104729 * (ep + 1)).permutation(ics)
        return ics

    def train_epoch(self, ep: int, H: int) -> float:
        """One pass of optimiser steps over epoch ``ep``'s initial conditions with roll-outs of
        ``H`` snapshots; returns the mean training loss (scaled units)."""
        torch = _torch()
        p, net, dev = self.p, self.net, self.dev
        order = self._epoch_ics(ep, H)
        bs = int(math.ceil(len(order) / p.n_batches)) if p.n_batches > 1 else int(p.train_batch)
        tot = 0.0
        net.train()
        shift_rng = np.random.default_rng(int(p.seed) * 31 + 7 * ep + 3)
        for a in range(0, len(order), bs):
            b = torch.from_numpy(order[a : a + bs]).to(dev)
            # each initial condition's row shift, an index into shifts (all 0 without augmentation)
            sh = torch.from_numpy(p._draw_shifts(shift_rng, len(self.shifts), len(b))).to(dev)
            x = self.Zs[sh, b]
            x = x + self.noise(x.shape, self.gen)
            target = torch.stack([self.Zs[sh, b + k] for k in range(1, H + 1)], dim=1)
            loss = p._rollout_loss(net, x, target, self.w, self.n_w)
            self.opt.zero_grad()
            loss.backward()
            if p.clip_grad:
                torch.nn.utils.clip_grad_norm_(net.parameters(), float(p.clip_grad))
            self.opt.step()
            tot += float(loss.detach()) * len(b)
        return tot / len(order)

    def run(self, n_ep: int, callback=None) -> tuple[list[float], list[float], BestEpoch]:
        """Train ``n_ep`` epochs (fewer with ``patience``); returns the training loss curve, the
        validation curve and the best epoch. ``callback(epoch, loss)`` after every epoch."""
        from passt_mav.progress import progress

        p = self.p
        curve: list[float] = []
        vcurve: list[float] = []
        best = BestEpoch()
        if self.val_sets and (p.zero_init or p.init):
            # epoch 0 (persistence, or the start model) competes too: a network that never beats it on validation is not kept
            best = self._snapshot(self.val_loss(), 0)
            vcurve.append(best.loss)
        # a bar with ETA on a terminal, a plain line every 10 % in a log
        bar = progress(n_ep, "KNODE training", "epoch", quiet=not p.progress)
        t0 = time.perf_counter()
        since_best = 0
        for ep in range(n_ep):
            H = p._horizon_at(ep, n_ep)
            curve.append(self.train_epoch(ep, H))
            if not math.isfinite(curve[-1]):
                raise ModelError(
                    f"KNODE training diverged at epoch {ep + 1} (loss {curve[-1]}); lower lr or raise substeps"
                )
            if self.val_sets and (ep + 1) % p.val_every == 0 or (self.val_sets and ep == n_ep - 1):
                vcurve.append(self.val_loss())
                # the best epoch is chosen once the roll-out length is the full horizon
                if H == p._horizon_at(n_ep - 1, n_ep) and vcurve[-1] < best.loss:
                    best, since_best = self._snapshot(vcurve[-1], ep + 1), 0
                elif H == p._horizon_at(n_ep - 1, n_ep):
                    since_best += p.val_every
            bar.note(f"loss {curve[-1]:.3e}, H {H}")
            bar.update()
            if callback is not None:
                callback(ep, curve[-1])
            if p.patience and since_best >= p.patience and p.select == "best":
                break
        bar.close()
        p.train_seconds_ = time.perf_counter() - t0
        return curve, vcurve, best

    def final_loss(self) -> float:
        """Noise-free one-step loss over the training window's pairs (scaled units, water cells)."""
        torch = _torch()
        with torch.no_grad():
            pred = self.p._advance(self.net, self.Z[:-1])
            return float((((pred - self.Z[1:]) ** 2) * self.w).sum() / (self.n_w * (self.T - 1)))


def fit_knode(p, field, start: int | None, stop: int | None, epochs: int | None, callback):
    """Train ``p`` on snapshots ``start..stop-1`` of ``field``; see :meth:`KnodePredictor.fit`."""
    torch = _torch()
    p._check_params()
    data = p._training_window(field, start, stop)
    n_ep = int(p.epochs if epochs is None else epochs)
    s0 = 0 if start is None else int(start)
    n_tr = p._split(data.shape[0])  # training part data[:n_tr]; validation: validation_sets() on data[n_tr:]
    water = check_training_window(p, data, n_tr)
    mean, std = fit_scaler(p, data[:n_tr], water)
    start_from = p._init_checkpoint(water.shape) if p.init else None
    if start_from is not None:  # fine-tuning: the weights were trained in the start model's scaling
        mean, std = start_from.mean_, start_from.std_
        p.init_metadata_ = getattr(start_from, "metadata_", None)
    dev = torch.device(p.device)
    net = build_network(p, water.shape, start_from, dev, fit_knowledge(p, data[:n_tr], water, mean, std, start_from))
    trainer = KnodeTrainer(p, net, field, data, s0, n_tr, Scaler(mean, std, water), dev)
    curve, vcurve, best = trainer.run(n_ep, callback)
    keep_best = best.state is not None and p.select == "best"
    if keep_best:
        net.load_state_dict(best.state)
    net.eval()
    p.net_ = net
    p._step = None
    p.loss_curve_ = curve
    p.val_curve_ = vcurve
    p.best_epoch_ = best.epoch if keep_best else len(curve)
    p.final_loss_ = trainer.final_loss()
    p.epochs_trained_ = len(curve)
    p.n_train_ = n_tr
    p.data_hash_ = field.data_hash() if hasattr(field, "data_hash") else None
    try:
        p.dt_ = float(field.dt)
    except Exception:  # noqa: BLE001 - a bare array or irregular times: no physical dt
        p.dt_ = None
    p.train_window_ = [s0, s0 + data.shape[0]]
    p.val_window_ = [s0 + n_tr, s0 + data.shape[0]] if n_tr < data.shape[0] else None
    return p
