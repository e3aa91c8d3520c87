"""passt-mav report: Write the HTML report (plots and summary) of a run directory."""

from __future__ import annotations

import argparse

HELP = "Write the HTML report (plots and summary) of a run directory"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav report' is not implemented yet in this version")
