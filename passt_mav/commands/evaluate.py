"""passt-mav evaluate: Offline PASST campaign: trials x path lengths, RMSE over time and POD energy."""

from __future__ import annotations

import argparse

HELP = "Offline PASST campaign: trials x path lengths, RMSE over time and POD energy"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav evaluate' is not implemented yet in this version")
