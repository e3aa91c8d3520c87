"""A fleet of three real ArduPilot Rover SITL boats through one PASST loop (marker ``sitl``).

Three instances of ../shared/sitl/ardurover (``start-sitl -I N``, MAV_SYSID 1, 2, 3), each
started in another cell of the small gentle field of test_sitl_faults (6x6 cells of ~40 m)
with the Lua current sensor, flown by ``passt-mav run``'s own code path
(:func:`passt_mav.commands.run.execute` with ``vehicles:``): one link and one tlog per boat,
one sample store, one shared estimate.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from test_sitl_faults import SPEEDUP, _field

pytestmark = pytest.mark.sitl

CELLS = [(1, 1), (4, 4), (1, 4)]


def _boot_at(tmp_path, sitl_factory, field, field_path, k: int, cell):
    """SITL instance for boat ``k`` (MAV_SYSID k+1) at the centre of ``cell``, with the Lua sensor."""
    from passt_mav.commands.data import export_lua_grid, lua_script_path
    from passt_mav.fields.field import load_field

    wd = tmp_path / f"sitl{k}"
    (wd / "scripts").mkdir(parents=True)
    export_lua_grid(load_field(field_path), wd / "scripts" / "current_grid.bin", time_at_boot=0.0)
    lua = tmp_path / f"lua{k}"
    lua.mkdir()
    (lua / "current_sensor.lua").write_text(Path(lua_script_path()).read_text())
    lat, lon = field.grid.cell_to_latlon(*cell)
    return sitl_factory(workdir=wd, speedup=SPEEDUP, scripts=lua, sysid=k + 1, home=(float(lat), float(lon)))


def test_three_sitl_boats_complete_a_fleet_mission(tmp_path, sitl_factory):
    from passt_mav.commands.run import execute
    from passt_mav.mission.config import validate_mission
    from passt_mav.runs.rundir import RunDir
    from passt_mav.runs.store import SampleStore

    # every leg spans at least one 600 s snapshot, and a boat that drops out and rejoins flies more legs:
    # 12 snapshots keep the truth defined for all of them
    field, path = _field(tmp_path, n_times=12)
    sitls = [_boot_at(tmp_path, sitl_factory, field, path, k, c) for k, c in enumerate(CELLS)]
    cfg = validate_mission(
        {
            "name": "sitl_fleet",
            "region": field.grid.describe(),
            "field": {"source": str(path)},
            "model": "persistence",
            "planner": {"name": "greedy", "path_length": 2},
            "legs": 2,
            "vehicles": [{"connect": s.connect, "speed_mps": 4.0, "wp_radius_m": 3.0} for s in sitls],
            "geofence_margin_m": 30.0,
            "gp": {"hyper": "first_leg"},
        },
        source="sitl fleet test",
    )
    rd = RunDir(tmp_path / "run").create()
    lines: list[str] = []
    summary = execute(
        cfg,
        connect=cfg.vehicle.connect,
        run_dir=rd,
        mission_text=None,
        speedup=SPEEDUP,
        ready_timeout=120.0,
        echo=lambda s: lines.append(s) or print(s),
        report=False,
    )
    assert summary["status"] == "complete", summary["events"]
    assert sorted(b["sysid"] for b in summary["boats"]) == [1, 2, 3]
    assert [b["status"] for b in summary["boats"]] == ["complete"] * 3
    legs = summary["legs"]
    assert len(legs) == 6 and sorted(x["boat"] for x in legs) == [0, 0, 1, 1, 2, 2]
    for leg in legs:
        assert leg["n_samples"] > 5 and leg["rmse_passt"] is not None
    with SampleStore(rd.samples_db, readonly=True) as st:
        sources = {r.source for r in st.all()}
    assert sources == {"mav:1/1", "mav:2/1", "mav:3/1"}
    assert [p.name for p in rd.boat_tlogs()] == [f"flight_boat{k}.tlog" for k in range(3)]
    assert all(p.stat().st_size > 10_000 for p in rd.boat_tlogs())
