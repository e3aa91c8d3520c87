"""passt-mav report: Write the HTML report (plots and summary) of a run directory."""

from __future__ import annotations

import argparse

HELP = "Write the HTML report (plots and summary) of a run directory"
EXAMPLES = """examples:
  passt-mav report runs/2026-05-01_ocean            # writes runs/2026-05-01_ocean/report/report.html
  passt-mav report runs/2026-05-01_ocean --out review/ocean

The page is self-contained (figures embedded): open it from disk in any browser.
The figures are also written as PNG files next to it. Parts a run did not record
(no telemetry log, no truth field, ...) are marked "not recorded".
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="run directory (holds summary.json and legs/)")
    p.add_argument("--out", metavar="DIR", default=None, help="output directory (default: RUN_DIR/report)")


def run(args: argparse.Namespace) -> int:
    from passt_mav.analysis.report import write_report

    damage: list[str] = []
    path = write_report(args.run_dir, out=args.out, damage=damage)
    if damage:  # one line: what the run lost (the report's header says it too)
        print(f"damaged run: {'; '.join(damage)}; the report shows what is still readable")
    print(path)
    return 0
