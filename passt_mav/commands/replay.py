"""passt-mav replay: Rebuild a run from its logs and recompute every decision."""

from __future__ import annotations

import argparse

HELP = "Rebuild a run from its logs and recompute every decision"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav replay' is not implemented yet in this version")
