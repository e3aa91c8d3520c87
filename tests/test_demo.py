"""`passt-mav demo` end to end: simulator subprocess, one short leg, run directory and report.

Slow (~40-60 s on two cores: the simulator generates the ocean field, boots, and the
5 m/s boat needs ~1.2 h of simulated time for 3 moves of 6.6 km at 150x).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest


@pytest.mark.slow
def test_demo_one_leg_writes_summary_and_report(tmp_path):
    out = tmp_path / "demo"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.monotonic()
    p = subprocess.run(
        [sys.executable, "-m", "passt_mav.cli", "demo", "--legs", "1", "--moves", "3", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=400,
        env=env,
    )
    wall = time.monotonic() - t0
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "complete" and len(s["legs"]) == 1
    leg = s["legs"][0]
    assert leg["n_samples"] > 100 and leg["rmse_passt"] is not None and leg["rmse_model"] is not None
    assert s["model"] in ("builtin:ocean", "dmd") and (s["model"] == "builtin:ocean") == (s["model_fallback"] is None)
    assert (out / "report" / "report.html").exists() and (out / "flight.tlog").stat().st_size > 0
    assert (out / "legs" / "000" / "mission.waypoints").exists() and (out / "mission.yaml").exists()
    assert str(out) in p.stdout and "report" in p.stdout
    print(f"demo --legs 1 --moves 3: {wall:.1f} s wall")
