"""The ``passt-mav`` command.

Each subcommand lives in its own module under :mod:`passt_mav.commands` and
exposes ``HELP`` (one line), ``EXAMPLES`` (epilog text), ``add_arguments(parser)``
and ``run(args) -> int``. Those modules import only the standard library at top
level; numpy, torch, sklearn and pymavlink are imported inside ``run`` so that
``passt-mav --help`` answers in well under a second.

Errors: a :class:`passt_mav.errors.UserError` (or ``geo.GeoError``), a
:class:`passt_mav.errors.MavlinkError` (a vehicle that cannot be reached or stops answering)
or an ``OSError`` (a file or network error) raised by a command is printed as one line
``passt-mav: error: ...`` and the exit code is 2; set ``PASST_TRACEBACK=1`` to see the
traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

__all__ = ["main", "COMMANDS"]

#: subcommand name -> module under passt_mav.commands
COMMANDS: dict[str, str] = {
    "demo": "demo",
    "data": "data",
    "model": "model",
    "evaluate": "evaluate",
    "paper": "paper",
    "plan": "plan",
    "run": "run",
    "replay": "replay",
    "report": "report",
    "bench": "bench",
    "export": "export",
    # live view: the run's page served while it flies
    "view": "view",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="passt-mav",
        description="PASST adaptive sampling of current fields with ArduPilot boats over MAVLink.",
        epilog="Run 'passt-mav COMMAND --help' for a command's options and examples.",
    )
    from passt_mav import __version__

    parser.add_argument("--version", action="version", version=f"passt-mav {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, modname in COMMANDS.items():
        mod = importlib.import_module(f"passt_mav.commands.{modname}")
        p = sub.add_parser(
            name,
            help=mod.HELP,
            description=mod.HELP,
            epilog=getattr(mod, "EXAMPLES", None),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def _is_user_error(exc: BaseException) -> bool:
    """Bad input, a file or network error, or a vehicle that cannot be reached or answered: one line, exit 2."""
    from passt_mav.errors import MavlinkError, UserError

    if isinstance(exc, (UserError, MavlinkError, OSError)):
        return True
    geo_mod = sys.modules.get("geo.region")
    return geo_mod is not None and isinstance(exc, geo_mod.GeoError)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    for a in sys.argv[1:] if argv is None else argv:
        # argparse (3.11) takes "--opt=--" for an option given no value at all (an empty list, not "--")
        if a.startswith("--") and a.endswith("=--"):
            parser.error(f"{a}: '--' is not a value for {a[:-3]}; give one, e.g. {a[:-3]}=VALUE")
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("passt-mav: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if _is_user_error(exc) and not os.environ.get("PASST_TRACEBACK"):
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            if isinstance(exc, OSError) and getattr(exc, "filename", None) and str(exc.filename) not in msg:
                msg = f"{exc.filename}: {msg}"
            print(f"passt-mav: error: {msg}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
