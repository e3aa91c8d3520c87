"""The controller against real ArduPilot Rover SITL (marker ``sitl``; skipped unless ``ARDUROVER``
points at an ``ardurover`` binary, e.g. ``build/sitl/bin/ardurover`` of an ArduPilot checkout).

SITL has no current sensor (that needs the Lua script of ARDUPILOT_ROVER.md), so the leg is
planned, uploaded, verified by read-back, flown in AUTO to "Mission Complete" and switched to
HOLD; then the controller stops with its "no current samples" error. That exercises
everything vehicle-facing against the real firmware.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

import geo

pytestmark = pytest.mark.sitl

ARDUROVER = os.environ.get("ARDUROVER")
HOME = (40.0, -63.0)


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.skipif(not ARDUROVER or not shutil.which(ARDUROVER) and not Path(ARDUROVER or "").exists(),
                    reason="set ARDUROVER to an ardurover SITL binary")
def test_one_leg_on_ardurover_sitl(tmp_path):
    from passt_mav.controller import MissionController
    from passt_mav.errors import MavlinkError
    from passt_mav.fields import FlowField
    from passt_mav.mavlink import Link, LinkConfig, Vehicle
    from passt_mav.mission.config import validate_mission
    from passt_mav.runs.rundir import RunDir

    n, d = 6, 0.0004  # ~40 m cells
    grid = geo.RegionGrid(HOME[0] - d * 2.5, HOME[1] - d * 2.5, HOME[0] + d * 2.5, HOME[1] + d * 2.5, n, n)
    field = FlowField(np.zeros((3, 2, n, n), np.float32) + 0.1, grid, np.array([0.0, 60.0, 120.0]),
                      time_origin="2020-01-01T00:00:00Z")
    fpath = tmp_path / "still.nc"
    field.to_netcdf(fpath)
    cfg = validate_mission({"name": "sitl", "region": grid.describe(), "field": {"source": str(fpath)},
                            "model": "persistence", "planner": {"name": "greedy", "path_length": 2}, "legs": 1,
                            "vehicle": {"speed_mps": 2.0, "wp_radius_m": 3.0}, "geofence_margin_m": 20.0},
                           source="sitl test")
    cmd = [ARDUROVER, "-S", "--model", "motorboat", "--speedup", "5", "-I0", "--home", f"{HOME[0]},{HOME[1]},0,0"]
    if os.environ.get("ARDUROVER_PARAMS"):  # e.g. Tools/autotest/default_params/rover.parm,motorboat.parm
        cmd += ["--defaults", os.environ["ARDUROVER_PARAMS"]]
    proc = subprocess.Popen(cmd,
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + 30
        while not _port_open(5760):
            assert proc.poll() is None and time.monotonic() < end, "SITL did not open tcp:5760"
            time.sleep(0.2)
        link = Link(LinkConfig("tcp:127.0.0.1:5760", connect_timeout_s=60)).connect()
        try:
            rd = RunDir(tmp_path / "run").create()
            ctl = MissionController(cfg, link, rd, field=field, predictor=None, vehicle=Vehicle(link),
                                    speedup_hint=5.0, ready_timeout_s=120.0, echo=print)
            with pytest.raises(MavlinkError, match="no current samples"):
                ctl.run()
            leg = rd.read_leg(0)
            assert leg["status"] == "flying" and Path(rd.waypoints_file(0)).exists()
            assert ctl.vehicle.mode == 4  # HOLD after "Mission Complete"
            assert any("Mission Complete" in t for _, _, t in link.texts)
        finally:
            link.close()
    finally:
        proc.terminate()
        proc.wait(10)
