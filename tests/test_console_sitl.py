"""Issue 44's Pause/Resume on ArduPilot Rover SITL (marker ``sitl``; skips without the build in ../shared/sitl).

The operator (tests/test_console.py's :class:`Operator`) pauses the leg once two items are behind the boat
and resumes it after the firmware has held for a while: the firmware reports HOLD, then AUTO at the item it
was paused at (MISSION_CURRENT), and the leg flies on to "Mission Complete". SITL has no current sensor here,
so the run then stops with its "no current samples" error, as in tests/test_sitl.py.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from test_console import Operator, _flying

import geo

pytestmark = pytest.mark.sitl

HOME = (40.0, -63.0)
HOLD, AUTO = 4, 10


def test_pause_and_resume_on_ardurover_sitl(tmp_path, sitl):
    from passt_mav.errors import MavlinkError
    from passt_mav.fields import FlowField
    from passt_mav.mavlink import Link, LinkConfig, Vehicle
    from passt_mav.mission.config import validate_mission
    from passt_mav.runs.rundir import RunDir
    from passt_mav.vehicle.controller import MissionController

    n, d = 8, 0.0004  # ~40 m cells
    grid = geo.RegionGrid(HOME[0] - d * 3.5, HOME[1] - d * 3.5, HOME[0] + d * 3.5, HOME[1] + d * 3.5, n, n)
    field = FlowField(
        np.zeros((3, 2, n, n), np.float32) + 0.1, grid, np.array([0.0, 60.0, 120.0]), time_origin="2020-01-01T00:00:00Z"
    )
    fpath = tmp_path / "still.nc"
    field.to_netcdf(fpath)
    cfg = validate_mission(
        {
            "name": "sitl",
            "region": grid.describe(),
            "field": {"source": str(fpath)},
            "model": "persistence",
            "planner": {"name": "lawnmower", "path_length": 6},
            "legs": 1,
            "vehicle": {"speed_mps": 2.0, "wp_radius_m": 3.0},
            "geofence_margin_m": 20.0,
        },
        source="sitl test",
    )
    link = Link(LinkConfig(sitl.connect, connect_timeout_s=60)).connect()
    seen: dict = {}
    try:
        rd = RunDir(tmp_path / "run").create()
        ctl = MissionController(
            cfg,
            link,
            rd,
            field=field,
            predictor=None,
            vehicle=Vehicle(link),
            speedup_hint=sitl.speedup,
            ready_timeout_s=120.0,
            pause_timeout_s=120.0,
            echo=print,
        )

        def settle(mode):  # the firmware's HEARTBEAT says ``mode``, then its MISSION_CURRENT after that
            end = time.monotonic() + 30
            while ctl.vehicle.mode != mode and time.monotonic() < end:
                time.sleep(0.01)
            time.sleep(0.5)  # >= 1 s of vehicle time at 10x: a fresh MISSION_CURRENT
            return ctl.vehicle.mode, int(link.latest("MISSION_CURRENT").seq)

        def paused(_a):
            seen["paused"] = settle(HOLD)
            seen["t"] = time.monotonic()

        def resumed(_a):
            seen["resumed"] = settle(AUTO)

        script = [
            (_flying, {"boat": 0, "action": "pause"}, paused),
            (lambda c: time.monotonic() > seen["t"] + 2.0, {"boat": 0, "action": "resume"}, resumed),
        ]
        op = Operator(ctl, rd.root, script)
        op.start()
        with pytest.raises(MavlinkError, match="no current samples"):
            ctl.run()
        op.join(10)
        assert op.error is None, op.error
        mode, seq = seen["paused"]
        assert mode == HOLD and seq >= 2
        assert seen["resumed"] == (AUTO, seq)  # AUTO at the item it was paused at
        assert [a["level"] for a in op.answers] == ["ok", "ok"]
        assert any("Mission Complete" in t for _, _, t in link.texts)  # the leg flew on to its end
        print(f"SITL: paused at item {seq} (HOLD), resumed there (AUTO), mission complete")
    finally:
        link.close()
