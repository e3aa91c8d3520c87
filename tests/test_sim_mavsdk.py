"""MAVSDK (python ``mavsdk`` 4.x, ctypes over libcmavsdk) against the simulator over TCP.

Real time is involved (MAVSDK's own timers are wall-clock), so the simulator
runs with a speedup and the test is marked slow (~10 s).
"""

from __future__ import annotations

import math
import time

import pytest
from simclient import free_port

from vehicle_sim import SimConfig, Simulator

mavsdk = pytest.importorskip("mavsdk")

HOME = (40.0, -63.0)


@pytest.mark.slow(reason="MAVSDK's server binary against the simulator in wall time (a separate client stack): ~1 min")
def test_mavsdk_mission_raw_upload_download_arm_start_and_progress():
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.mission_raw import MissionItem, MissionRaw, MissionRawResult
    from mavsdk.plugins.telemetry import Telemetry

    port = free_port()
    # storage initialises 15 s (1.5 s wall) after boot: MAVSDK's first upload meets NO_SPACE,
    # which it reports as TOO_MANY_MISSION_ITEMS (ARDUPILOT_ROVER.md); a retry later succeeds
    sim = Simulator(None, home=HOME, config=SimConfig.fast(storage_ready_s=15.0, ekf_gps_s=1.5))
    sim.serve([f"tcp:127.0.0.1:{port}"], speedup=10)
    drone = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        assert drone.add_any_connection(f"tcpout://127.0.0.1:{port}") == 0
        system = drone.first_autopilot(10.0)
        assert system is not None
        mr, act, tel = MissionRaw(system), Action(system), Telemetry(system)
        dlat = 20.0 / 111_035.0  # 20 m legs north
        items = [
            MissionItem(
                i,
                0 if i == 0 else 6,
                16,
                1 if i == 0 else 0,
                1,
                0,
                0,
                0,
                0,
                int(round((HOME[0] + dlat * i) * 1e7)),
                int(round(HOME[1] * 1e7)),
                0.0,
                0,
            )
            for i in range(4)
        ]
        results = []
        t_first = sim.t
        for _ in range(60):
            try:
                results.append(mr.upload_mission(items))
                break
            except Exception as exc:  # noqa: BLE001 - MissionRawError
                results.append(exc.args[0] if exc.args else exc)
                assert results[-1] == MissionRawResult.TOO_MANY_MISSION_ITEMS, results
                time.sleep(0.1)
        assert results[-1] == MissionRawResult.SUCCESS, results
        print("MAVSDK upload attempts:", [getattr(r, "name", r) for r in results], "first at sim t", round(t_first, 2))
        if t_first < 14.0:
            assert results[0] == MissionRawResult.TOO_MANY_MISSION_ITEMS and len(results) > 1
        got = mr.download_mission()
        assert len(got) == 4
        assert [(g.x, g.y) for g in got[1:]] == [(i.x, i.y) for i in items[1:]]
        assert (got[0].x, got[0].y, got[0].frame) == (int(round(HOME[0] * 1e7)), int(round(HOME[1] * 1e7)), 0)
        while sim.t < 2.0:
            time.sleep(0.05)
        act.arm()
        p0 = tel.position()
        progress = []
        mr.subscribe_mission_progress(lambda p, _ud: progress.append((p.current, p.total)))
        mr.start_mission()
        t0 = time.time()
        while not mr.is_mission_finished() and time.time() - t0 < 30:
            time.sleep(0.1)
        assert mr.is_mission_finished()
        p1 = tel.position()
        moved = (p1.latitude_deg - p0.latitude_deg) * 111_035.0
        assert moved == pytest.approx(60.0, abs=4.0) and math.isfinite(p1.longitude_deg)
        assert progress and max(c for c, _ in progress) >= 3
        assert tel.armed()
    finally:
        drone.destroy()
        sim.stop()
