"""Issue 44's Pause/Resume on ArduPilot Rover SITL (marker ``sitl``; skips without the build in ../shared/sitl).

The operator (tests/test_console.py's :class:`Operator`) pauses the leg once two items are behind the boat
and resumes it after the firmware has held for a while: the firmware reports LOITER (the wait_mode), then AUTO at the item it
was paused at (MISSION_CURRENT), and the leg flies on to "Mission Complete". SITL has no current sensor here,
so the run then stops with its "no current samples" error, as in tests/test_sitl.py.
"""

from __future__ import annotations

import time

import pytest
from test_console import Operator, _flying
from test_sitl import sitl_controller, still_mission

pytestmark = pytest.mark.sitl

HOLD, AUTO, LOITER = 4, 10, 5


@pytest.mark.long(reason="ArduRover SITL in wall time through a pause and a resume: ~20 s")
def test_pause_and_resume_on_ardurover_sitl(tmp_path, sitl):
    from passt_mav.errors import MavlinkError

    field, cfg = still_mission(tmp_path, 8, {"name": "lawnmower", "path_length": 6})
    rd, ctl = sitl_controller(tmp_path, sitl, field, cfg, pause_timeout_s=120.0)
    link = ctl.link
    seen: dict = {}
    try:

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
        assert mode == LOITER and seq >= 2  # the wait_mode: the firmware keeps station
        assert seen["resumed"] == (AUTO, seq)  # AUTO at the item it was paused at
        assert [a["level"] for a in op.answers] == ["ok", "ok"]
        assert any("Mission Complete" in t for _, _, t in link.texts)  # the leg flew on to its end
        print(f"SITL: paused at item {seq} (HOLD), resumed there (AUTO), mission complete")
    finally:
        link.close()
