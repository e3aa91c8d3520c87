"""Issue 52, item 4: legs planned in the current, flown on vehicle_sim.

``passt-mav run missions/north_atlantic.yaml --legs 2 --set planner.path_length=6`` as shipped (2 m/s,
``builtin:ocean``: a Gulf-Stream-like jet up to ~1.7 m/s), against an in-process :class:`vehicle_sim.Simulator`
in the controller-driven lockstep (``run --lockstep 1``: its clock runs only while the controller waits for
it, 1 s of vehicle time a step). Before, a leg was timed at 2 m/s over ground: against
the jet the boat makes ~0.75 m/s, the leg took far longer than planned and the overrun rule cut it.

The simulator's boat holds its track like ArduPilot's L1 controller (``nav="crosstrack"``: it crabs against
the cross-track current, the law the plan is timed with; the simulator's default ``pursuit`` points at the
next waypoint and lets the current push it off the line), and its hull makes at most the mission's 2 m/s
through the water (``max_speed``; the mission's ``vehicle.max_water_speed_mps`` is unset, i.e. 2 m/s): the
autopilot holds 2 m/s over ground where the hull can, full throttle against the jet. Known answers: both legs complete, none is cut,
each leg's planned duration (leg.json ``planned_duration_vehicle_s``, in the forecast current) is within
20 % (the issue's bound; 5 % here, measured 0.7 %) of the vehicle seconds it flew, and every planned move makes at least ``FEASIBLE_MARGIN`` x 2 m/s over
ground in the forecast.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest
import yaml

from passt_mav.cli import main
from passt_mav.fields.datasets import resolve_field
from passt_mav.mavlink import link as link_mod
from passt_mav.planning.transit import FEASIBLE_MARGIN
from vehicle_sim import SimConfig, Simulator
from vehicle_sim.boat import BoatParams

MISSION = Path(__file__).resolve().parent.parent / "missions" / "north_atlantic.yaml"
STEP_S = 1.0  # vehicle seconds per lockstep step (legs of ~7-8 h)


@pytest.mark.long(
    reason="two legs of six 6.8 km moves of the ocean mission (~18 h of vehicle time in 1 s lockstep steps): ~3-6 min"
)
def test_north_atlantic_legs_finish_in_the_time_planned_in_the_current(tmp_path, monkeypatch):
    data = yaml.safe_load(MISSION.read_text())
    assert data["vehicle"]["speed_mps"] == 2.0 and data["field"]["source"] == "builtin:ocean"  # as shipped
    field = resolve_field(data["field"]["source"], seed=data["seeds"]["field"])
    r0, c0 = data["start_cell"]
    sim = Simulator(
        field,
        home=tuple(float(x) for x in field.grid.cell_to_latlon(r0, c0)),
        config=SimConfig.fast(
            params=(("WP_SPEED", 2.0),), current_rate_hz=0.2, seed=1, boat=BoatParams(nav="crosstrack", max_speed=2.0)
        ),
        start_time=float(field.times[data["t0"]]),
    )
    # the controller-driven lockstep: the vehicle's clock runs only while the controller waits for it, 1 s a
    # step, so a loaded machine cannot make the vehicle's mission-transfer timers outrun the controller
    sim.serve([], lockstep=True)
    monkeypatch.setattr(link_mod.LinkConfig, "open", lambda self: sim.connect_inprocess().mavlink_connection())
    out = tmp_path / "run"
    try:
        rc = main(
            [
                "run",
                str(MISSION),
                "--connect",
                "tcp:127.0.0.1:5760",
                "--legs",
                "2",
                "--set",
                "planner.path_length=6",
                "--out",
                str(out),
                "--lockstep",
                str(STEP_S),
                "--speedup-hint",
                "1000000",
                "--no-report",
                "--quiet",
            ]
        )
    finally:
        sim.stop()
    summary = json.loads((out / "summary.json").read_text())
    assert rc == 0 and summary["status"] == "complete", summary.get("events")
    assert len(summary["legs"]) == 2
    for leg in summary["legs"]:
        assert leg["status"] == "complete" and leg["overrun"] is None
        flown, planned = leg["duration_vehicle_s"], leg["planned_duration_vehicle_s"]
        assert flown > 6 * 3000.0  # hours of vehicle time: six cells of 6.8 km at ~2 m/s
        assert abs(planned - flown) <= 0.2 * flown, (leg["index"], planned, flown)  # the bound
        # measured: -0.7 % and -0.6 %; the still-water rule (planner.current_aware false, the same paths)
        # was off by -4.8 % and -7.7 %, so this bound tells the two apart
        assert abs(planned - flown) <= 0.05 * flown, (leg["index"], planned, flown)
        assert len(leg["path"]) == 7
        assert min(leg["planned_ground_speed_m_s"]) >= FEASIBLE_MARGIN * 2.0
        arr = leg["planned_arrival_vehicle_s"]
        assert arr[0] == 0.0 and all(b > a for a, b in itertools.pairwise(arr))
