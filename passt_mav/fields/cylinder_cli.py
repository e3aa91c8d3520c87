"""Command-line glue for the cylinder CFD: ``passt-mav data cylinder`` / ``data oscillating``.

``passt_mav/commands/data.py`` wires its two sub-commands to
:func:`add_cylinder_arguments` and :func:`run_cylinder`. Until then (and for
scripts) this module runs on its own::

    python -m passt_mav.fields.cylinder_cli cylinder --out cylinder.nc --seed 0
    python -m passt_mav.fields.cylinder_cli oscillating --out oscillating.nc --amplitude 0.5

Only the standard library is imported at module level: the command line builds
its parsers without loading numpy or torch.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

__all__ = ["add_cylinder_arguments", "run_cylinder", "main"]

#: Defaults shared with :class:`passt_mav.fields.cylinder.CylinderConfig` (kept here so that
#: building the parser does not import numpy); a test checks that they agree.
DEFAULTS = {
    "seed": 0,
    "snapshots": 500,
    "resolution": 10,
    "dt": 0.4,
    "spin_up": 120.0,
    "amplitude_oscillating": 0.5,
    "period_snapshots": 96,
}


def add_cylinder_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``data cylinder`` and ``data oscillating`` (same set for both)."""
    d = DEFAULTS
    parser.add_argument("--out", required=True, metavar="FILE.nc", help="output NetCDF file")
    parser.add_argument(
        "--seed",
        type=int,
        default=d["seed"],
        help="seed of the symmetry-breaking start perturbation (default %(default)s)",
    )
    parser.add_argument(
        "--snapshots", type=int, default=d["snapshots"], help="output snapshots after the spin-up (default %(default)s)"
    )
    parser.add_argument(
        "--resolution",
        type=int,
        default=d["resolution"],
        help="lattice cells per cylinder radius (default %(default)s; 6 is a quick coarse run)",
    )
    parser.add_argument(
        "--dt",
        type=float,
        default=d["dt"],
        help="output interval, non-dimensional time (default %(default)s: ~25 snapshots per shedding period)",
    )
    parser.add_argument(
        "--spin-up",
        type=float,
        default=d["spin_up"],
        dest="spin_up",
        help="non-dimensional time simulated before the first snapshot (default %(default)s)",
    )
    parser.add_argument(
        "--amplitude",
        type=float,
        default=None,
        help=f"cylinder oscillation amplitude in radii (oscillating only; default {d['amplitude_oscillating']})",
    )
    parser.add_argument(
        "--period-snapshots",
        type=int,
        default=d["period_snapshots"],
        dest="period_snapshots",
        help="oscillation period in output snapshots (default %(default)s)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch CPU threads (default: torch's choice; results do not depend on it)",
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _command_line() -> str:
    argv0 = Path(sys.argv[0]).name if sys.argv else "passt-mav"
    if argv0 in ("cylinder_cli.py", "__main__.py", "-c", ""):
        argv0 = "python -m passt_mav.fields.cylinder_cli"
    return " ".join([argv0] + [shlex.quote(a) for a in sys.argv[1:]])


def _amplitude(amplitude: float | None, oscillating: bool) -> float:
    """The cylinder's oscillation amplitude (radii) from ``--amplitude``: the oscillating default when
    not given, 0 for the static cylinder (which refuses a non-zero one)."""
    from passt_mav.errors import FieldError

    if oscillating:
        amplitude = DEFAULTS["amplitude_oscillating"] if amplitude is None else amplitude
        if amplitude <= 0:
            raise FieldError(f"--amplitude must be positive for the oscillating cylinder, got {amplitude}")
    else:
        if amplitude not in (None, 0, 0.0):
            raise FieldError("--amplitude applies to 'data oscillating' only (the static cylinder does not move)")
        amplitude = 0.0
    return amplitude


def _print_summary(summary: dict) -> None:
    """Print a run's summary (see :func:`run_cylinder`) as text lines."""
    lo, hi = summary["pod4_window"]
    if summary["strouhal"] == summary["strouhal"]:
        print(f"Strouhal number: {summary['strouhal']:.4f} (lift spectrum; literature 0.19-0.20 at Re 200)")
    else:
        print("Strouhal number: n/a (record shorter than 2 shedding periods; use more --snapshots)")
    print(f"POD energy of the first 4 modes (snapshots {lo}-{hi}): {summary['pod4_energy']:.4f}")
    print(
        f"mean drag coefficient: {summary['drag_coefficient_mean']:.3f}; wall time {summary['wall_time_s']:.0f} s; data hash {summary['data_hash']}"
    )
    print(f"wrote {summary['out']}")


def run_cylinder(args: argparse.Namespace, oscillating: bool) -> int:
    """Generate the static (``oscillating=False``) or oscillating cylinder data set.

    Writes ``args.out`` and prints the Strouhal number, the POD-4 energy and the
    path. Returns the exit code (0). Bad options raise ``FieldError`` (a ``UserError``).
    """
    from passt_mav.errors import FieldError
    from passt_mav.fields.cylinder import CylinderConfig, generate_cylinder

    out = Path(args.out)
    if out.suffix != ".nc":
        raise FieldError(f"--out must name a .nc file, got {out}")
    amplitude = _amplitude(args.amplitude, oscillating)
    cfg = CylinderConfig(
        resolution=args.resolution,
        n_snapshots=args.snapshots,
        dt_out=args.dt,
        spin_up=args.spin_up,
        amplitude=amplitude,
        period_snapshots=args.period_snapshots,
        seed=args.seed,
        threads=args.threads,
    )
    try:
        field = generate_cylinder(cfg, progress=not args.quiet, command=_command_line())
    except FloatingPointError as exc:
        raise FieldError(str(exc)) from None
    field.to_netcdf(out)
    a = field.attrs
    summary = {
        "scenario": a["scenario"],
        "out": str(out),
        "snapshots": field.n_times,
        "dt": cfg.dt_out,
        "strouhal": a["strouhal"],
        "pod4_energy": a["pod4_energy"],
        "pod4_window": a["pod4_window"],
        "drag_coefficient_mean": a["drag_coefficient_mean"],
        "wall_time_s": a["wall_time_s"],
        "data_hash": field.data_hash(),
    }
    if getattr(args, "json", False):
        print(json.dumps(summary, indent=2))
    else:
        _print_summary(summary)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m passt_mav.fields.cylinder_cli {cylinder,oscillating} --out FILE.nc ...``."""
    p = argparse.ArgumentParser(prog="python -m passt_mav.fields.cylinder_cli", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="scenario", required=True)
    for name in ("cylinder", "oscillating"):
        add_cylinder_arguments(sub.add_parser(name, help=f"make the {name} data set"))
    args = p.parse_args(argv)
    try:
        return run_cylinder(args, oscillating=args.scenario == "oscillating")
    except ValueError as exc:  # UserError is a ValueError: one line, exit 2
        from passt_mav.errors import UserError

        if isinstance(exc, UserError):
            print(f"error: {exc}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
