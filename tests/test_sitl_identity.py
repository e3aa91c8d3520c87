"""Our identity beside a ground station on the real firmware (issue 28, item 3; marker ``sitl``).

ArduPilot Rover 4.7 SITL (speed-up 10), the controller's Link on SERIAL0 and a QGroundControl-like
client (255/190) on SERIAL1, the boat armed in MANUAL with the GCS failsafe on (FS_GCS_ENABLE 1,
FS_ACTION 2 = HOLD). The failsafe counts only heartbeats from MAV_GCS_SYSID (255). QGC goes silent
while the controller's link stays alive and keeps sending heartbeats:

* as 245 (our default) the failsafe fires and the boat holds: it still means "the operator's ground
  station is gone";
* as 255 (QGC's id, the old default) the controller's heartbeats keep it fed: the boat goes on in
  MANUAL with nobody watching (the masking docs/real-boat.md, "Identity on a shared link", warns of).

Measured on this build: the failsafe's STATUSTEXT reads "Radio Failsafe" (Rover prints the type of
the check that happens to run when the timeout passes), so the test asserts the mode and a
"Failsafe" text, not the word GCS. Our heartbeats go at 20 Hz wall: at speed-up 10 FS_GCS_TIMEOUT
(5 s) is 0.5 s wall, shorter than the 1 s default period (on a real boat 1 Hz is ample).
"""

from __future__ import annotations

import os
import threading
import time

import pytest

pytestmark = pytest.mark.sitl

HOME = (40.0, -63.0)


@pytest.mark.parametrize("our_system, failsafe", [(245, True), (255, False)], ids=["ours-245", "qgc-255"])
def test_qgc_going_silent_trips_the_gcs_failsafe_unless_we_speak_as_its_id(sitl_factory, our_system, failsafe):
    from pymavlink import mavutil

    from passt_mav.mavlink import Link, LinkConfig, Vehicle

    s = sitl_factory(speedup=10, home=HOME)
    link = Link(
        LinkConfig(s.connect, connect_timeout_s=60, source_system=our_system, heartbeat_period_s=0.05)
    ).connect()
    os.environ.setdefault("MAVLINK20", "1")
    qgc = mavutil.mavlink_connection(
        f"tcp:127.0.0.1:{s.port + 2}", source_system=255, source_component=190, autoreconnect=False
    )
    assert qgc.wait_heartbeat(timeout=30) is not None
    beating, stop = threading.Event(), threading.Event()
    beating.set()

    def qgc_heartbeats():
        while not stop.is_set():
            if beating.is_set():
                qgc.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4)
            while qgc.recv_match(blocking=False) is not None:
                pass  # keep its socket drained
            time.sleep(0.05)

    th = threading.Thread(target=qgc_heartbeats, daemon=True)
    th.start()
    v = Vehicle(link, retry_delay_s=0.2)
    try:
        v.wait_ready(timeout=120)
        assert v.get_param("MAV_GCS_SYSID") == 255 and v.set_param("FS_GCS_ENABLE", 1) == 1
        v.arm(timeout=60)  # commands from 245/195 are taken like a ground station's
        time.sleep(1.0)  # both beating: no failsafe
        assert v.mode == 0 and v.armed and not any("Failsafe" in t for _, _, t in link.texts)
        beating.clear()  # QGC goes silent
        end = time.monotonic() + 8.0  # 80 s of vehicle time: 16 x FS_GCS_TIMEOUT
        while time.monotonic() < end and v.mode == 0:
            time.sleep(0.05)
        if failsafe:
            assert v.mode == 4 and any(t.endswith("Failsafe") for _, _, t in link.texts), list(link.texts)[-5:]
        else:
            assert v.mode == 0 and not any(t.endswith("Failsafe") for _, _, t in link.texts), list(link.texts)[-5:]
        assert not link.lost  # our link was alive all along
    finally:
        stop.set()
        th.join(5)
        try:
            v.disarm(force=True)
        except Exception:  # noqa: BLE001, S110 - teardown of a vehicle about to be stopped
            pass
        qgc.close()
        link.close()
