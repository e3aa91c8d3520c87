"""passt-mav bench: Run the project's benchmarks and print a table of figures."""

from __future__ import annotations

import argparse

HELP = "Run the project's benchmarks and print a table of figures"
EXAMPLES = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    raise UserError("'passt-mav bench' is not implemented yet in this version")
