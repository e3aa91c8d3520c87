"""The controller against real ArduPilot Rover SITL (marker ``sitl``: runs when ../shared/sitl holds
the build, skips with the reason otherwise; fixtures ``sitl`` / ``sitl_factory`` in conftest.py).

SITL has no current sensor here (that needs the Lua script of ARDUPILOT_ROVER.md), so the leg is
planned, uploaded, verified by read-back, flown in AUTO to "Mission Complete" and switched to
HOLD; then the controller stops with its "no current samples" error. That exercises
everything vehicle-facing against the real firmware.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import geo

pytestmark = pytest.mark.sitl

HOME = (40.0, -63.0)


def _param(m, name: str, timeout: float = 20.0):
    """PARAM_VALUE of ``name`` read with PARAM_REQUEST_READ (resent each second), or None."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        m.mav.param_request_read_send(m.target_system, 1, name.encode(), -1)
        r = m.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
        if r is not None and r.param_id == name:
            return r.param_value
    return None


def test_fixture_restart_keeps_eeprom(sitl):
    """kill9() + restart() is a reboot: same port, new process, parameters kept in eeprom.bin."""
    m = sitl.mavlink()
    try:
        assert m.target_system == 1
        m.mav.param_set_send(1, 1, b"WP_RADIUS", 4.5, 9)
        assert _param(m, "WP_RADIUS") == pytest.approx(4.5)
    finally:
        m.close()
    # parameters are written to eeprom.bin asynchronously (~1 s of wall time is ample)
    time.sleep(2.0)
    old = sitl.pid
    sitl.kill9()
    assert not sitl.alive()
    sitl.restart()
    assert sitl.alive() and sitl.pid != old
    m = sitl.mavlink()
    try:
        assert _param(m, "WP_RADIUS") == pytest.approx(4.5)
    finally:
        m.close()


def test_one_leg_on_ardurover_sitl(tmp_path, sitl):
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
    link = Link(LinkConfig(sitl.connect, connect_timeout_s=60)).connect()
    try:
        rd = RunDir(tmp_path / "run").create()
        ctl = MissionController(cfg, link, rd, field=field, predictor=None, vehicle=Vehicle(link),
                                speedup_hint=sitl.speedup, ready_timeout_s=120.0, echo=print)
        with pytest.raises(MavlinkError, match="no current samples"):
            ctl.run()
        leg = rd.read_leg(0)
        assert leg["status"] == "flying" and Path(rd.waypoints_file(0)).exists()
        assert ctl.vehicle.mode == 4  # HOLD after "Mission Complete"
        assert any("Mission Complete" in t for _, _, t in link.texts)
    finally:
        link.close()
