"""passt-mav data: make, import, inspect or plot a flow field (.nc).

Subcommands: ``cylinder`` and ``oscillating`` (CFD, from
:mod:`passt_mav.fields.cylinder_cli`), ``ocean`` (synthetic North Atlantic),
``import`` (real model/radar files), ``info``, ``show`` and ``export-lua`` (the grid
file of the ArduPilot Lua current sensor ``vehicle_sim/lua/current_sensor.lua``).

Only the standard library is imported at module level (``passt-mav --help``
must stay fast); numpy, xarray and matplotlib are imported inside the handlers.
"""

from __future__ import annotations

import argparse
import importlib
import json
from typing import Any, NamedTuple

HELP = "Make, import, inspect or plot a flow field (.nc)"
EXAMPLES = """examples:
  passt-mav data ocean --out ocean.nc --seed 0 --hours 504
  passt-mav data import RU_MARA_20180301.nc --region 38,-74,41,-69 --grid 30x30 --out radar.nc
  passt-mav data import hycom.nc --region north_atlantic --start 2018-03-01T00:00Z --hours 504 --out na.nc
  passt-mav data import radar_cms.nc --units cm/s --region 38,-74,41,-69 --out radar.nc   # a file in cm/s
  passt-mav data info ocean.nc --json
  passt-mav data show ocean.nc --out ocean.png --time 100
  passt-mav data export-lua builtin:ocean --snapshots 0:48 --scripts-dir sitl_scripts
  passt-mav data export-lua builtin:cylinder --mission missions/cylinder.yaml --out current_grid.bin
  passt-mav data cylinder --help
"""

#: named regions for --region (cell-centre corners S, W, N, E and default grid)
REGIONS = {"north_atlantic": "the paper's 30x30 North Atlantic region (geo.north_atlantic_grid)"}


def _add_cylinder(sub, name: str, oscillating: bool) -> None:
    help_ = (
        "cylinder wake CFD, Re 200 (static cylinder)"
        if not oscillating
        else "cylinder wake CFD, Re 200, cylinder oscillating once per 96 snapshots"
    )
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

    raise UserError(
        "the cylinder CFD generator is not part of this installation (passt_mav/fields/cylinder_cli.py is missing)"
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="data_command", metavar="SUBCOMMAND")
    _add_cylinder(sub, "cylinder", oscillating=False)
    _add_cylinder(sub, "oscillating", oscillating=True)

    o = sub.add_parser(
        "ocean",
        help="synthetic North Atlantic currents (jet, rings, M2 tide), seconds to make",
        description="Write the embedded synthetic North Atlantic surface-current field "
        "(meandering jet, drifting rings, M2 tide; 30x30 hourly, m/s) to a NetCDF file.",
    )
    o.add_argument("--out", required=True, help="output .nc file")
    o.add_argument("--seed", type=int, default=0, help="realisation seed (default 0)")
    o.add_argument("--hours", type=int, default=504, help="number of hourly snapshots (default 504)")
    o.add_argument("--json", action="store_true", help="print a JSON summary")
    o.set_defaults(_data_run=_run_ocean)

    i = sub.add_parser(
        "import",
        help="regrid a real model/radar file (HYCOM, RTOFS, Copernicus, ROMS, NEMO, HF radar) to a region grid",
        description="Read surface currents from an ocean-model or HF-radar NetCDF file, convert units "
        "to m/s, pick the surface, select the time window and regrid bilinearly to a region grid. "
        "Projected (CF grid_mapping: polar stereographic, Lambert, rotated pole, Mercator, ...) and "
        "curvilinear (2-D latitude/longitude, ROMS C grid) sources are read too: velocities along the "
        "grid's x/y axes are rotated to east/north and regridded linearly on triangles of the source nodes. "
        "Cells without data stay NaN (masked).",
    )
    i.add_argument("file", help="source NetCDF file")
    i.add_argument(
        "--region",
        default="north_atlantic",
        help="S,W,N,E cell-centre corners in degrees (write --region=S,W,N,E when S is negative), "
        "or a named region: " + ", ".join(REGIONS) + " (default)",
    )
    i.add_argument("--grid", default="30x30", help="ROWSxCOLS (default 30x30)")
    i.add_argument("--start", default=None, help="first time, ISO-8601 UTC (default: the file's first)")
    i.add_argument("--hours", type=int, default=None, help="window length in hours (default: the rest of the file)")
    i.add_argument("--variables", default=None, help="U,V variable names (default: detected)")
    i.add_argument(
        "--units",
        default=None,
        help="the velocity units of a file whose u/v have no units attribute or a wrong one (e.g. cm/s); "
        "units other than the file's own are taken, with a warning",
    )
    i.add_argument(
        "--allow-fast",
        action="store_true",
        help="import speeds no surface current has (median above 2.5 m/s or any above 10 m/s over the "
        "valid cells), which are refused otherwise as a sign of wrong --units",
    )
    i.add_argument(
        "--min-coverage",
        type=float,
        default=None,
        metavar="PERCENT",
        help="refuse a region whose cell-times hold data less than PERCENT %% of the time (default 20: a region "
        "or time window that misses the file keeps 0-4 %%); 0 imports any share",
    )
    i.add_argument("--out", required=True, help="output .nc file")
    i.add_argument("--json", action="store_true", help="print the coverage report as JSON")
    i.set_defaults(_data_run=_run_import)

    n = sub.add_parser(
        "info",
        help="shape, times, units, grid, coverage, speeds, POD energies of a field file",
        description="Describe a passt_mav field file (or builtin:ocean / builtin:cylinder ...).",
    )
    n.add_argument("file", help="field .nc file or builtin:NAME")
    n.add_argument("--modes", type=int, default=5, help="number of POD modes to report (default 5)")
    n.add_argument("--json", action="store_true", help="print JSON instead of text")
    n.set_defaults(_data_run=_run_info)

    s = sub.add_parser(
        "show",
        help="plot one snapshot: speed colour map and arrows",
        description="Plot one snapshot of a field file: speed colour map with velocity arrows "
        "(lat/lon axes for geographic fields, x/y metres for metric ones).",
    )
    s.add_argument("file", help="field .nc file or builtin:NAME")
    s.add_argument("--out", required=True, help="output image (.png, .pdf, .svg)")
    s.add_argument("--time", type=int, default=0, help="snapshot index (negative counts from the end; default 0)")
    s.set_defaults(_data_run=_run_show)

    x = sub.add_parser(
        "export-lua",
        help="write the binary grid file read by the ArduPilot Lua current sensor",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Write a field as the little-endian grid file that vehicle_sim/lua/current_sensor.lua "
        "reads on ArduPilot (SITL or a real autopilot): a 128-byte header (lat/lon -> cell map, "
        "field time at boot, snapshot times) and float32 u/v (m/s east/north, NaN = land). The "
        "script sends CUR_U/CUR_V for field time = time_at_boot + millis()/1000.",
        epilog="Copy the file next to the script: SITL reads WORKDIR/scripts/current_grid.bin "
        "(start-sitl --scripts DIR copies only *.lua, so put the .bin in WORKDIR/scripts yourself, "
        "or use --scripts-dir and copy that folder), a real autopilot APM/scripts/current_grid.bin.",
    )
    x.add_argument("file", help="field .nc file or builtin:NAME")
    x.add_argument(
        "--out", default=None, help="output file (default current_grid.bin, or DIR/current_grid.bin with --scripts-dir)"
    )
    x.add_argument(
        "--scripts-dir",
        default=None,
        help="also copy current_sensor.lua into this folder "
        "(ready for start-sitl --scripts DIR / the autopilot's scripts folder)",
    )
    x.add_argument(
        "--time-at-boot",
        type=float,
        default=None,
        help="field time (field units, like the mission's "
        "--field-time-at-boot) at vehicle boot (default: the mission's snapshot t0, else the first snapshot)",
    )
    x.add_argument(
        "--region",
        default=None,
        help="crop to the cells whose centres lie in S,W,N,E degrees (write --region=S,W,N,E when S is negative)",
    )
    x.add_argument(
        "--snapshots",
        default=None,
        help="START:STOP snapshot indices to keep (Python slice, "
        "e.g. 0:48); the vehicle holds the last one after the span",
    )
    x.add_argument(
        "--mission",
        default=None,
        help="mission YAML: its field velocity_scale/time_scale, t0 and, "
        "for a metric field, the region that places it on Earth",
    )
    x.add_argument("--anchor", default=None, help="LAT,LON: put a metric field's centre here (overrides its anchor)")
    x.add_argument("--json", action="store_true", help="print a JSON summary")
    x.set_defaults(_data_run=_run_export_lua)


def run(args: argparse.Namespace) -> int:
    fn = getattr(args, "_data_run", None)
    if fn is None:
        from passt_mav.errors import UserError

        raise UserError(
            "choose a subcommand: cylinder, oscillating, ocean, import, info, show, export-lua "
            "(see 'passt-mav data --help')"
        )
    return int(fn(args) or 0)


# -- handlers -------------------------------------------------------------------
def _run_ocean(args) -> int:
    import geo
    from passt_mav.fields.checks import check_size
    from passt_mav.fields.ocean import make_ocean_default

    if args.hours > 0:  # a time axis too large for memory: its size and the limit, before any work
        check_size((args.hours, 2, geo.NORTH_ATLANTIC["rows"], geo.NORTH_ATLANTIC["cols"]), f"--hours {args.hours}")
    f = make_ocean_default(seed=args.seed, hours=args.hours)
    f.attrs["command"] = f"passt-mav data ocean --seed {args.seed} --hours {args.hours}"
    path = f.to_netcdf(args.out)
    sp = f.speed()
    summary = {
        "out": str(path),
        "shape": list(f.shape),
        "seed": args.seed,
        "max_speed_m_s": float(sp.max()),
        "mean_speed_m_s": float(sp.mean()),
        "data_hash": f.data_hash(),
    }
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(
            f"ocean field {f.shape[0]} x {f.shape[2]}x{f.shape[3]} (seed {args.seed}), "
            f"speed max {summary['max_speed_m_s']:.2f} m/s, mean {summary['mean_speed_m_s']:.2f} m/s"
        )
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
    from passt_mav.fields.checks import check_grid_cells

    check_grid_cells(rows, cols, f"--grid {grid_text}")  # before anything is read: say the size and the limit
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
    from passt_mav.fields.checks import check_size
    from passt_mav.fields.importers import coverage_report, import_currents

    floor = _min_coverage(args.min_coverage)
    grid = parse_region(args.region, args.grid)
    if args.hours is not None and args.hours > 0:  # the longest time axis the window can hold, before reading
        check_size((args.hours, 2, grid.rows, grid.cols), f"--hours {args.hours}")
    variables = None
    if args.variables:
        variables = tuple(x.strip() for x in args.variables.split(","))
        if len(variables) != 2 or not all(variables):
            raise UserError(f"--variables must be U,V (two names), got {args.variables!r}")
    f = import_currents(args.file, grid, start=args.start, hours=args.hours, variables=variables, units=args.units)
    f.attrs["command"] = "passt-mav data import " + " ".join(
        [str(args.file), "--region", args.region, "--grid", args.grid]
        + (["--start", args.start] if args.start else [])
        + (["--hours", str(args.hours)] if args.hours else [])
        + (["--variables", args.variables] if args.variables else [])
        + (["--units", args.units] if args.units else [])
        + (["--allow-fast"] if args.allow_fast else [])
        + (["--min-coverage", f"{args.min_coverage:g}"] if args.min_coverage is not None else [])
    )
    warnings = _import_findings(f, args, floor)
    path = f.to_netcdf(args.out)
    rep = coverage_report(f)
    rep["warnings"] = warnings
    rep.update(
        out=str(path),
        time_origin=f.time_origin,
        variables=f.attrs["variables"],
        time_selection=f.attrs["time_selection"],
    )
    if args.json:
        print(json.dumps(rep, indent=2))
    else:
        print(
            f"imported {f.attrs['variables'][0]}/{f.attrs['variables'][1]} -> {f.n_times} snapshots from {f.time_origin} "
            f"on {grid.rows}x{grid.cols} ({f.attrs['time_selection']})"
        )
        print(
            f"coverage {rep['coverage']:.1%} of cell-times; cells with data at every time {rep['cells_all']:.1%}, "
            f"at some time {rep['cells_any']:.1%}"
        )
        print(f"wrote {path}")
    return 0


def _min_coverage(percent: float | None) -> float:
    """``--min-coverage PERCENT`` as a fraction (None: :data:`~passt_mav.fields.importers.MIN_IMPORT_COVERAGE`)."""
    from passt_mav.errors import UserError
    from passt_mav.fields.importers import MIN_IMPORT_COVERAGE

    if percent is None:
        return MIN_IMPORT_COVERAGE
    if not 0.0 <= percent <= 100.0:
        raise UserError(f"--min-coverage must be a percentage from 0 to 100, got {percent:g}")
    return percent / 100.0


def _import_findings(f, args, floor: float) -> list[str]:
    """What ``data import`` checks in the regridded field ``f`` before writing it: speeds no surface current
    has (refused unless --allow-fast), what every door refuses (:func:`~passt_mav.fields.checks.check_field`),
    less of the region's cell-times holding data than ``floor`` (a fraction; refused, one line naming the share
    and --min-coverage). Returns the warnings (each printed as one line on stderr): a thin region, --units
    that contradict the file's own units."""
    import sys

    from passt_mav.errors import UserError
    from passt_mav.fields.checks import check_field
    from passt_mav.fields.importers import coverage_check, speed_check, units_conflict

    fast = speed_check(f)
    if fast is not None and not args.allow_fast:
        problem, units = fast
        hint = f"{units}? use --units {units}" if units else "check the file's values and units (--units)"
        raise UserError(f"{args.file}: {problem}; {hint} (or --allow-fast to import them as they are)")
    check_field(f, str(args.file))  # what every door refuses (no data, infinite values, absurd speeds)
    if f.coverage < floor:
        raise UserError(
            f"{args.file}: only {100.0 * f.coverage:.1f} % of the region's cell-times hold data (below "
            f"{100.0 * floor:g} %): check --region, --start and --hours against the file, or give "
            "--min-coverage 0 to import it anyway"
        )
    warnings = []
    low = coverage_check(f)
    if low:
        warnings.append(low)
        print(f"warning: {low}; check --region and --start against the file", file=sys.stderr)
    clash = units_conflict(f)
    if clash:
        warnings.append(clash)
        print(f"warning: {clash}", file=sys.stderr)
    return warnings


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
        if ok.any()
        else None
    )
    info["strouhal"] = _find_key(f.attrs, "strouhal")
    pod = None
    if f.n_times >= 2:
        try:
            e = pod_energy(f.data, n_modes, cumulative=False)
            valid_cells = int(np.isfinite(f.data).all(axis=(0, 1)).sum())
            pod = {
                "modes": [float(x) for x in e],
                "cumulative": [float(x) for x in np.cumsum(e)],
                "cells_used": valid_cells,
            }
        except ValueError as exc:  # no cell valid at every time
            pod = {"error": str(exc)}
    info["pod_energy"] = pod
    for k in ("generator", "seed", "source_file", "source_grid", "rotation", "title", "command"):
        if k in f.attrs:
            info[k] = f.attrs[k]
    return info


def _run_info(args) -> int:
    from passt_mav.errors import UserError
    from passt_mav.fields.datasets import resolve_field

    if args.modes < 1:
        raise UserError(f"--modes must be >= 1, got {args.modes}")
    f = resolve_field(args.file, check=False)  # look at any field file
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
        print(
            f"grid        lat {g['south']:.4f}..{g['north']:.4f}, lon {g['west']:.4f}..{g['east']:.4f} "
            f"(cell centres), {g['rows']}x{g['cols']}, cells {info['cell_size_m'][0] / 1e3:.2f} x {info['cell_size_m'][1] / 1e3:.2f} km"
        )
    else:
        print(
            f"grid        metric x {g['x0']:g}..{g['x1']:g}, y {g['y0']:g}..{g['y1']:g} m, {g['rows']}x{g['cols']}, "
            f"anchor {g['anchor_lat']:.5f},{g['anchor_lon']:.5f}, scale {g['scale']:g}, rotation {g['rotation_deg']:g} deg"
        )
    dt = info["dt"]
    dt_s = "uneven" if dt is None else (f"{dt / 3600:g} h" if info["time_origin"] else f"{dt:g}")
    print(f"times       {info['n_times']} snapshots, {info['first_time']} .. {info['last_time']}, step {dt_s}")
    c = info["coverage"]
    print(
        f"coverage    {c['coverage']:.1%} of cell-times; cells with data always {c['cells_all']:.1%}, ever {c['cells_any']:.1%}"
    )
    s = info["speed"]
    if s:
        print(
            f"speed       min {s['min']:.3f}, mean {s['mean']:.3f}, median {s['median']:.3f}, p95 {s['p95']:.3f}, max {s['max']:.3f}"
        )
    if info["strouhal"] is not None:
        print(f"strouhal    {info['strouhal']:.4f}")
    pod = info["pod_energy"]
    if pod and "modes" in pod:
        print(
            "POD energy  "
            + ", ".join(f"{x:.3f}" for x in pod["modes"])
            + f" (cumulative {pod['cumulative'][-1]:.3f} in {len(pod['modes'])} modes; {pod['cells_used']} cells valid at every time)"
        )
    elif pod:
        print(f"POD energy  n/a ({pod['error']})")
    for k in ("generator", "seed", "source_file", "source_grid", "rotation", "command"):
        if k in info:
            print(f"{k:<11} {info[k]}")
    return 0


def _run_show(args) -> int:
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.fields.plotting import plot_snapshot

    f = resolve_field(args.file, check=False)  # look at any field file
    path = plot_snapshot(f, args.time, args.out)
    print(f"wrote {path}")
    return 0


# -- the Lua sensor's grid file ----------------------------------------------------
#: layout documented in vehicle_sim/lua/current_sensor.lua (keep both in step)
LUA_MAGIC = b"PCUR"
LUA_VERSION = 1
LUA_HEADER_BYTES = 128
_LUA_HEADER_FMT = "<4sHHHHI11d"  # 104 bytes, zero-padded to LUA_HEADER_BYTES


def lua_script_path():
    """Path of the shipped ``current_sensor.lua`` (package data of vehicle_sim), found without importing it."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.find_spec("vehicle_sim")
    if spec is None or not spec.submodule_search_locations:
        from passt_mav.errors import UserError

        raise UserError("vehicle_sim is not installed: current_sensor.lua ships with it")
    return Path(next(iter(spec.submodule_search_locations))) / "lua" / "current_sensor.lua"


def export_lua_grid(
    field, path, *, time_at_boot: float | None = None, velocity_scale: float = 1.0, time_scale: float = 1.0, grid=None
) -> dict:
    """Write ``field`` as the Lua current sensor's grid file; returns a JSON-able summary.

    Args:
        field: a :class:`FlowField` (geographic, or metric with an Earth placement).
        path: output file.
        time_at_boot: field time (field units) at vehicle boot; default the first snapshot.
        velocity_scale: m/s per field velocity unit (mission ``field.velocity_scale``).
        time_scale: seconds per field time unit (mission ``field.time_scale``).
        grid: placement of a metric field (a :class:`geo.MetricRegionGrid` of the field's
            shape); default the field's own grid.

    The file stores u/v in m/s east/north (metric fields are rotated to east/north and
    scaled), times in seconds (field units x ``time_scale``) and an affine map from lat/lon
    (degrees) to fractional cell. For lat/lon grids the map is exact; for metric grids it is
    the tangent map at the grid centre and ``max_map_error_cells`` says how far it is off at
    the corners (it must stay below 0.01 cell).
    """
    from pathlib import Path

    import numpy as np

    from passt_mav.errors import FieldError

    g = field.grid if grid is None else grid
    if g.shape != field.grid.shape:
        raise FieldError(f"placement grid {g.shape} does not match the field's {field.grid.shape}")
    (R, C), T = g.shape, field.n_times
    data = field.data.astype(np.float64) * float(velocity_scale)
    if field.is_geographic and grid is None:
        cell_map = _LatLonCellMap(g.south, g.west, 0.0, 0.0, np.array([[1.0 / g.dlat, 0.0], [0.0, 1.0 / g.dlon]]), 0.0)
    else:
        rot = getattr(g, "velocity_to_local", None)
        if rot is not None:
            u, v = rot(data[:, 0], data[:, 1])
            data = np.stack([u, v], axis=1)
        cell_map = _tangent_cell_map(g)
    times_s = field.times * float(time_scale)
    dt_s = field.dt * float(time_scale) if T > 1 else 0.0
    t_boot = float(field.times[0] if time_at_boot is None else time_at_boot) * float(time_scale)
    header = _lua_header((R, C, T), cell_map, t_boot=t_boot, t0_s=float(times_s[0]), dt_s=float(dt_s))
    body = np.ascontiguousarray(data.astype("<f4")).tobytes()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header + body)
    return {
        "out": str(path),
        "bytes": len(header) + len(body),
        "rows": R,
        "cols": C,
        "snapshots": T,
        "time_at_boot_s": t_boot,
        "t0_s": float(times_s[0]),
        "dt_s": float(dt_s),
        "span_s": float(times_s[-1] - times_s[0]),
        "max_map_error_cells": cell_map.error_cells,
        "land_cells": int(field.land_mask.sum()),
    }


class _LatLonCellMap(NamedTuple):
    """The grid file's affine map from lat/lon (degrees) to fractional cell (row, col):
    ``cell = (r_ref, c_ref) + jac @ (lat - lat_ref, lon - lon_ref)``; ``error_cells``: how far it is
    off at the grid's corners (cells)."""

    lat_ref: float
    lon_ref: float
    r_ref: float
    c_ref: float
    jac: Any
    error_cells: float


def _tangent_cell_map(g) -> _LatLonCellMap:
    """The tangent map of metric grid ``g`` at its centre (central differences of its projection),
    or the error naming how far off it is at a corner when that exceeds 0.01 cell."""
    import numpy as np

    from passt_mav.errors import FieldError

    R, C = g.shape
    r_ref, c_ref = (R - 1) / 2.0, (C - 1) / 2.0
    lat_ref, lon_ref = (float(x) for x in g.fcell_to_latlon(r_ref, c_ref))
    h = 1e-4  # degrees: central differences of a smooth projection, error ~h^2
    jac = np.empty((2, 2))
    for j, (dla, dlo) in enumerate(((h, 0.0), (0.0, h))):
        rp, cp = g.latlon_to_fcell(lat_ref + dla, lon_ref + dlo)
        rm, cm = g.latlon_to_fcell(lat_ref - dla, lon_ref - dlo)
        jac[0, j] = (float(rp) - float(rm)) / (2 * h)
        jac[1, j] = (float(cp) - float(cm)) / (2 * h)
    cr = np.array([0.0, 0.0, R - 1.0, R - 1.0])
    cc = np.array([0.0, C - 1.0, 0.0, C - 1.0])
    la, lo = g.fcell_to_latlon(cr, cc)
    ra = r_ref + jac[0, 0] * (la - lat_ref) + jac[0, 1] * (lo - lon_ref)
    ca = c_ref + jac[1, 0] * (la - lat_ref) + jac[1, 1] * (lo - lon_ref)
    map_err = float(np.max(np.hypot(ra - cr, ca - cc)))
    if map_err > 0.01:
        raise FieldError(
            f"the metric grid is too large for a linear lat/lon map ({map_err:.3f} cells off at "
            "a corner); export a smaller --region or a smaller scale"
        )
    return _LatLonCellMap(lat_ref, lon_ref, r_ref, c_ref, jac, map_err)


def _lua_header(shape: tuple[int, int, int], m: _LatLonCellMap, *, t_boot: float, t0_s: float, dt_s: float) -> bytes:
    """The grid file's header (``LUA_HEADER_BYTES``, zero-padded): ``shape`` (rows, cols, snapshots),
    the lat/lon-to-cell map, field time at boot, first snapshot and step (seconds)."""
    import struct

    R, C, T = shape
    header = struct.pack(
        _LUA_HEADER_FMT,
        LUA_MAGIC,
        LUA_VERSION,
        LUA_HEADER_BYTES,
        R,
        C,
        T,
        float(m.lat_ref),
        float(m.lon_ref),
        float(m.r_ref),
        float(m.c_ref),
        float(m.jac[0, 0]),
        float(m.jac[0, 1]),
        float(m.jac[1, 0]),
        float(m.jac[1, 1]),
        t_boot,
        t0_s,
        dt_s,
    )
    return header.ljust(LUA_HEADER_BYTES, b"\0")


def read_lua_grid(path) -> dict:
    """Read a grid file written by :func:`export_lua_grid` (header dict + ``data`` (T, 2, rows, cols) float32)."""
    import struct
    from pathlib import Path

    import numpy as np

    from passt_mav.errors import FieldError

    b = Path(path).read_bytes()
    n = struct.calcsize(_LUA_HEADER_FMT)
    if len(b) < n or b[:4] != LUA_MAGIC:
        raise FieldError(f"{path} is not a Lua current grid file")
    keys = (
        "magic",
        "version",
        "header",
        "rows",
        "cols",
        "snapshots",
        "lat_ref",
        "lon_ref",
        "r_ref",
        "c_ref",
        "drdlat",
        "drdlon",
        "dcdlat",
        "dcdlon",
        "time_at_boot_s",
        "t0_s",
        "dt_s",
    )
    h = dict(zip(keys, struct.unpack(_LUA_HEADER_FMT, b[:n])))
    shape = (h["snapshots"], 2, h["rows"], h["cols"])
    h["data"] = np.frombuffer(b, dtype="<f4", offset=h["header"]).reshape(shape)
    return h


def _run_export_lua(args) -> int:
    import shutil
    from pathlib import Path

    from passt_mav.errors import UserError
    from passt_mav.fields.datasets import resolve_field

    velocity_scale, time_scale, t0, placement, seed = 1.0, 1.0, None, None, 0
    if args.mission:
        from passt_mav.mission.config import load_mission

        cfg = load_mission(args.mission)
        velocity_scale, time_scale, t0 = cfg.field.velocity_scale, cfg.field.time_scale, cfg.t0
        placement, seed = cfg.grid(), cfg.seeds.field
    f = resolve_field(args.file, seed=seed)
    placement = _lua_placement(f, placement, args.anchor)
    time_at_boot = args.time_at_boot
    if time_at_boot is None and t0 is not None:
        if not 0 <= t0 < f.n_times:
            raise UserError(f"the mission's t0 {t0} is outside the field's {f.n_times} snapshots")
        time_at_boot = float(f.times[t0])
    if args.snapshots:
        f = _keep_snapshots(f, args.snapshots)
    if args.region:
        f = _crop_region(f, args.region)
    if time_at_boot is None:
        time_at_boot = float(f.times[0])
    out = (
        Path(args.out) if args.out else (Path(args.scripts_dir) if args.scripts_dir else Path(".")) / "current_grid.bin"
    )
    summary = export_lua_grid(
        f, out, time_at_boot=time_at_boot, velocity_scale=velocity_scale, time_scale=time_scale, grid=placement
    )
    if args.scripts_dir:
        d = Path(args.scripts_dir)
        d.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(lua_script_path(), d / "current_sensor.lua")
        summary["script"] = str(d / "current_sensor.lua")
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(
            f"Lua grid {summary['rows']}x{summary['cols']}, {summary['snapshots']} snapshots every "
            f"{summary['dt_s']:g} s, field time at boot {summary['time_at_boot_s']:g} s, "
            f"{summary['bytes'] / 1024:.1f} KiB"
        )
        if "script" in summary:
            print(f"wrote {summary['script']}")
        print(f"wrote {summary['out']}")
    return 0


def _lua_placement(f, placement, anchor: str | None):
    """Where the exported grid lies on Earth: ``None`` for a lat/lon field (it places itself), else the
    mission's region (``placement``) or the field's own metric grid, moved to ``--anchor LAT,LON``
    (degrees) if given."""
    import geo
    from passt_mav.errors import UserError

    if placement is not None and placement.shape != f.grid.shape:
        raise UserError(
            f"the mission's region is {placement.shape[0]}x{placement.shape[1]} but the field is "
            f"{f.grid.shape[0]}x{f.grid.shape[1]}"
        )
    if f.is_geographic:
        if anchor:
            raise UserError("--anchor is for metric fields (x/y metres); this field is already on lat/lon")
        return None
    g = placement or f.grid
    if anchor:
        try:
            alat, alon = (float(x) for x in anchor.split(","))
        except ValueError:
            raise UserError(f"--anchor must be LAT,LON in degrees, got {anchor!r}") from None
        d = g.describe()
        d.update(anchor_lat=alat, anchor_lon=alon)
        d.pop("kind")
        g = geo.MetricRegionGrid(**d)
    return g


def _keep_snapshots(f, spec: str):
    """Field ``f`` cut to ``--snapshots START:STOP`` (snapshot indices, either may be empty)."""
    from passt_mav.errors import UserError

    try:
        a, b = (int(x) if x.strip() else None for x in spec.split(":"))
    except ValueError:
        raise UserError(f"--snapshots must be START:STOP snapshot indices, got {spec!r}") from None
    sl = slice(a, b)
    if len(range(f.n_times)[sl]) < 1:
        raise UserError(f"--snapshots {spec} keeps none of the field's {f.n_times} snapshots")
    return f.isel(time=sl)


def _crop_region(f, spec: str):
    """Lat/lon field ``f`` cropped to the cell centres inside ``--region S,W,N,E`` (degrees)."""
    import numpy as np

    from passt_mav.errors import UserError

    if not f.is_geographic:
        raise UserError("--region crops lat/lon fields; for a metric field export its mission region")
    try:
        s_, w_, n_, e_ = (float(x) for x in spec.split(","))
    except ValueError:
        raise UserError(f"--region must be S,W,N,E in degrees, got {spec!r}") from None
    rows = np.nonzero((f.grid.lats >= s_) & (f.grid.lats <= n_))[0]
    cols = np.nonzero((f.grid.lons >= w_) & (f.grid.lons <= e_))[0]
    if rows.size < 2 or cols.size < 2:
        raise UserError(f"--region {spec} holds fewer than 2x2 cell centres of the field")
    return f.isel(rows=slice(int(rows[0]), int(rows[-1]) + 1), cols=slice(int(cols[0]), int(cols[-1]) + 1))
