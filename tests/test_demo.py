"""`passt-mav demo` end to end: simulator subprocess, one short leg, run directory and report.

Slow (~30-60 s on two cores: the simulator loads the oscillating wake, boots, the boat flies 10 moves
of 30 m, and the counterfactuals are flown offline). The fast tests below check the demo's choice of
mission and its last line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest


@pytest.mark.slow(reason="the quick start's demo as a process with the shipped KNODE and its report: ~1 min")
def test_demo_one_leg_writes_summary_and_report(tmp_path):
    out = tmp_path / "demo"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.monotonic()
    p = subprocess.run(
        [sys.executable, "-m", "passt_mav.cli", "demo", "--legs", "1", "--moves", "10", "--out", str(out)],
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
    # 10 moves of 30 m at 5 m/s, a reading every 5 s: ~16 samples
    assert leg["n_samples"] >= 10 and leg["rmse_passt"] is not None and leg["rmse_model"] is not None
    assert s["model"] in ("builtin:cylinder", "dmd") and (s["model"] == "builtin:cylinder") == (
        s["model_fallback"] is None
    )
    assert s["mission"] == "oscillating_cylinder"
    cf = s["counterfactual"]
    assert len(cf["random_walks"]) == 5 and len(cf["random"]) == 1 and cf["lawnmower"][0] is not None
    assert (out / "report" / "report.html").exists() and (out / "flight.tlog").stat().st_size > 0
    assert (out / "legs" / "000" / "mission.waypoints").exists() and (out / "mission.yaml").exists()
    assert str(out) in p.stdout and "report" in p.stdout
    print(f"demo --legs 1 --moves 10: {wall:.1f} s wall")


def _args(*argv):
    import argparse

    from passt_mav.commands import demo

    p = argparse.ArgumentParser()
    demo.add_arguments(p)
    return p.parse_args(list(argv))


def test_the_default_demo_is_the_oscillating_wake_and_its_embedded_copy_agrees():
    """No --mission/--field: missions/oscillating_cylinder.yaml with its own 5 legs of 50 moves (the
    package's embedded copy when missions/ is not beside it must be the same mission); --field
    builtin:ocean still flies the North Atlantic mission, 3 legs of 5 moves."""
    from pathlib import Path

    import yaml

    from passt_mav.commands import demo

    missions = Path(__file__).resolve().parents[1] / "missions"
    assert demo._EMBEDDED == yaml.safe_load((missions / "oscillating_cylinder.yaml").read_text())
    _, cfg, over, origin = demo._demo_mission(_args())
    assert cfg.name == "oscillating_cylinder" and origin.endswith("oscillating_cylinder.yaml")
    assert (cfg.legs, cfg.planner.path_length, cfg.model) == (5, 50, "builtin:cylinder")
    assert cfg.fleet[0].speed_mps == 5.0 and "legs" not in over
    _, cfg, _, _ = demo._demo_mission(_args("--field", "builtin:ocean"))
    assert (cfg.name, cfg.legs, cfg.planner.path_length) == ("north_atlantic", 3, 5)
    _, cfg, _, _ = demo._demo_mission(_args("--legs", "2", "--moves", "7"))
    assert (cfg.name, cfg.legs, cfg.planner.path_length) == ("oscillating_cylinder", 2, 7)


def test_final_line_sets_the_run_beside_the_walks_mean():
    from passt_mav.commands.demo import final_line

    line = final_line(0.10, 0.14, [0.09, 0.12, 0.15], 0.3)
    assert "random walk through the same model + GP 0.1200 m/s (mean of 3, 0.0900-0.1500)" in line
    assert line.endswith("PASST is below the model alone and below the random walks' mean (below 2 of the 3 walks)")
    line = final_line(0.13, 0.14, [0.09, 0.12, 0.15], None, boats=3)
    assert "NOT below the random walks' mean (below 1 of the 3 walks)" in line and "3 random walks" in line
    # a walk without a final figure: no mean, no verdict on the walks (nor on a missing model alone)
    assert "GP n/a" in final_line(0.1, None, [0.1, None], None) and "PASST is" not in final_line(0.1, None, None, None)


def test_the_default_speed_up_keeps_a_wall_second_under_a_snapshot():
    """150x, or less where snapshots are short (a wall second of planning is at most 0.625 snapshot):
    the oscillating wake's 80 s snapshots 50x, the ocean's hourly ones 150x."""
    from passt_mav.commands.demo import _demo_mission, default_speedup
    from passt_mav.fields.datasets import mission_field

    _, cfg, _, _ = _demo_mission(_args())
    f = mission_field(cfg)
    assert float(f.dt) * cfg.field.time_scale == pytest.approx(80.0)
    assert default_speedup(80.0) == 50.0 and default_speedup(3600.0) == 150.0 and default_speedup(0.5) == 1.0
