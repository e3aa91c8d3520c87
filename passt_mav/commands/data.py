"""passt-mav data: Make, import, inspect or plot a flow field (.nc)."""

from __future__ import annotations

import argparse

HELP = "Make, import, inspect or plot a flow field (.nc)"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav data' is not implemented yet in this version")
