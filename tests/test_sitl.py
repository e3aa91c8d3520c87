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


def _waypoints(n: int):
    """n NAV_WAYPOINTs on a 10 x k lattice ~11 m apart around HOME, with a radius in param2."""
    from passt_mav.mission.items import MissionItem

    return [
        MissionItem(0, lat=HOME[0] + 1e-4 * (i % 10), lon=HOME[1] + 1e-4 * (i // 10) + 3e-7, param2=5.0, alt=1.25)
        for i in range(n)
    ]


def test_no_space_at_boot_is_retried(sitl_factory):
    """Right after boot Rover answers an upload NO_SPACE ("Only 0 items are supported") until its
    storage is initialised; the mission client retries while the vehicle is initialising and succeeds."""
    from passt_mav.mavlink import Link, LinkConfig, MissionClient, with_home

    s = sitl_factory(speedup=1)  # real time: the upload starts well inside the vehicle's storage init
    link = Link(LinkConfig(s.connect, connect_timeout_s=60, stream_rates_hz=())).connect()
    try:
        mc = MissionClient(link, no_space_delay_s=0.5, no_space_retries=20)
        items = with_home(_waypoints(5), home=HOME)
        res = mc.upload(items)
        assert res.no_space_retries >= 1, res  # the NO_SPACE path was really taken
        assert any(t == "Only 0 items are supported" for _, _, t in link.texts)
        got = mc.download()
        assert [(g.x_int, g.y_int) for g in got[1:]] == [(i.x_int, i.y_int) for i in items[1:]]
    finally:
        link.close()


def test_verified_upload_of_100_items(sitl_factory):
    """100 waypoints (+ home) uploaded, read back and compared with what Rover keeps (the radius in
    param2 is dropped by the firmware and is not compared)."""
    from passt_mav.mavlink import Link, LinkConfig, MissionClient, with_home
    from passt_mav.mavlink.mission_client import rover_stored

    s = sitl_factory(speedup=20)
    link = Link(LinkConfig(s.connect, connect_timeout_s=60)).connect()
    try:
        mc = MissionClient(link, no_space_delay_s=0.5, no_space_retries=20)
        items = with_home(_waypoints(100), home=HOME)
        t0 = time.monotonic()
        got = mc.upload_verified(items)
        took = time.monotonic() - t0
        assert len(got) == 101
        assert all(rover_stored(a) == b for a, b in zip(items[1:], got[1:]))
        assert {g.param2 for g in got[1:]} == {0.0} and {round(g.alt, 4) for g in got[1:]} == {1.25}
        print(f"100-item verified upload on SITL x{s.speedup:g}: {took:.2f} s wall")
    finally:
        link.close()


def test_wp_radius_parameter_on_the_firmware(sitl):
    """WP_RADIUS is set through PARAM_SET (PARAM_VALUE echo) and restored; an unknown name gets no reply."""
    from passt_mav.errors import LinkTimeout
    from passt_mav.mavlink import Link, LinkConfig, Vehicle

    link = Link(LinkConfig(sitl.connect, connect_timeout_s=60)).connect()
    try:
        v = Vehicle(link)
        before = v.get_param("WP_RADIUS")
        assert v.set_wp_radius(before + 4.5) == pytest.approx(before + 4.5)
        assert v.get_param("WP_RADIUS") == pytest.approx(before + 4.5)
        assert v.restore_params() == {"WP_RADIUS": pytest.approx(before)}
        assert v.get_param("WP_RADIUS") == pytest.approx(before)
        with pytest.raises(LinkTimeout, match="ARMING_CHECK"):
            v.get_param("ARMING_CHECK", timeout=2.0)  # gone in 4.7: no PARAM_VALUE at all
    finally:
        link.close()


def still_mission(tmp_path, n: int = 6, planner: dict | None = None):
    """(field, mission): an ``n`` x ``n`` grid of ~40 m cells around HOME with a still 0.1 m/s current, one leg
    of ``planner`` (default greedy, 2 moves) at 2 m/s."""
    from passt_mav.fields import FlowField
    from passt_mav.mission.config import validate_mission

    d, h = 0.0004, (n - 1) / 2
    grid = geo.RegionGrid(HOME[0] - d * h, HOME[1] - d * h, HOME[0] + d * h, HOME[1] + d * h, n, n)
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
            "planner": planner or {"name": "greedy", "path_length": 2},
            "legs": 1,
            "vehicle": {"speed_mps": 2.0, "wp_radius_m": 3.0},
            "geofence_margin_m": 20.0,
        },
        source="sitl test",
    )
    return field, cfg


def sitl_controller(tmp_path, sitl, field, cfg, **kw):
    """(run directory, controller) flying ``cfg`` over ``field`` on the SITL instance ``sitl``, over a fresh link
    and with no predictor (``kw``: more MissionController options). The caller closes ``ctl.link``."""
    from passt_mav.mavlink import Link, LinkConfig, Vehicle
    from passt_mav.runs.rundir import RunDir
    from passt_mav.vehicle.controller import MissionController

    link = Link(LinkConfig(sitl.connect, connect_timeout_s=60)).connect()
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
            echo=print,
            **kw,
        )
    except BaseException:
        link.close()
        raise
    return rd, ctl


def test_one_leg_on_ardurover_sitl(tmp_path, sitl):
    from passt_mav.errors import MavlinkError

    field, cfg = still_mission(tmp_path)
    rd, ctl = sitl_controller(tmp_path, sitl, field, cfg)
    link = ctl.link
    try:
        with pytest.raises(MavlinkError, match="no current samples"):
            ctl.run()
        leg = rd.read_leg(0)
        assert leg["status"] == "flying" and Path(rd.waypoints_file(0)).exists()
        assert ctl.vehicle.mode == 5  # LOITER (vehicle.wait_mode) after "Mission Complete": HOLD would drift
        assert any("Mission Complete" in t for _, _, t in link.texts)
    finally:
        link.close()
