"""Issue 52, item 2: the boat keeps station whenever the controller makes it wait, and every wait is measured.

ArduPilot Rover's HOLD stops the motor (``Rover/mode_hold.cpp``): a boat in HOLD drifts with the current (on
Rover SITL in a 0.5 m/s tide, 60.2 m in 120 s; LOITER 1.9 m). vehicle-sim does the same, so here, in a uniform
0.5 m/s current flowing west and in lockstep (the vehicle's clock runs only while the controller waits), a leg
that awaits the operator's approval for 600 s of vehicle time must keep the boat within 2 x WP_RADIUS in the
default ``vehicle.wait_mode: loiter``, and drift about 0.5 m/s x the wait with ``wait_mode: hold``.
"""

from __future__ import annotations

import numpy as np
import pytest
from mavlink_helpers import HOME, inprocess_factory, link_config
from test_console import WALL_S, Operator, _awaiting
from test_controller import controller, mission, sim_config, wave_field

from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.fields.field import FlowField
from passt_mav.mavlink import Link
from passt_mav.runs.rundir import RunDir
from vehicle_sim import Simulator

TIDE = (-0.5, 0.0)  # m/s east, north: the water flows west (SITL's SIM_TIDE_DIR 90, SIM_TIDE_SPEED 0.5)
WAIT_S = 600.0  # vehicle seconds the second leg waits for its approval
WP_RADIUS = 3.0  # the test mission's vehicle.wp_radius_m


def _still_field() -> FlowField:
    """The wave field's grid and times with no current of its own: the uniform tide is all that moves the boat."""
    f = wave_field()
    return FlowField(np.zeros_like(f.data), f.grid, f.times, time_origin=f.time_origin)


@pytest.mark.parametrize("wait_mode", ["loiter", "hold"])
def test_an_approval_wait_of_600_s_keeps_station_in_loiter_and_drifts_in_hold(tmp_path, wait_mode):
    field = _still_field()
    sim = Simulator(field, home=HOME, config=sim_config(), uniform_current=TIDE)
    sim.serve([], lockstep=True)
    rd = RunDir(tmp_path / "run").create()
    link = Link(
        link_config(lockstep_s=1.0, lockstep_pace=1e5, stream_rates_hz=LEAN_STREAMS, tlog=str(rd.tlog)),
        connection_factory=inprocess_factory(sim),
    )
    cfg = mission(
        tmp_path,
        field,
        legs=2,
        approve={"enabled": True, "timeout_s": WALL_S},
        vehicle={"speed_mps": 5.0, "wp_radius_m": WP_RADIUS, "wait_mode": wait_mode},
    )
    seen: dict[str, float] = {}

    def waited_600_s(ctl) -> bool:
        if not _awaiting(rd, 1)(ctl):
            return False
        seen.setdefault("t0", sim.t)
        return sim.t >= seen["t0"] + WAIT_S

    script = [
        (_awaiting(rd, 0), {"boat": 0, "action": "approve", "leg": 0}, None),
        (waited_600_s, {"boat": 0, "action": "approve", "leg": 1}, None),
    ]
    if wait_mode == "hold":  # 300 m west: out of the start cell, so the leg is planned again from there
        script.append((_awaiting(rd, 1, attempts=1), {"boat": 0, "action": "approve", "leg": 1}, None))
    link.connect()
    try:
        ctl = controller(cfg, field, link, rd, echo=None)
        op = Operator(ctl, rd.root, script)
        op.start()
        summary = ctl.run()
        op.join(10)
    finally:
        link.close()
        sim.stop()
    assert op.error is None, op.error
    assert summary["status"] == "complete"
    (wait,) = summary["legs"][1]["waits"]  # from leg 1's end through planning and the approval to leg 2's AUTO
    assert wait["kind"] == "between legs" and wait["mode"] == wait_mode.upper()
    assert wait["vehicle_s"] >= WAIT_S
    leg2 = summary["legs"][1]
    if wait_mode == "loiter":
        assert wait["drift_m"] <= 2 * WP_RADIUS
        assert not leg2.get("attempts")
    else:  # the tide's 0.5 m/s over the whole wait, within 10 %
        assert wait["drift_m"] == pytest.approx(0.5 * wait["vehicle_s"], rel=0.10)
        assert wait["to"][1] < wait["from"][1]  # west
        # the approved plan started where the boat no longer was: planned again from the cell it drifted to
        (attempt,) = leg2["attempts"]
        assert attempt["status"] == "drifted while awaiting approval"
        assert leg2["start_cell"] == list(field.grid.latlon_to_cell(*wait["to"], clip=True))
        assert leg2["start_cell"] != attempt["start_cell"]
        # and the log says so: a replay plans both attempts and reproduces every path
        from passt_mav.analysis.replay import replay

        result = replay(rd.root, out=False)
        assert result.reproduced, [(x.index, x.differing_cells, x.notes) for x in result.legs]
    # the run ends with the boat loitering, armed (vehicle.on_end: loiter), never armed in HOLD
    assert summary["end"]["mode"] == "LOITER" and summary["end"]["armed"]
