"""Model evaluation: error vs lookahead from every initial condition of a window, and POD energy.

For a window ``[a, b)`` of a field and each lookahead ``h`` (kept when ``h <= b - a - 1``),
every snapshot ``t`` with ``t + h < b`` (every ``ic_stride``-th) is an initial condition;
the prediction ``h`` steps ahead is compared with snapshot ``t + h`` (MSE, mean cosine
distance of the velocity vectors). Initial conditions are batched: those needing the
same number of steps run in one ``predict`` call. Land cells (NaN) are filled with 0 at
the input, as the PASST loop does, and left out of the metrics.

POD energy: the model is rolled out from the first snapshot of ``pod_window`` to its
end; the cumulative energy of the first POD modes of the predicted series is set
beside that of the true series (paper: first four modes 89.8 % predicted vs 91.8 % true,
snapshots 300-350).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from passt_mav.errors import ModelError
from passt_mav.models.metrics import cosine_distance, mse

__all__ = ["LOOKAHEADS", "lookahead_errors", "pod_comparison", "evaluate_predictors", "evaluate_command", "format_table", "write_plots"]

LOOKAHEADS = (1, 2, 5, 10, 20, 50, 100)


def lookahead_errors(predictor, data: np.ndarray, window: tuple[int, int], lookaheads=LOOKAHEADS, *, ic_stride: int = 1) -> dict:
    """``{h: {"mse", "cosine", "n_ic"}}`` for the lookaheads the window allows (see module docstring).

    ``data``: ``(time, 2, rows, cols)`` float32 (NaN = land/missing).
    """
    a, b = int(window[0]), int(window[1])
    if not (0 <= a < b <= data.shape[0]):
        raise ModelError(f"window {a}:{b} outside the field's {data.shape[0]} snapshots")
    hs = sorted({int(h) for h in lookaheads if 1 <= int(h) <= b - a - 1})
    if not hs:
        raise ModelError(f"no lookahead in {list(lookaheads)} fits window {a}:{b}")
    ics = np.arange(a, b - 1, max(1, int(ic_stride)))
    # steps each initial condition needs: the largest lookahead it can be scored on
    need = np.array([max([h for h in hs if t + h < b], default=0) for t in ics])
    preds: dict[int, np.ndarray] = {}
    for H in sorted(set(need.tolist())):
        if H == 0:
            continue
        sel = ics[need == H]
        x = np.nan_to_num(data[sel], nan=0.0)
        p = predictor.predict(x, H)  # (n, H, 2, R, C)
        for t, pt in zip(sel, p):
            preds[int(t)] = pt
    out = {}
    for h in hs:
        ts = [t for t in preds if t + h < b]
        P = np.stack([preds[t][h - 1] for t in ts])
        Tr = data[np.array(ts) + h]
        out[h] = {"mse": mse(P, Tr), "cosine": cosine_distance(P, Tr), "n_ic": len(ts)}
    return out


def pod_comparison(predictor, data: np.ndarray, window: tuple[int, int], n_modes: int = 6) -> dict:
    """Cumulative POD energy of the first ``n_modes`` of a roll-out from ``window[0]`` vs the truth."""
    from passt_mav.fields.analysis import pod_energy

    a, b = int(window[0]), int(window[1])
    if not (0 <= a < b <= data.shape[0]) or b - a < 3:
        raise ModelError(f"POD window {a}:{b} invalid for {data.shape[0]} snapshots (need >= 3 snapshots)")
    true = data[a:b]
    land = ~np.isfinite(true).all(axis=(0, 1))
    x0 = np.nan_to_num(true[0], nan=0.0)
    pred = np.concatenate([x0[None], predictor.predict(x0, b - a - 1)])
    pred[:, :, land] = 0.0
    t0 = np.where(np.isfinite(true), true, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        # a constant roll-out (persistence) has no fluctuation energy: reported as None
        e_pred, e_true = pod_energy(pred, n_modes), pod_energy(t0, n_modes)
    fin = lambda e: [None if not np.isfinite(x) else float(x) for x in e]  # noqa: E731
    return {"window": [a, b], "predicted": fin(e_pred), "true": fin(e_true)}


def evaluate_predictors(predictors: dict, windows: dict, lookaheads=LOOKAHEADS, *, ic_stride: int = 1, pod: tuple | None = None, pod_modes: int = 6) -> dict:
    """Every predictor on every window.

    ``windows``: ``{label: (data (T,2,R,C), (a, b))}``. ``pod``: ``(data, (a, b))`` or None.
    Returns ``{"lookahead": {label: {predictor: {h: {...}}}}, "pod": {predictor: {...}}, "seconds": {...}}``.
    """
    res: dict = {"lookahead": {}, "pod": {}, "seconds": {}}
    for label, (data, win) in windows.items():
        res["lookahead"][label] = {}
        for name, p in predictors.items():
            t0 = time.perf_counter()
            res["lookahead"][label][name] = {str(h): v for h, v in lookahead_errors(p, data, win, lookaheads, ic_stride=ic_stride).items()}
            res["seconds"][f"{label}/{name}"] = round(time.perf_counter() - t0, 3)
    if pod is not None:
        for name, p in predictors.items():
            res["pod"][name] = pod_comparison(p, pod[0], pod[1], pod_modes)
    return res


def format_table(res: dict) -> str:
    """A side-by-side text table: MSE and cosine distance per lookahead, window and predictor."""
    lines = []
    for label, per in res["lookahead"].items():
        names = list(per)
        hs = list(next(iter(per.values())))
        lines.append(f"[{label}]  MSE / cosine distance by lookahead (steps)")
        lines.append("h".rjust(5) + "".join(f"{n:>24}" for n in names))
        for h in hs:
            lines.append(f"{h:>5}" + "".join(f"{per[n][h]['mse']:>12.3e} / {per[n][h]['cosine']:<9.4f}" for n in names))
    if res.get("pod"):
        lines.append("[POD] cumulative energy of the first modes, predicted roll-out vs true")
        for n, d in res["pod"].items():
            lines.append(f"{n:>12} {d['window']}: predicted " + " ".join("n/a" if x is None else f"{x:.3f}" for x in d["predicted"]) + " | true " + " ".join(f"{x:.3f}" for x in d["true"]))
    return "\n".join(lines)


def write_plots(res: dict, out_dir: Path) -> list[str]:
    """PNG figures: error vs lookahead per window (MSE log-scale, cosine) and POD bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    for label, per in res["lookahead"].items():
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for name, d in per.items():
            hs = [int(h) for h in d]
            ax[0].plot(hs, [d[h]["mse"] for h in d], "o-", label=name)
            ax[1].plot(hs, [d[h]["cosine"] for h in d], "o-", label=name)
        for a_, yl in zip(ax, ("MSE", "mean cosine distance")):
            a_.set_xscale("log")
            a_.set_xlabel("lookahead (snapshots)")
            a_.set_ylabel(yl)
            a_.grid(alpha=0.3)
        ax[0].set_yscale("log")
        ax[0].legend()
        fig.suptitle(f"prediction error vs lookahead - {label}")
        fig.tight_layout()
        p = out_dir / f"error_vs_lookahead_{label}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        files.append(str(p))
    if res.get("pod"):
        fig, ax = plt.subplots(figsize=(7, 4))
        names = list(res["pod"])
        first = res["pod"][names[0]]
        k = np.arange(1, len(first["true"]) + 1)
        w = 0.8 / (len(names) + 1)
        ax.bar(k - 0.4 + w / 2, first["true"], w, label="true")
        for i, n in enumerate(names):
            ax.bar(k - 0.4 + w * (i + 1.5), [np.nan if x is None else x for x in res["pod"][n]["predicted"]], w, label=n)
        ax.set_xlabel("POD modes")
        ax.set_ylabel("cumulative energy fraction")
        ax.set_ylim(0, 1.05)
        ax.set_title(f"POD energy, snapshots {first['window'][0]}-{first['window'][1]}")
        ax.legend()
        fig.tight_layout()
        p = out_dir / "pod_energy.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        files.append(str(p))
    return files


def _model_from_spec(spec: str, field, train: tuple[int, int]):
    from passt_mav.models.base import PREDICTORS, load_predictor, make_predictor

    if spec in PREDICTORS:
        return spec, make_predictor(spec).fit(field, start=train[0], stop=train[1])
    p = load_predictor(spec)
    return p.name, p


def evaluate_command(*, model: str, data: str, train=(200, 300), test=(300, 400), oscillating: str | None = None, lookaheads=LOOKAHEADS, baselines=("dmd", "persistence"), ic_stride: int = 1, pod_window=(300, 350), pod_modes: int = 6, threads: int | None = None, out: str | None = None) -> dict:
    """What ``passt-mav model evaluate`` does; returns the JSON-able results (and writes them under ``out``)."""
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.models.base import make_predictor

    if threads is not None:
        import torch

        torch.set_num_threads(int(threads))
    field = resolve_field(data)
    name, m = _model_from_spec(model, field, train)
    if tuple(getattr(m, "grid_shape_", ())) != field.data.shape[2:]:
        raise ModelError(f"model grid {getattr(m, 'grid_shape_', None)} does not match the field's {field.data.shape[2:]}")
    predictors = {name: m}
    for bname in baselines:
        if bname not in predictors:
            predictors[bname] = make_predictor(bname).fit(field, start=train[0], stop=train[1])
    windows = {"train": (field.data, train), "test": (field.data, test)}
    if oscillating:
        osc = resolve_field(oscillating)
        if osc.data.shape[2:] != field.data.shape[2:]:
            raise ModelError(f"--oscillating grid {osc.data.shape[2:]} differs from --data's {field.data.shape[2:]}")
        windows["oscillating"] = (osc.data, test)
    pw = (pod_window[0], min(pod_window[1], field.n_times))
    res = evaluate_predictors(predictors, windows, lookaheads, ic_stride=ic_stride, pod=(field.data, pw), pod_modes=pod_modes)
    res["config"] = {"model": model, "data": data, "train": list(train), "test": list(test), "oscillating": oscillating, "lookaheads": list(lookaheads), "ic_stride": ic_stride, "pod_window": list(pw), "baselines": list(baselines), "data_hash": field.data_hash()}
    if out:
        od = Path(out)
        od.mkdir(parents=True, exist_ok=True)
        res["files"] = write_plots(res, od)
        (od / "results.json").write_text(json.dumps(res, indent=1) + "\n")
        res["out"] = str(od)
    return res
