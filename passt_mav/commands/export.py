"""passt-mav export: a run directory as CF NetCDF, GeoJSON, KML or CSV (:mod:`passt_mav.analysis.export`).

Only the standard library at module level (``passt-mav --help`` stays fast).
"""

from __future__ import annotations

import argparse
import json

HELP = "Export a run: CF-1.8 NetCDF (estimate grid or samples), GeoJSON/KML (tracks, paths, fence), CSV"
EXAMPLES = """examples:
  passt-mav export runs/demo --format netcdf                  # runs/demo/export/estimate.nc (grid + std)
  passt-mav export runs/demo --format netcdf --samples        # runs/demo/export/samples.nc (DSG trajectories)
  passt-mav export runs/demo --format geojson --out demo.geojson   # QGIS
  passt-mav export runs/demo --format kml --out demo.kml           # Google Earth
  passt-mav export runs/demo --format csv --out samples.csv        # spreadsheets

The estimate grid and the samples are two NetCDF files because CF's featureType is global:
one file cannot be both a grid and a trajectory (see passt_mav/analysis/export.py).
The estimate file re-imports with 'passt-mav data import FILE --region S,W,N,E --grid RxC'.
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="run directory (passt-mav run / demo)")
    # validated in run() (not argparse choices) so a bad value is one line on stderr
    p.add_argument("--format", default="netcdf", metavar="FORMAT", help="netcdf (default), geojson, kml or csv")
    p.add_argument(
        "--samples",
        action="store_true",
        help="netcdf only: the samples as a CF trajectory file instead of the estimate grid",
    )
    p.add_argument("--out", metavar="FILE", help="output file (default RUN_DIR/export/NAME; a folder gets NAME inside)")
    p.add_argument("--json", action="store_true", help="print what was written as JSON")


def run(args: argparse.Namespace) -> int:
    from passt_mav.analysis.export import export_run

    path, info = export_run(args.run_dir, args.format, args.out, samples=args.samples)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        extra = ", ".join(f"{k} {v}" for k, v in info.items() if k not in ("out", "format", "samples", "damaged"))
        if info.get("damaged"):  # one line: what the run lost; the export holds what is still readable
            print(f"damaged run: {info['damaged']}")
        print(f"exported {args.format}{' samples' if args.samples else ''} ({extra}); wrote {path}")
    return 0
