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
from collections.abc import Callable
from pathlib import Path

import numpy as np

from passt_mav.errors import ModelError
from passt_mav.models.metrics import cosine_distance, mse

__all__ = [
    "LOOKAHEADS",
    "lookahead_errors",
    "gp_initial_states",
    "skill_report",
    "skill_lines",
    "skill_warning",
    "echo_skill",
    "pod_comparison",
    "evaluate_predictors",
    "evaluate_command",
    "format_table",
    "write_plots",
]

LOOKAHEADS = (1, 2, 5, 10, 20, 50, 100)


def lookahead_errors(
    predictor,
    data: np.ndarray,
    window: tuple[int, int],
    lookaheads=LOOKAHEADS,
    *,
    ic_stride: int = 1,
    initial_states: dict | None = None,
) -> dict:
    """``{h: {"mse", "cosine", "n_ic"}}`` for the lookaheads the window allows (see module docstring).

    ``data``: ``(time, 2, rows, cols)`` float32 (NaN = land/missing).
    ``initial_states``: ``{t: (2, R, C)}`` states to start from instead of the truth at
    ``t`` (e.g. GP reconstructions, :func:`gp_initial_states`); then only those ``t`` are used.
    """
    a, b = int(window[0]), int(window[1])
    if not (0 <= a < b <= data.shape[0]):
        raise ModelError(f"window {a}:{b} outside the field's {data.shape[0]} snapshots")
    hs = sorted({int(h) for h in lookaheads if 1 <= int(h) <= b - a - 1})
    if not hs:
        raise ModelError(f"no lookahead in {list(lookaheads)} fits window {a}:{b}")
    ics = np.arange(a, b - 1, max(1, int(ic_stride)))
    if initial_states is not None:
        ics = np.array(sorted(t for t in initial_states if a <= t < b - 1), dtype=int)
    # steps each initial condition needs: the largest lookahead it can be scored on
    need = np.array([max([h for h in hs if t + h < b], default=0) for t in ics])
    preds: dict[int, np.ndarray] = {}
    for H in sorted(set(need.tolist())):
        if H == 0:
            continue
        sel = ics[need == H]
        x = (
            np.nan_to_num(data[sel], nan=0.0)
            if initial_states is None
            else np.stack([initial_states[int(t)] for t in sel])
        )
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


def gp_initial_states(
    field,
    window: tuple[int, int],
    *,
    ic_stride: int = 1,
    path_length: int = 50,
    noise_std: float = 0.02,
    seed: int = 0,
    progress: bool = False,
) -> dict:
    """``{t: (2, R, C)}``: GP reconstructions of snapshots of ``window`` as the loop makes them.

    Samples along a random ``path_length``-move path at ``t`` with sensor noise
    ``noise_std`` (field units), GP prior the truth at ``t - 1``
    (:func:`passt_mav.models.noise.reconstruct_states`); the same states are given to
    every predictor, so their errors compare.
    """
    from passt_mav.models.noise import reconstruct_states

    a, b = int(window[0]), int(window[1])
    ts = np.arange(max(a, 1), b - 1, max(1, int(ic_stride)))
    rec = reconstruct_states(
        field.data,
        field.grid,
        field.times,
        ts,
        path_length=path_length,
        noise_std=noise_std,
        seed=seed,
        land=field.land_mask,
        progress=progress,
    )
    return {int(t): r for t, r in zip(ts, rec)}


def skill_report(
    predictor,
    field,
    *,
    train: tuple[int, int],
    val: tuple[int, int],
    horizon: int = 10,
    seed: int = 0,
    lookaheads=(1, 2, 5, 10, 20, 50),
) -> dict:
    """Skill of ``predictor`` on the held-out window ``val``: MSE vs lookahead beside persistence and DMD.

    DMD is fitted on the training part ``(train[0], val[0])``. Errors from the true states
    (``"true"``) and from GP reconstructions (``"gp"``, see :func:`gp_initial_states`).
    ``"verdict"``: per start, whether the model's mean MSE over lookaheads ``<= horizon``
    is below persistence's (``"beats_persistence"``), and the ratio.
    """
    from passt_mav.models.base import make_predictor

    fit_win = (int(train[0]), int(val[0]))
    others = {"persistence": make_predictor("persistence").fit(field, start=fit_win[0], stop=fit_win[1])}
    try:
        others["dmd"] = make_predictor("dmd").fit(field, start=fit_win[0], stop=fit_win[1])
    except Exception:  # noqa: BLE001 - DMD needs enough snapshots; the report says when it could not be fitted
        others["dmd"] = None
    preds = {"model": predictor, **{k: v for k, v in others.items() if v is not None}}
    win = (int(val[0]), int(val[1]))
    hs = [h for h in lookaheads if h <= win[1] - win[0] - 1]
    gp_states = gp_initial_states(field, win, seed=seed + 31)
    rep: dict = {"window": list(win), "fit_window": list(fit_win), "lookaheads": hs, "horizon": int(horizon)}
    for start, init in (("true", None), ("gp", gp_states)):
        rep[start] = {
            n: {str(h): v["mse"] for h, v in lookahead_errors(p, field.data, win, hs, initial_states=init).items()}
            for n, p in preds.items()
        }
    verdict = {}
    for start in ("true", "gp"):
        keep = [str(h) for h in hs if h <= horizon] or [str(hs[0])]
        m = float(np.mean([rep[start]["model"][h] for h in keep]))
        pz = float(np.mean([rep[start]["persistence"][h] for h in keep]))
        verdict[start] = {
            "model": m,
            "persistence": pz,
            "ratio": m / pz if pz > 0 else None,
            "beats_persistence": bool(m < pz),
        }
    rep["verdict"] = verdict
    return rep


def skill_lines(rep: dict) -> list[str]:
    """A printable table of a :func:`skill_report`."""
    lines = [f"skill on the held-out window {rep['window'][0]}:{rep['window'][1]} (MSE in field units^2, e.g. (m/s)^2)"]
    for start in ("true", "gp"):
        names = list(rep[start])
        lines.append(
            f"  {'from true states' if start == 'true' else 'from GP reconstructions'}".ljust(28)
            + "".join(f"{n:>13}" for n in names)
        )
        for h in rep["lookaheads"]:
            lines.append(f"    h={h}".ljust(28) + "".join(f"{rep[start][n][str(h)]:>13.3e}" for n in names))
    v = rep["verdict"]
    lines.append(
        f"  over the leg horizon (h <= {rep['horizon']}): model/persistence = {v['true']['ratio']:.3f} from true states, {v['gp']['ratio']:.3f} from GP states"
    )
    return lines


def skill_warning(meta: dict) -> str | None:
    """One line when a checkpoint's stored skill says it is worse than persistence over the leg horizon."""
    rep = (meta or {}).get("skill")
    if not rep:
        return None
    bad = [s for s in ("true", "gp") if not rep["verdict"][s]["beats_persistence"]]
    if not bad:
        return None
    v = rep["verdict"][bad[-1]]
    return (
        f"warning: this model is worse than persistence over the leg horizon on its validation window "
        f"({'GP-reconstructed' if bad[-1] == 'gp' else 'true'} starts: MSE {v['model']:.3g} vs {v['persistence']:.3g}); "
        f"consider --model persistence or more training data"
    )


def echo_skill(spec: str, meta: dict | None, echo: Callable[[str], None]) -> None:
    """Print a checkpoint's stored validation skill, and a one-line warning when it loses to persistence."""
    rep = (meta or {}).get("skill")
    if not rep:
        echo(f"model {spec}: no skill report stored (trained before skill reports, or without a validation window)")
        return
    v = rep["verdict"]
    echo(
        f"model {spec}: skill on its validation window {rep['window'][0]}:{rep['window'][1]}, MSE model/persistence over "
        f"h <= {rep['horizon']}: {v['true']['ratio']:.3f} from true states, {v['gp']['ratio']:.3f} from GP reconstructions"
    )
    w = skill_warning(meta)
    if w:
        echo(w)


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
    fin = lambda e: [None if not np.isfinite(x) else float(x) for x in e]
    return {"window": [a, b], "predicted": fin(e_pred), "true": fin(e_true)}


def evaluate_predictors(
    predictors: dict,
    windows: dict,
    lookaheads=LOOKAHEADS,
    *,
    ic_stride: int = 1,
    pod: tuple | None = None,
    pod_modes: int = 6,
) -> dict:
    """Every predictor on every window.

    ``windows``: ``{label: (data (T,2,R,C), (a, b))}`` or ``{label: (data, (a, b), initial_states)}``
    (``initial_states`` as in :func:`lookahead_errors`). ``pod``: ``(data, (a, b))`` or None.
    Returns ``{"lookahead": {label: {predictor: {h: {...}}}}, "pod": {predictor: {...}}, "seconds": {...}}``.
    """
    res: dict = {"lookahead": {}, "pod": {}, "seconds": {}}
    for label, (data, win, *init) in windows.items():
        res["lookahead"][label] = {}
        for name, p in predictors.items():
            t0 = time.perf_counter()
            res["lookahead"][label][name] = {
                str(h): v
                for h, v in lookahead_errors(
                    p, data, win, lookaheads, ic_stride=ic_stride, initial_states=init[0] if init else None
                ).items()
            }
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
            lines.append(
                f"{n:>12} {d['window']}: predicted "
                + " ".join("n/a" if x is None else f"{x:.3f}" for x in d["predicted"])
                + " | true "
                + " ".join(f"{x:.3f}" for x in d["true"])
            )
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
        p = out_dir / f"error_vs_lookahead_{label.replace('/', '_')}.png"
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
            ax.bar(
                k - 0.4 + w * (i + 1.5), [np.nan if x is None else x for x in res["pod"][n]["predicted"]], w, label=n
            )
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


def evaluate_command(
    *,
    model: str,
    data: str,
    train=(200, 300),
    test=(300, 400),
    oscillating: str | None = None,
    lookaheads=LOOKAHEADS,
    baselines=("dmd", "persistence"),
    ic_stride: int = 1,
    pod_window=(300, 350),
    pod_modes: int = 6,
    threads: int | None = None,
    out: str | None = None,
    gp_starts: bool = True,
    gp_ic_stride: int = 4,
    gp_path_length: int = 50,
    gp_noise: float = 0.02,
    seed: int = 0,
) -> dict:
    """What ``passt-mav model evaluate`` does; returns the JSON-able results (and writes them under ``out``).

    With ``gp_starts``, every test window is also scored from GP reconstructions of its
    snapshots (label ``WINDOW/gp``; every ``gp_ic_stride``-th snapshot, ``gp_path_length``-move
    random paths, sensor noise ``gp_noise``; see :func:`gp_initial_states`): the states the
    PASST loop starts its model from.
    """
    from passt_mav.fields.datasets import resolve_field

    if threads is not None:
        _set_torch_threads(threads)
    field = resolve_field(data, series=True)
    m, predictors = _predictors(model, field, train, baselines)
    gp = dict(ic_stride=gp_ic_stride, path_length=gp_path_length, noise_std=gp_noise, seed=seed) if gp_starts else None
    windows = _evaluation_windows(field, train, test, oscillating, gp)
    pw = (pod_window[0], min(pod_window[1], field.n_times))
    res = evaluate_predictors(
        predictors, windows, lookaheads, ic_stride=ic_stride, pod=(field.data, pw), pod_modes=pod_modes
    )
    res.update(_stored_skill(getattr(m, "metadata_", None)))
    res["config"] = {
        "gp_starts": gp_starts,
        "gp_ic_stride": gp_ic_stride,
        "gp_path_length": gp_path_length,
        "gp_noise": gp_noise,
        "seed": seed,
        "model": model,
        "data": data,
        "train": list(train),
        "test": list(test),
        "oscillating": oscillating,
        "lookaheads": list(lookaheads),
        "ic_stride": ic_stride,
        "pod_window": list(pw),
        "baselines": list(baselines),
        "data_hash": field.data_hash(),
    }
    if out:
        _write_results(res, Path(out))
    return res


def _set_torch_threads(threads: int) -> None:
    """Run torch on ``threads`` CPU threads."""
    import torch

    torch.set_num_threads(int(threads))


def _stored_skill(meta: dict | None) -> dict:
    """``skill`` and ``skill_warning`` entries of the results from a checkpoint's metadata that holds a
    skill report (else none)."""
    if meta and meta.get("skill"):
        return {"skill": meta["skill"], "skill_warning": skill_warning(meta)}
    return {}


def _predictors(model: str, field, train: tuple[int, int], baselines) -> tuple[object, dict]:
    """``(m, predictors)``: the model ``m`` of spec ``model`` (checked to be on the field's grid) and
    ``{name: predictor}`` of it plus each baseline in ``baselines``, fitted on ``field``'s ``train`` window."""
    from passt_mav.models.base import make_predictor

    name, m = _model_from_spec(model, field, train)
    if tuple(getattr(m, "grid_shape_", ())) != field.data.shape[2:]:
        raise ModelError(
            f"model grid {getattr(m, 'grid_shape_', None)} does not match the field's {field.data.shape[2:]}"
        )
    predictors = {name: m}
    for bname in baselines:
        if bname not in predictors:
            predictors[bname] = make_predictor(bname).fit(field, start=train[0], stop=train[1])
    return m, predictors


def _evaluation_windows(field, train, test, oscillating: str | None, gp: dict | None) -> dict:
    """The windows to score: ``train`` and ``test`` of ``field``, ``test`` of the ``oscillating``
    field when given, and with ``gp`` (keywords of :func:`gp_initial_states`) the test windows
    again from GP-reconstructed initial states (labels ``test/gp``, ``oscillating/gp``)."""
    from passt_mav.fields.datasets import resolve_field

    windows = {"train": (field.data, train), "test": (field.data, test)}
    if oscillating:
        osc = resolve_field(oscillating)
        if osc.data.shape[2:] != field.data.shape[2:]:
            raise ModelError(f"--oscillating grid {osc.data.shape[2:]} differs from --data's {field.data.shape[2:]}")
        windows["oscillating"] = (osc.data, test)
    if gp is not None:
        for label, fld in (("test", field), ("oscillating", osc if oscillating else None)):
            if fld is not None:
                windows[f"{label}/gp"] = (fld.data, test, gp_initial_states(fld, test, **gp))
    return windows


def _write_results(res: dict, od: Path) -> None:
    """Write the plots and ``results.json`` under ``od`` (created); records ``files`` and ``out`` in ``res``."""
    od.mkdir(parents=True, exist_ok=True)
    res["files"] = write_plots(res, od)
    (od / "results.json").write_text(json.dumps(res, indent=1) + "\n")
    res["out"] = str(od)
