"""The states the PASST loop starts its model from: GP reconstructions, and noise that imitates them.

Every leg, the loop starts the predictor from a Gaussian-process reconstruction made
from one leg's sparse, noisy samples (``passt.PasstLoop.update``). Such a state is
the truth plus a *spatially correlated* residual: the GP is exact near the path
and falls back to its prior (the forecast) away from it. A model trained only on
true snapshots (plus white noise, as in the paper) never sees such states and may
diverge from them. This module

* makes those states offline (:func:`reconstruct_states`): for a snapshot ``t``,
  samples along a random ``path_length``-move grid path at ``t`` with Gaussian
  sensor noise, GP prior = the truth ``lag`` snapshots earlier (a stale forecast);
* measures their residual (:func:`measure_residual`): RMS per pixel in the model's
  scaled units and a spatial correlation length in cells;
* draws training noise with that size and correlation (:class:`CorrelatedNoise`).

The same reconstructions are the "from GP reconstructions" initial conditions of
``passt-mav model evaluate`` and of the training skill report, so the figure a user
reads is measured on the states the loop really produces. Deterministic given ``seed``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["reconstruct_states", "measure_residual", "CorrelatedNoise", "correlation_length"]


def reconstruct_states(
    data: np.ndarray,
    grid,
    times,
    ts,
    *,
    path_length: int = 50,
    lag: int = 1,
    noise_std: float = 0.02,
    seed: int = 0,
    land=None,
    progress: bool = False,
) -> np.ndarray:
    """GP reconstructions of snapshots ``ts`` of ``data`` from sparse noisy samples.

    Args:
        data: ``(T, 2, R, C)`` float32 field (m/s or the field's units; NaN = land).
        grid: the field's :class:`geo.RegionGrid` (metres frame for the GP).
        times: ``(T,)`` snapshot times (the field's units).
        ts: snapshot indices to reconstruct, each ``>= lag``.
        path_length: moves of the random sampling path (one sample per visited cell).
        lag: the GP prior is the true snapshot ``t - lag`` (a forecast that is ``lag`` steps stale).
        noise_std: Gaussian sensor noise added to each sample (field units).
        seed: seeds the paths and the noise.
        land: ``(R, C)`` bool, True = land (never sampled; 0 in the result).

    Returns ``(len(ts), 2, R, C)`` float32 with land set to 0 (as predictors take it).
    """
    from passt_mav.loop.passt import Samples
    from passt_mav.planning import make_planner
    from passt_mav.reconstruction import GPReconstructor

    R, C = data.shape[2:]
    land = np.zeros((R, C), bool) if land is None else np.asarray(land, bool)
    rng = np.random.default_rng(seed)
    gp = GPReconstructor(grid_xy=grid.centres_xy(), prior="forecast", noise_std=max(noise_std, 1e-3), seed=seed)
    walker = make_planner("random")
    water = np.argwhere(~land)
    out = np.empty((len(ts), 2, R, C), np.float32)
    from tqdm.auto import tqdm

    for i, t in enumerate(tqdm(list(ts), desc="GP states", disable=not progress, leave=False)):
        t = int(t)
        if t - lag < 0:
            raise ValueError(f"snapshot {t} has no prior {lag} steps earlier")
        truth = np.nan_to_num(data[t])
        prior = np.nan_to_num(data[t - lag])
        start = tuple(int(x) for x in water[rng.integers(len(water))])
        path = walker.plan(np.ones((R, C)), start, int(path_length), seed=int(rng.integers(2**31)), mask=~land)
        r, c = path[:, 0].astype(np.float64), path[:, 1].astype(np.float64)
        ri, ci = path[:, 0], path[:, 1]
        uv = truth[:, ri, ci].T + rng.normal(0.0, noise_std, (len(ri), 2))
        fa = prior[:, ri, ci].T
        s = Samples(np.full(len(r), float(times[t])), r, c, uv[:, 0], uv[:, 1])
        xy = s.xy(grid)
        gp.fit(xy, s.uv, forecast_at_samples=fa)
        mean, _ = gp.reconstruct(xy, s.uv, forecast=prior, forecast_at_samples=fa, mask=~land)
        out[i] = np.where(land, np.float32(0), np.nan_to_num(mean)).astype(np.float32)
    return out


def correlation_length(res: np.ndarray, max_lag: int = 6) -> float:
    """Spatial correlation length (cells) of residual fields ``(..., R, C)``.

    Fits ``rho(k) = exp(-k^2 / (2 l^2))`` to the autocorrelation at lags ``k = 1..max_lag``
    along rows and columns (least squares on ``-2 ln rho = k^2 / l^2`` over lags with
    ``rho > 0.05``); 0.5 when even lag 1 is uncorrelated (white noise).
    """
    r = np.asarray(res, np.float64)
    var = float(np.mean(r**2))
    if var <= 0:
        return 0.5
    ks, ys = [], []
    for k in range(1, max_lag + 1):
        if k >= min(r.shape[-2:]):
            break
        rho = 0.5 * (np.mean(r[..., :, k:] * r[..., :, :-k]) + np.mean(r[..., k:, :] * r[..., :-k, :])) / var
        if rho <= 0.05:
            break
        ks.append(k)
        ys.append(-2.0 * math.log(min(rho, 0.999)))
    if not ks:
        return 0.5
    ks, ys = np.array(ks, float), np.array(ys)
    inv_l2 = float((ks**2 @ ys) / (ks**4).sum())
    return float(1.0 / math.sqrt(max(inv_l2, 1e-6)))


def measure_residual(
    data: np.ndarray,
    grid,
    times,
    window: tuple[int, int],
    mean: np.ndarray,
    std: np.ndarray,
    *,
    n: int = 12,
    path_length: int = 50,
    lag: int = 1,
    noise_std: float = 0.02,
    seed: int = 0,
    land=None,
) -> dict:
    """Size and correlation of the GP-reconstruction residual over snapshots of ``window``.

    ``mean``/``std``: the model's per-pixel scaler ``(2, R, C)``; the residual is reported
    in those scaled units. Returns ``{"rms", "amplitude" (2, R, C) per-pixel RMS smoothed
    over 1 cell, "corr_cells", "n", "path_length", "lag", "noise_std", "rms_field_units"}``.
    """
    a, b = int(window[0]), int(window[1])
    rng = np.random.default_rng(seed)
    lo = a + lag
    ts = np.sort(rng.choice(np.arange(lo, b), size=min(n, b - lo), replace=False))
    rec = reconstruct_states(
        data, grid, times, ts, path_length=path_length, lag=lag, noise_std=noise_std, seed=seed, land=land
    )
    truth = np.nan_to_num(data[ts])
    res = rec - truth
    scaled = res / std
    water = ~(np.zeros(data.shape[2:], bool) if land is None else np.asarray(land, bool))
    amp = np.sqrt(np.mean(scaled**2, axis=0))  # (2, R, C)
    from scipy.ndimage import gaussian_filter

    amp = np.stack([gaussian_filter(amp[k], 1.0, mode="nearest") for k in range(2)]) * water
    return {
        "rms": float(np.sqrt(np.mean(scaled[:, :, water] ** 2))),
        "rms_field_units": float(np.sqrt(np.mean(res[:, :, water] ** 2))),
        "amplitude": amp.astype(np.float32),
        "corr_cells": correlation_length(scaled * water),
        "n": int(len(ts)),
        "path_length": int(path_length),
        "lag": int(lag),
        "noise_std": float(noise_std),
    }


class CorrelatedNoise:
    """Gaussian noise with a per-pixel amplitude and a Gaussian spatial correlation (torch).

    White noise is smoothed with a normalised Gaussian (std ``corr_cells / sqrt(2)`` cells,
    so the result's correlation is ``exp(-d^2 / (2 corr_cells^2))``) — scaled so each pixel
    keeps unit variance — then multiplied by ``amplitude``
    ``(2, R, C)`` (scaled units). ``scale`` multiplies the whole draw (for a schedule).
    """

    def __init__(self, amplitude, corr_cells: float, *, device="cpu"):
        import torch

        self.amplitude = torch.as_tensor(np.asarray(amplitude, np.float32), device=device)
        # smoothing white noise with a Gaussian of std s gives the correlation exp(-d^2 / (4 s^2)):
        # a field correlation length l needs s = l / sqrt(2)
        self.sigma = max(float(corr_cells), 1e-3) / math.sqrt(2.0)
        half = max(1, int(math.ceil(3 * self.sigma)))
        x = np.arange(-half, half + 1)
        g = np.exp(-(x**2) / (2 * self.sigma**2))
        # a white field smoothed by kernel k has variance sum(k^2): normalise to unit variance
        k2 = np.outer(g, g)
        k2 = k2 / np.sqrt((k2**2).sum())
        self.kernel = torch.as_tensor(k2[None, None].repeat(2, 0).astype(np.float32), device=device)
        self.half = half

    def sample(self, shape, generator):
        """Noise of ``shape`` ``(B, 2, R, C)``."""
        import torch

        B, ch, R, C = shape
        h = self.half
        w = torch.randn((B, ch, R + 2 * h, C + 2 * h), generator=generator, device=self.kernel.device)
        n = torch.nn.functional.conv2d(w, self.kernel, groups=ch)
        return n * self.amplitude
