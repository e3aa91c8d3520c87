"""The forecast alone, kept beside the loop, and the guard that needs no truth.

:class:`OpenLoop` is the model's forecast from the mission's first state, never re-initialised
(the "model alone"). The loop keeps it as a candidate background beside the forecast restarted
from the last estimate, so that what a leg could not see is never lost: where no sample reaches,
the analysis is a forecast, never a zero mean.

:func:`guard_record` scores, before a leg's samples enter the estimate, the loop's forecast (the
one restarted from the last estimate) and the open-loop forecast at those samples, by their
RMSE (field units) and their innovation log likelihood (nats) under the GP's stationary kernels
and sensor noise. When the loop's forecast fits the new samples worse than the forecast alone
(``behind``), the loop takes the open-loop forecast as the leg's background (``fallback``: the
better of the two at the samples). When that happens on :data:`GUARD_LEGS` legs running, or by more
than :data:`GUARD_MARGIN` on one leg, the record raises an alarm (``alarm``, ``message``: one line
for the console, the report and the live view). No truth is read: only the samples a leg collects.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["GUARDS", "GUARD_LEGS", "GUARD_MARGIN", "OpenLoop", "guard_record", "guard_message"]

#: values of ``PasstLoop(guard=...)``
GUARDS = ("on", "off")
#: legs running on which the loop's forecast fits the new samples worse than the forecast alone (by
#: RMSE at the samples) before the guard raises its alarm
GUARD_LEGS = 2
#: one leg raises the alarm when the loop's RMSE at the samples exceeds the forecast alone's by this fraction
GUARD_MARGIN = 0.10


class OpenLoop:
    """The model alone: its forecast from ``state`` ((2, R, C), field units, NaN on land) at field
    time ``t0``, one snapshot every ``dt`` (field time units), rolled out as far as asked.

    ``forecast``: ``(state, steps) -> (steps + 1, 2, R, C)`` (:meth:`PasstLoop.forecast`); the
    trajectory is extended from its last snapshot, so a model with a memory of more than one
    snapshot is not supported (none of :data:`passt_mav.models.base.PREDICTORS` has one).
    ``trajectory``: a ready roll-out from ``state`` (the lockstep engine computes it once for a
    batch of trials), extended the same way when a leg runs past it.
    """

    def __init__(self, forecast: Callable, state, t0: float, dt: float, trajectory=None):
        self._forecast = forecast
        self.t0, self.dt = float(t0), float(dt)
        traj = np.asarray(state, np.float32)[None] if trajectory is None else np.asarray(trajectory, np.float32)
        self.trajectory = traj

    def _extend(self, n: int) -> None:
        """At least ``n + 1`` snapshots in :attr:`trajectory`."""
        have = self.trajectory.shape[0]
        if have <= n:
            more = np.asarray(self._forecast(self.trajectory[-1], n + 1 - have), np.float32)[1:]
            self.trajectory = np.concatenate([self.trajectory, more], axis=0)

    def at(self, t_start: float, dt: float, n: int) -> np.ndarray:
        """(n, 2, R, C) float64: the open-loop forecast at field times ``t_start + i * dt``, i < n,
        linear in time between the model's snapshots (before ``t0``: the first state)."""
        x = np.maximum((float(t_start) + float(dt) * np.arange(n) - self.t0) / self.dt, 0.0)
        k = np.floor(x + 1e-9).astype(int)
        w = np.clip(x - k, 0.0, 1.0)
        self._extend(int(k.max()) + 1 if np.any(w > 0) else int(k.max()))
        lo = self.trajectory[k].astype(np.float64)
        if not np.any(w > 0):
            return lo
        hi = self.trajectory[np.minimum(k + 1, self.trajectory.shape[0] - 1)].astype(np.float64)
        return (1.0 - w)[:, None, None, None] * lo + w[:, None, None, None] * hi


def _rms(residual: np.ndarray) -> float:
    """Root mean square over finite (u, v) rows of an (n, 2) residual (field units); NaN when none."""
    r = np.asarray(residual, float)
    ok = np.isfinite(r).all(axis=1)
    return float(np.sqrt(np.mean(r[ok] ** 2))) if ok.any() else float("nan")


def guard_record(
    leg: int,
    uv: np.ndarray,
    loop_at: np.ndarray,
    open_at: np.ndarray,
    loglik: Callable[[np.ndarray], float],
    history: list[dict],
) -> dict:
    """The guard's record of leg ``leg`` (0-based) before its samples enter the estimate.

    ``uv``: (n, 2) samples (field units, east/north); ``loop_at`` / ``open_at``: the loop's
    forecast and the open-loop forecast at the samples' positions and times ((n, 2)); ``loglik``:
    the innovation log likelihood of an (n, 2) residual (nats); ``history``: earlier records.
    Keys: ``rmse_loop`` / ``rmse_open_loop`` (field units), ``loglik_loop`` / ``loglik_open_loop``
    (nats), ``behind`` (the loop's RMSE above the forecast alone's), ``behind_legs`` (legs running),
    ``fallback`` (the leg's background is the forecast alone: whenever ``behind``) and ``alarm``
    (``behind`` on :data:`GUARD_LEGS` legs running or by more than :data:`GUARD_MARGIN`).
    """
    uv = np.asarray(uv, float)
    r_loop, r_open = uv - np.asarray(loop_at, float), uv - np.asarray(open_at, float)
    e_loop, e_open = _rms(r_loop), _rms(r_open)
    behind = bool(np.isfinite(e_loop) and np.isfinite(e_open) and e_loop > e_open)
    run = (int(history[-1]["behind_legs"]) if history and history[-1]["behind"] else 0) + 1 if behind else 0
    alarm = behind and (run >= GUARD_LEGS or e_loop > (1.0 + GUARD_MARGIN) * e_open)
    return {
        "leg": int(leg),
        "rmse_loop": e_loop,
        "rmse_open_loop": e_open,
        "loglik_loop": float(loglik(r_loop)),
        "loglik_open_loop": float(loglik(r_open)),
        "behind": behind,
        "behind_legs": int(run),
        "fallback": behind,
        "alarm": bool(alarm),
    }


def guard_message(rec: dict, *, leg_label: str, scale: float = 1.0, unit: str = "m/s") -> str | None:
    """The guard's one line for a person (console, report, live view): the alarm's, the quieter note
    of a fallback without an alarm, or None when the loop's forecast fitted the samples at least as well.

    ``scale``: field units -> ``unit`` (a field's ``velocity_scale``)."""
    if not rec or not rec.get("behind"):
        return None
    a, b = scale * rec["rmse_loop"], scale * rec["rmse_open_loop"]
    fit = (
        f"at {leg_label}'s samples the forecast restarted from the estimate is off by {a:.4f} {unit} RMS against "
        f"{b:.4f} {unit} for the forecast alone; {leg_label} falls back to the forecast alone as its background"
    )
    return f"sampling is not helping: {fit}" if rec.get("alarm") else fit


def time_correlation(kernels, lags) -> np.ndarray:
    """The correlation in time of each space-time kernel at ``lags`` (field time units): (2, n) for the u
    and v kernels (their stationary part evaluated between one place at two times; 1 at lag 0). None
    where a kernel spans space only (no time axis: nothing decays)."""
    lags = np.atleast_1d(np.asarray(lags, np.float64))
    out = []
    for kern in kernels:
        corr = kern.k1.k2  # constant * correlation + white: the correlation part
        if np.size(corr.length_scale) != 3:
            return None
        pts = np.column_stack([np.zeros((lags.size, 2)), np.abs(lags)])
        out.append(corr(np.zeros((1, 3)), pts)[0])
    return np.asarray(out)


def relax_to_open_loop(fc, open_fc, times, t_recon: float, kernels):
    """The restarted forecast ``fc`` ((S+1, 2, R, C) at field ``times``) with its departure from the
    model alone ``open_fc`` (same shape) decayed by the GP's own correlation in time since the
    reconstruction it restarted from (field time ``t_recon``): ``open + rho(t - t_recon) (fc - open)``,
    per component. A correction the samples made is carried no longer than the GP believes a residual
    lasts; where the kernels span space only, ``fc`` is returned unchanged."""
    rho = time_correlation(kernels, np.asarray(times, np.float64) - float(t_recon))
    if rho is None:
        return fc
    fc = np.asarray(fc, np.float64)
    open_fc = np.asarray(open_fc, np.float64)
    w = rho.T[:, :, None, None]  # (S+1, 2, 1, 1)
    return open_fc + w * (fc - open_fc)
