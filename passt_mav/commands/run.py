"""passt-mav run: Run a PASST mission on a vehicle (real or simulated) over MAVLink."""

from __future__ import annotations

import argparse

HELP = "Run a PASST mission on a vehicle (real or simulated) over MAVLink"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav run' is not implemented yet in this version")
