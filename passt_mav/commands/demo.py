"""passt-mav demo: Embedded default: start the simulator, run a short PASST mission with the shipped model, write a report."""

from __future__ import annotations

import argparse

HELP = "Embedded default: start the simulator, run a short PASST mission with the shipped model, write a report"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav demo' is not implemented yet in this version")
