"""passt-mav data: make, import, inspect or plot a flow field (.nc).

Subcommands: ``cylinder`` and ``oscillating`` (CFD, from
:mod:`passt_mav.fields.cylinder_cli`), ``ocean`` (synthetic North Atlantic),
``import`` (real model/radar files), ``info`` and ``show``.

Only the standard library is imported at module level (``passt-mav --help``
must stay fast); numpy, xarray and matplotlib are imported inside the handlers.
"""

from __future__ import annotations

import argparse
import importlib
import json

HELP = "Make, import, inspect or plot a flow field (.nc)"
EXAMPLES = """examples:
  passt-mav data ocean --out ocean.nc --seed 0 --hours 504
  passt-mav data import RU_MARA_20180301.nc --region 38,-74,41,-69 --grid 30x30 --out radar.nc
  passt-mav data import hycom.nc --region north_atlantic --start 2018-03-01T00:00Z --hours 504 --out na.nc
  passt-mav data info ocean.nc --json
  passt-mav data show ocean.nc --out ocean.png --time 100
  passt-mav data cylinder --help
"""

#: named regions for --region (cell-centre corners S, W, N, E and default grid)
REGIONS = {"north_atlantic": "the paper's 30x30 North Atlantic region (geo.north_atlantic_grid)"}


def _add_cylinder(sub, name: str, oscillating: bool) -> None:
    help_ = ("cylinder wake CFD, Re 200 (static cylinder)" if not oscillating
             else "cylinder wake CFD, Re 200, cylinder oscillating once per 96 snapshots")
    try:
        # stdlib-only module: importing it here keeps the parser complete without numpy
        cylinder_cli = importlib.import_module("passt_mav.fields.cylinder_cli")
    except ModuleNotFoundError as exc:
        if exc.name != "passt_mav.fields.cylinder_cli":
            raise
        p = sub.add_parser(name, help=help_ + " [not available]", description=help_)
        p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        p.set_defaults(_data_run=_cylinder_missing)
        return
    p = sub.add_parser(name, help=help_, description=help_, formatter_class=argparse.RawDescriptionHelpFormatter)
    cylinder_cli.add_cylinder_arguments(p)
    p.set_defaults(_data_run=lambda args, _o=oscillating: cylinder_cli.run_cylinder(args, oscillating=_o))


def _cylinder_missing(args) -> int:
    from passt_mav.errors import UserError

    raise UserError("the cylinder CFD generator is not part of this installation (passt_mav/fields/cylinder_cli.py is missing)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="data_command", metavar="SUBCOMMAND")
    _add_cylinder(sub, "cylinder", oscillating=False)
    _add_cylinder(sub, "oscillating", oscillating=True)

    o = sub.add_parser("ocean", help="synthetic North Atlantic currents (jet, rings, M2 tide), seconds to make",
                       description="Write the embedded synthetic North Atlantic surface-current field "
                       "(meandering jet, drifting rings, M2 tide; 30x30 hourly, m/s) to a NetCDF file.")
    o.add_argument("--out", required=True, help="output .nc file")
    o.add_argument("--seed", type=int, default=0, help="realisation seed (default 0)")
    o.add_argument("--hours", type=int, default=504, help="number of hourly snapshots (default 504)")
    o.add_argument("--json", action="store_true", help="print a JSON summary")
    o.set_defaults(_data_run=_run_ocean)

    i = sub.add_parser("import", help="regrid a real model/radar file (HYCOM, RTOFS, Copernicus, HF radar) to a region grid",
                       description="Read surface currents from an ocean-model or HF-radar NetCDF file, convert units "
                       "to m/s, pick the surface, select the time window and regrid bilinearly to a region grid. "
                       "Cells without data stay NaN (masked).")
    i.add_argument("file", help="source NetCDF file")
    i.add_argument("--region", default="north_atlantic",
                   help="S,W,N,E cell-centre corners in degrees (write --region=S,W,N,E when S is negative), "
                   "or a named region: " + ", ".join(REGIONS) + " (default)")
    i.add_argument("--grid", default="30x30", help="ROWSxCOLS (default 30x30)")
    i.add_argument("--start", default=None, help="first time, ISO-8601 UTC (default: the file's first)")
    i.add_argument("--hours", type=int, default=None, help="window length in hours (default: the rest of the file)")
    i.add_argument("--variables", default=None, help="U,V variable names (default: detected)")
    i.add_argument("--units", default=None, help="override the velocity units of the file (e.g. cm/s)")
    i.add_argument("--out", required=True, help="output .nc file")
    i.add_argument("--json", action="store_true", help="print the coverage report as JSON")
    i.set_defaults(_data_run=_run_import)

    n = sub.add_parser("info", help="shape, times, units, grid, coverage, speeds, POD energies of a field file",
                       description="Describe a passt_mav field file (or builtin:ocean / builtin:cylinder ...).")
    n.add_argument("file", help="field .nc file or builtin:NAME")
    n.add_argument("--modes", type=int, default=5, help="number of POD modes to report (default 5)")
    n.add_argument("--json", action="store_true", help="print JSON instead of text")
    n.set_defaults(_data_run=_run_info)

    s = sub.add_parser("show", help="plot one snapshot: speed colour map and arrows",
                       description="Plot one snapshot of a field file: speed colour map with velocity arrows "
                       "(lat/lon axes for geographic fields, x/y metres for metric ones).")
    s.add_argument("file", help="field .nc file or builtin:NAME")
    s.add_argument("--out", required=True, help="output image (.png, .pdf, .svg)")
    s.add_argument("--time", type=int, default=0, help="snapshot index (negative counts from the end; default 0)")
    s.set_defaults(_data_run=_run_show)


def run(args: argparse.Namespace) -> int:
    fn = getattr(args, "_data_run", None)
    if fn is None:
        from passt_mav.errors import UserError

        raise UserError("choose a subcommand: cylinder, oscillating, ocean, import, info, show (see 'passt-mav data --help')")
    return int(fn(args) or 0)


# -- handlers -------------------------------------------------------------------
def _run_ocean(args) -> int:
    from passt_mav.fields.ocean import make_ocean_default

    f = make_ocean_default(seed=args.seed, hours=args.hours)
    f.attrs["command"] = f"passt-mav data ocean --seed {args.seed} --hours {args.hours}"
    path = f.to_netcdf(args.out)
    sp = f.speed()
    summary = {"out": str(path), "shape": list(f.shape), "seed": args.seed, "max_speed_m_s": float(sp.max()),
               "mean_speed_m_s": float(sp.mean()), "data_hash": f.data_hash()}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"ocean field {f.shape[0]} x {f.shape[2]}x{f.shape[3]} (seed {args.seed}), "
              f"speed max {summary['max_speed_m_s']:.2f} m/s, mean {summary['mean_speed_m_s']:.2f} m/s")
        print(f"wrote {path}")
    return 0


def parse_region(text: str, grid_text: str):
    """``--region`` and ``--grid`` -> :class:`geo.RegionGrid` (UserError on bad input)."""
    import geo
    from passt_mav.errors import UserError

    try:
        rows, cols = (int(x) for x in grid_text.lower().split("x"))
    except ValueError:
        raise UserError(f"--grid must look like ROWSxCOLS (e.g. 30x30), got {grid_text!r}") from None
    name = text.strip().lower()
    if name == "north_atlantic":
        d = dict(geo.NORTH_ATLANTIC)
        d.update(rows=rows, cols=cols)
        return geo.RegionGrid(**d)
    try:
        s, w, n, e = (float(x) for x in text.split(","))
    except ValueError:
        raise UserError(f"--region must be S,W,N,E in degrees or one of {', '.join(REGIONS)}, got {text!r}") from None
    return geo.RegionGrid(s, w, n, e, rows, cols)


def _run_import(args) -> int:
    from passt_mav.errors import UserError
    from passt_mav.fields.importers import coverage_report, import_currents

    grid = parse_region(args.region, args.grid)
    variables = None
    if args.variables:
        variables = tuple(x.strip() for x in args.variables.split(","))
        if len(variables) != 2 or not all(variables):
            raise UserError(f"--variables must be U,V (two names), got {args.variables!r}")
    f = import_currents(args.file, grid, start=args.start, hours=args.hours, variables=variables, units=args.units)
    f.attrs["command"] = "passt-mav data import " + " ".join(
        [str(args.file), "--region", args.region, "--grid", args.grid]
        + (["--start", args.start] if args.start else []) + (["--hours", str(args.hours)] if args.hours else []))
    path = f.to_netcdf(args.out)
    rep = coverage_report(f)
    rep.update(out=str(path), time_origin=f.time_origin, variables=f.attrs["variables"],
               time_selection=f.attrs["time_selection"])
    if args.json:
        print(json.dumps(rep, indent=2))
    else:
        print(f"imported {f.attrs['variables'][0]}/{f.attrs['variables'][1]} -> {f.n_times} snapshots from {f.time_origin} "
              f"on {grid.rows}x{grid.cols} ({f.attrs['time_selection']})")
        print(f"coverage {rep['coverage']:.1%} of cell-times; cells with data at every time {rep['cells_all']:.1%}, "
              f"at some time {rep['cells_any']:.1%}")
        print(f"wrote {path}")
    return 0


def _find_key(d, key: str):
    """First value whose key contains ``key`` (case-insensitive), searching nested dicts."""
    if isinstance(d, dict):
        for k, v in d.items():
            if key in str(k).lower() and isinstance(v, (int, float)) and not isinstance(v, bool):
                return float(v)
        for v in d.values():
            r = _find_key(v, key)
            if r is not None:
                return r
    return None


def field_info(f, n_modes: int = 5) -> dict:
    """JSON-able description of a FlowField (what ``data info`` prints)."""
    import numpy as np

    from passt_mav.fields.analysis import pod_energy
    from passt_mav.fields.importers import coverage_report

    sp = f.speed()
    ok = np.isfinite(sp)
    info: dict = {
        "shape": list(f.shape),
        "grid": f.grid.describe(),
        "units": f.units,
        "n_times": f.n_times,
        "time_origin": f.time_origin,
    }
    if f.time_origin is not None:
        dts = f.datetimes()
        info["first_time"] = str(dts[0].astype("datetime64[s]")) + "Z"
        info["last_time"] = str(dts[-1].astype("datetime64[s]")) + "Z"
    else:
        info["first_time"], info["last_time"] = float(f.times[0]), float(f.times[-1])
    try:
        info["dt"] = f.dt
    except Exception:  # noqa: BLE001 - a single snapshot or uneven steps: report what there is
        info["dt"] = None
    if f.is_geographic:
        dy, dx = f.grid.cell_size_m
        info["cell_size_m"] = [round(dy, 1), round(dx, 1)]
    info["coverage"] = coverage_report(f)
    info["speed"] = (
        {k: float(fn(sp[ok])) for k, fn in (("min", np.min), ("mean", np.mean), ("median", np.median), ("max", np.max))}
        | {"p95": float(np.percentile(sp[ok], 95))}
        if ok.any() else None
    )
    info["strouhal"] = _find_key(f.attrs, "strouhal")
    pod = None
    if f.n_times >= 2:
        try:
            e = pod_energy(f.data, n_modes, cumulative=False)
            valid_cells = int(np.isfinite(f.data).all(axis=(0, 1)).sum())
            pod = {"modes": [float(x) for x in e], "cumulative": [float(x) for x in np.cumsum(e)],
                   "cells_used": valid_cells}
        except ValueError as exc:  # no cell valid at every time
            pod = {"error": str(exc)}
    info["pod_energy"] = pod
    for k in ("generator", "seed", "source_file", "title", "command"):
        if k in f.attrs:
            info[k] = f.attrs[k]
    return info


def _run_info(args) -> int:
    from passt_mav.errors import UserError
    from passt_mav.fields.datasets import resolve_field

    if args.modes < 1:
        raise UserError(f"--modes must be >= 1, got {args.modes}")
    f = resolve_field(args.file)
    info = field_info(f, args.modes)
    info = {"file": str(args.file), **info}
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    g = info["grid"]
    print(f"file        {args.file}")
    if "title" in info:
        print(f"title       {info['title']}")
    print(f"shape       {info['shape']} (time, u/v, rows, cols), units {info['units']}")
    if g["kind"] == "geographic":
        print(f"grid        lat {g['south']:.4f}..{g['north']:.4f}, lon {g['west']:.4f}..{g['east']:.4f} "
              f"(cell centres), {g['rows']}x{g['cols']}, cells {info['cell_size_m'][0] / 1e3:.2f} x {info['cell_size_m'][1] / 1e3:.2f} km")
    else:
        print(f"grid        metric x {g['x0']:g}..{g['x1']:g}, y {g['y0']:g}..{g['y1']:g} m, {g['rows']}x{g['cols']}, "
              f"anchor {g['anchor_lat']:.5f},{g['anchor_lon']:.5f}, scale {g['scale']:g}, rotation {g['rotation_deg']:g} deg")
    dt = info["dt"]
    dt_s = "uneven" if dt is None else (f"{dt / 3600:g} h" if info["time_origin"] else f"{dt:g}")
    print(f"times       {info['n_times']} snapshots, {info['first_time']} .. {info['last_time']}, step {dt_s}")
    c = info["coverage"]
    print(f"coverage    {c['coverage']:.1%} of cell-times; cells with data always {c['cells_all']:.1%}, ever {c['cells_any']:.1%}")
    s = info["speed"]
    if s:
        print(f"speed       min {s['min']:.3f}, mean {s['mean']:.3f}, median {s['median']:.3f}, p95 {s['p95']:.3f}, max {s['max']:.3f}")
    if info["strouhal"] is not None:
        print(f"strouhal    {info['strouhal']:.4f}")
    pod = info["pod_energy"]
    if pod and "modes" in pod:
        print("POD energy  " + ", ".join(f"{x:.3f}" for x in pod["modes"])
              + f" (cumulative {pod['cumulative'][-1]:.3f} in {len(pod['modes'])} modes; {pod['cells_used']} cells valid at every time)")
    elif pod:
        print(f"POD energy  n/a ({pod['error']})")
    for k in ("generator", "seed", "source_file", "command"):
        if k in info:
            print(f"{k:<11} {info[k]}")
    return 0


def _run_show(args) -> int:
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.fields.plotting import plot_snapshot

    f = resolve_field(args.file)
    path = plot_snapshot(f, args.time, args.out)
    print(f"wrote {path}")
    return 0
