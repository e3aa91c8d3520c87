"""passt-mav model: Train or evaluate predictors (KNODE, DMD, persistence)."""

from __future__ import annotations

import argparse

HELP = "Train or evaluate predictors (KNODE, DMD, persistence)"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav model' is not implemented yet in this version")
