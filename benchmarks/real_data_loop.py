"""Benchmark: the missions' PASST loop on real current files, leg by leg against the forecast alone.

    .venv/bin/python benchmarks/real_data_loop.py                 # 24 cases, prints the table
    .venv/bin/python benchmarks/real_data_loop.py --json out.json --cases 6

Real files from ``../shared/data`` (read there, never copied): NOAA Global RTOFS off Washington
(``wa_RTOFS_global.nc``), the HYCOM-like file over the same coast (``gridded_current.nc``) and the
MARACOOS HF-radar totals (``RU_MARA_*.nc``, cm/s, where a region has data in every frame). Each case
is a (file, region, start snapshot, start cell, model, path length): the region is imported with
:func:`passt_mav.fields.importers.import_currents`, the model is persistence or DMD fitted on the
snapshots before the start (never on the hours it is asked to predict; persistence where a file is
too short to fit one before four legs), and the loop is the one
``missions/rtofs.yaml`` flies (information planner, ``select`` prior blend with share 0.05, GP
bias, the guard), built by :func:`passt_mav.loop.legstep.build_loop` and driven leg by leg through
:class:`passt_mav.loop.legstep.LegStep` exactly as ``passt-mav run`` drives it: a boat at the
mission's speed follows the planned cells' centres, reads the true current (bilinear in space and
time) plus N(0, 0.02 m/s) noise every ``--sample-s`` seconds of vehicle time, and those readings
go through ``LegStep.absorb`` (field units, thinning, stretch, GP update, RMSE vs the truth).

Per (case, leg): PASST's RMSE at the leg's end (m/s, water cells) against the model alone's (the
same model from the truth at the start snapshot, never re-initialised); the same loop with a
random walk and with a lawnmower as the planner. Printed: the share of (case, leg) where PASST <=
1.02 x the model alone, the worst ratio, and PASST's mean RMSE against the random walk's and the
lawnmower's. Seeds: ``--seed`` picks the cases (regions, start snapshots, start cells) and every
sensor's noise; the same seed gives the same table.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

# --repo DIR: run another checkout's package (e.g. the commit before a change) on the same cases
_REPO = next((sys.argv[i + 1] for i, x in enumerate(sys.argv[:-1]) if x == "--repo"), None)
sys.path.insert(0, str(Path(_REPO).resolve() if _REPO else Path(__file__).resolve().parent.parent))

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"

#: (file, units, boxes to draw regions from (south, west, north, east), region size deg (lat, lon), grid)
FILES = {
    "rtofs": ("wa_RTOFS_global.nc", "m/s", (46.6, -126.8, 49.6, -124.0), (1.2, 1.2), (16, 16)),
    "gridded": ("gridded_current.nc", None, (47.0, -125.9, 49.0, -124.6), (1.2, 1.0), (14, 12)),
    "hfradar": (
        "RU_MARA_20180301T000000Z-20180301T120000Z_aggregated.nc",
        "cm/s",
        (39.8, -72.5, 41.2, -69.8),
        (0.3, 0.4),
        (12, 14),
    ),
}


def _mission(path_length: int, model: str, legs: int, t0: int, start_cell, region) -> object:
    """``missions/rtofs.yaml`` with this case's region, model, path length, legs, t0 and start cell."""
    import yaml

    from passt_mav.mission.config import validate_mission

    base = yaml.safe_load((Path(__file__).resolve().parent.parent / "missions" / "rtofs.yaml").read_text())
    base["region"].update(region)
    base.update(model=model, legs=legs, t0=t0, start_cell=list(start_cell))
    base["planner"]["path_length"] = path_length
    return validate_mission(base, source="real_data_loop")


def _readings():
    """:mod:`passt_mav.loop.readings`, from this checkout's file when ``--repo``'s package predates it (the
    same readings and legs for both)."""
    try:
        from passt_mav.loop import readings

        readings.fly_legs  # noqa: B018 - an older package has the module without it
    except (ModuleNotFoundError, ImportError, AttributeError):
        import importlib.util

        path = Path(__file__).resolve().parent.parent / "passt_mav" / "loop" / "readings.py"
        spec = importlib.util.spec_from_file_location("_readings", path)
        readings = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(readings)
    return readings


def _build_loop():
    """:func:`passt_mav.loop.legstep.build_loop` (a module attribute, so a study can swap it)."""
    from passt_mav.loop.legstep import build_loop

    return build_loop


def fly_case(case: dict, planner: str, *, sample_s: float = 120.0, noise: float = 0.02) -> list[dict]:
    """One case with ``planner`` (the mission's, or a baseline's): per leg, PASST's and the model
    alone's RMSE (m/s) and the guard's record."""
    from passt_mav.loop.legstep import LegStep

    build_loop = _build_loop()
    from passt_mav.models.base import make_predictor

    field, t0 = case["field"], case["t0"]
    cfg = _mission(case["L"], case["model"], case["legs"], t0, case["start"], case["region"])
    if planner != "mission":
        cfg = cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"name": planner})})
    # the hours up to the start only (persistence learns nothing from them; it needs two to be fitted)
    predictor = make_predictor(case["model"]).fit(field, stop=max(t0 + 1, 2))
    loop = build_loop(cfg, predictor, field.grid, land=field.land_mask)
    step = LegStep(cfg, field, loop)
    rng = np.random.default_rng(case["seed"])
    out = []
    legs = _readings().fly_legs(
        step, case["start"], case["legs"], every_s=sample_s, noise_std=noise, rng=rng, strict=False
    )
    for i, (_planned, ab) in enumerate(legs):
        if ab.rmse_passt is None or ab.rmse_model is None or ab.t_state > field.times[-1]:
            break
        out.append({"leg": i, "passt": ab.rmse_passt, "model": ab.rmse_model, "guard": getattr(ab, "guard", None)})
    return out


def _region(box, size, rng) -> dict:
    s, w, n, e = box
    lat0 = rng.uniform(s, n - size[0])
    lon0 = rng.uniform(w, e - size[1])
    return {"south": lat0, "west": lon0, "north": lat0 + size[0], "east": lon0 + size[1]}


def make_cases(n: int, seed: int, say=print) -> list[dict]:
    """``n`` cases over the files present (module docstring), drawn with ``seed``; a region whose
    water cells have gaps at some times, or is over 65 % land, is redrawn (up to 40 n tries a file)."""
    import geo
    from passt_mav.fields.importers import import_currents

    rng = np.random.default_rng(seed)
    present = [k for k, f in FILES.items() if (DATA / f[0]).exists()]
    if not present:
        raise SystemExit(f"no real current files in {DATA}")
    cases, tries = [], {k: 0 for k in present}
    while len(cases) < n and present:
        key = present[len(cases) % len(present)]
        tries[key] += 1
        if tries[key] > 40 * n:  # this file has no region that qualifies: the others go on
            say(f"  no usable region in {FILES[key][0]} after {tries[key] - 1} tries")
            present.remove(key)
            continue
        fname, units, box, size, shape = FILES[key]
        reg = _region(box, size, rng)
        grid = geo.RegionGrid(reg["south"], reg["west"], reg["north"], reg["east"], *shape)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                field = import_currents(DATA / fname, grid, units=units)
            except Exception as exc:  # noqa: BLE001 - a region off the file's data: draw another
                say(f"  skip {key} region: {exc}")
                continue
        # a cell without data at some of the times is left out (NaN throughout, as land): the loop's
        # state must hold every water cell, and the rule for gaps that come and go is not this bench's
        gappy = field.mask.any(axis=0) & ~field.land_mask
        if gappy.any():
            data = field.data.copy()
            data[:, :, gappy] = np.nan
            field = type(field)(data, field.grid, field.times, field.time_origin, field.units, dict(field.attrs))
        land = field.land_mask
        if land.mean() > 0.65:
            say(f"  skip {key} region: {land.mean():.0%} without data at every time")
            continue
        # the model is fitted before t0; legs need room after it
        T = field.n_times
        cell_m = field.grid.mean_cell_size_m
        L = int(rng.choice([5, 10, 20]))
        steps = max(1, round(L * cell_m / 2.0 / field.dt))
        legs = 4
        model = ("persistence", "dmd")[len(cases) // len(present) % 2]
        t_hi = T - 2 - legs * steps  # one snapshot to spare for a leg that runs long
        if t_hi < 0:
            L, steps = 5, max(1, round(5 * cell_m / 2.0 / field.dt))
            t_hi = T - 2 - legs * steps
        t_lo = max(4, T // 4) if model == "dmd" else 0  # DMD is fitted on the snapshots before t0
        if t_hi < t_lo and model == "dmd":
            model, t_lo = "persistence", 0  # too short a file to fit DMD before the legs
        if t_hi < t_lo:
            say(f"  skip {key} region: {T} snapshots leave no room for {legs} legs")
            continue
        t0 = int(rng.integers(t_lo, t_hi + 1))
        water = np.argwhere(~land)
        start = tuple(int(x) for x in water[rng.integers(len(water))])
        cases.append(
            {
                "file": key,
                "region": {**reg, "rows": shape[0], "cols": shape[1]},
                "field": field,
                "t0": t0,
                "start": start,
                "L": L,
                "legs": legs,
                "model": model,
                "seed": int(rng.integers(1 << 31)),
            }
        )
    return cases


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sample-s", type=float, default=120.0, help="vehicle seconds between readings")
    ap.add_argument("--baselines", default="random,lawnmower", help="planners flown in the same loop ('' = none)")
    ap.add_argument("--json", default=None, help="write every (case, leg) figure here")
    ap.add_argument("--only", default=None, help="fly only these case indices (comma-separated; same draws)")
    ap.add_argument("--repo", default=None, help="import passt_mav from this checkout instead (same cases)")
    a = ap.parse_args(argv)
    from tqdm import tqdm

    cases = make_cases(a.cases, a.seed)
    if a.only:
        cases = [cases[int(i)] for i in a.only.split(",")]
    rows = []
    for c in tqdm(cases, desc="cases", file=sys.stderr):
        row = {k: c[k] for k in ("file", "region", "t0", "start", "L", "legs", "model")}
        row["mission"] = fly_case(c, "mission", sample_s=a.sample_s)
        for b in filter(None, a.baselines.split(",")):
            row[b] = fly_case(c, b, sample_s=a.sample_s)
        rows.append(row)
    legs = [(r, x) for r in rows for x in r["mission"]]
    ratios = np.array([x["passt"] / x["model"] for _, x in legs])
    fell_back = sum(bool(x["guard"] and x["guard"]["fallback"]) for _, x in legs)
    print(f"{len(rows)} cases, {len(legs)} (case, leg) pairs")
    for r in rows:
        rr = [f"{x['passt'] / x['model']:.3f}" for x in r["mission"]]
        print(
            f"  {r['file']:<8} {r['model']:<11} L={r['L']:<3} t0={r['t0']:<3} start={r['start']}  PASST/model per leg: {' '.join(rr)}"
        )
    print(
        f"PASST <= 1.02 x model alone: {np.mean(ratios <= 1.02) * 100:.1f} % of (case, leg); worst ratio {ratios.max():.3f}; "
        f"mean ratio {ratios.mean():.3f}; guard fell back on {fell_back} legs"
    )
    mean_p = float(np.mean([x["passt"] for _, x in legs]))
    print(f"mean RMSE (m/s): PASST {mean_p:.4f}, model alone {np.mean([x['model'] for _, x in legs]):.4f}")
    for b in filter(None, a.baselines.split(",")):
        pairs = [(x["passt"], y["passt"]) for r in rows for x, y in zip(r["mission"], r[b])]
        p, q = np.array(pairs).T
        print(
            f"  same loop, {b}: mean {q.mean():.4f} m/s; PASST / {b} {p.mean() / q.mean():.3f}; PASST lower on {np.mean(p < q) * 100:.0f} % of legs"
        )
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
