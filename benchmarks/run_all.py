"""Run every benchmarks/bench_*.py and print one table (same as ``passt-mav bench``).

    .venv/bin/python benchmarks/run_all.py --quick --out bench.json

Options are those of ``passt-mav bench`` (see ``passt-mav bench --help``).
"""

from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__":
    # a source checkout need not be installed for this script
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from passt_mav.cli import main

    sys.exit(main(["bench", *sys.argv[1:]]))
