"""passt-mav plan: Plan one leg: state -> path -> mission file (.plan / .waypoints)."""

from __future__ import annotations

import argparse

HELP = "Plan one leg: state -> path -> mission file (.plan / .waypoints)"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav plan' is not implemented yet in this version")
