"""Every shipped mission file flies: ``passt-mav run missions/NAME.yaml`` on vehicle_sim (issue 28, item 1).

``passt-mav run`` is called as a user calls it (``passt_mav.cli.main``: argument parsing, the mission
file, ``--legs``/``--set`` shortening, the field-on-region rule shared with ``plan``, the link, the
controller, summary.json), with one seam: the transport. ``LinkConfig.open`` is replaced by an
in-process endpoint of a :class:`vehicle_sim.Simulator` served in the controller-driven lockstep (``run
--lockstep``: the simulator's clock runs only while the controller waits for the vehicle, one step at a
time), so simulated time follows the controller and the run does not depend on the machine's load.

The simulator's field is placed from the mission file's own numbers (read here with yaml, not through
``passt_mav``'s rule), so a controller that put the cylinder somewhere else would fly outside its region.
Known answers: the mission stored on the vehicle is the leg's planned path (cell centres of the mission's
region, to the wire's 1e-7 deg), the path starts at the mission's start cell and has the --set length,
every frame the controller sent carried its default identity (245/195), and every sample lies inside
the mission's region.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mavlink_helpers import Wire, open_in_lockstep

import geo
from passt_mav.cli import main
from passt_mav.fields.datasets import resolve_field
from passt_mav.mavlink import link as link_mod
from passt_mav.runs.store import SampleStore
from vehicle_sim import SimConfig, Simulator

MISSIONS = Path(__file__).resolve().parent.parent / "missions"
STEP_S = "0.5"  # vehicle seconds per lockstep step (run --lockstep)


def placed_field(data: dict):
    """The mission's field where the mission file puts it, built from the file's numbers directly."""
    field = resolve_field(data["field"]["source"], seed=(data.get("seeds") or {}).get("field", 0))
    r = data["region"]
    if r.get("kind") == "metric":
        g = field.grid
        assert (g.x0, g.x1, g.y0, g.y1, g.rows, g.cols) == (r["x0"], r["x1"], r["y0"], r["y1"], r["rows"], r["cols"])
        field.grid = geo.MetricRegionGrid(
            g.x0,
            g.x1,
            g.y0,
            g.y1,
            g.rows,
            g.cols,
            anchor_lat=r["anchor_lat"],
            anchor_lon=r["anchor_lon"],
            rotation_deg=r["rotation_deg"],
            scale=r["scale"],
        )
    return field


def fly(
    name: str,
    tmp_path,
    monkeypatch,
    *,
    moves: int,
    speed: float,
    extra: tuple[str, ...] = (),
    mission: Path | None = None,
):
    """``passt-mav run missions/NAME.yaml --legs 1 --set planner.path_length=MOVES ...`` on a lockstep sim
    (``mission``: another mission file, whose field is missions/NAME.yaml's)."""
    data = yaml.safe_load((MISSIONS / f"{name}.yaml").read_text())
    path = MISSIONS / f"{name}.yaml" if mission is None else mission
    field = placed_field(data)
    t0 = int(data.get("t0", 0))
    r0, c0 = data["start_cell"]
    home = tuple(float(x) for x in field.grid.cell_to_latlon(r0, c0))
    fs = data["field"]
    sim = Simulator(
        field,
        home=home,
        config=SimConfig.fast(params=(("WP_SPEED", speed),), current_rate_hz=1.0, seed=1),
        velocity_scale=float(fs.get("velocity_scale", 1.0)),
        time_scale=float(fs.get("time_scale", 1.0)),
        start_time=float(field.times[t0]),
    )
    wire = Wire()
    open_in_lockstep(monkeypatch, sim, wire.wrap)
    out = tmp_path / name
    try:
        rc = main(
            [
                "run",
                str(path),
                "--connect",
                "tcp:127.0.0.1:5760",
                "--legs",
                "1",
                "--out",
                str(out),
                "--set",
                f"planner.path_length={moves}",
                "--set",
                f"vehicle.speed_mps={speed}",
                "--lockstep",
                STEP_S,
                "--speedup-hint",
                "1000000",
                "--no-report",
                "--quiet",
                *extra,
            ]
        )
    finally:
        sim.stop()
    f = out / "summary.json"
    summary = json.loads(f.read_text()) if f.exists() else {}
    return rc, summary, sim, wire, out, field


def check_flight(rc, summary, sim, wire, out, field, *, moves: int, start: tuple[int, int]):
    assert rc == 0, summary.get("events")
    assert summary["status"] == "complete" and len(summary["legs"]) == 1
    leg = summary["legs"][0]
    path = np.array(leg["path"])
    # the leg starts where the boat is: at the mission's start cell, or a neighbour after drifting in
    # HOLD while the controller waited for the EKF and planned (a boat holds no position in a current)
    assert np.abs(path[0] - np.array(start)).max() <= 1 and len(path) == moves + 1
    # the mission on the vehicle is the planned path: waypoints at cell centres of the mission's region
    got = np.array([(it.x, it.y) for it in sim.autopilot.store.items[0] if it.command == 16 and it.seq >= 1]) / 1e7
    want = np.array(leg["waypoints"])
    assert got.shape == want.shape and np.allclose(got, want, atol=1.5e-7)
    cells = np.array(leg.get("waypoint_cells") or [])
    if cells.size:
        lat, lon = field.grid.cell_to_latlon(cells[:, 0], cells[:, 1])
        assert np.allclose(np.column_stack([lat, lon]), want, atol=1e-9)
    # every frame the controller sent carried our default identity, never QGC's 255/190
    assert wire.ids == {(link_mod.DEFAULT_SOURCE_SYSTEM, link_mod.DEFAULT_SOURCE_COMPONENT)}
    assert (link_mod.DEFAULT_SOURCE_SYSTEM, link_mod.DEFAULT_SOURCE_COMPONENT) == (245, 195)
    store = SampleStore(out / "samples.sqlite", readonly=True)
    recs = store.all()
    store.close()
    assert leg["n_samples"] > 0 and len(recs) >= leg["n_samples"]
    lat = np.array([r.lat for r in recs])
    lon = np.array([r.lon for r in recs])
    assert field.grid.contains(lat, lon, margin_m=0.5 * field.grid.mean_cell_size_m).all()


@pytest.mark.parametrize("name", ["cylinder", "oscillating_cylinder"])
def test_cylinder_mission_files_fly(name, tmp_path, monkeypatch):
    # 3 moves of ~31 m at 3 m/s: ~40 s of vehicle time; background 0 keeps the GP's roll-out out of the leg
    rc, summary, sim, wire, out, field = fly(
        name, tmp_path, monkeypatch, moves=3, speed=3.0, extra=("--set", "gp.background=0")
    )
    check_flight(rc, summary, sim, wire, out, field, moves=3, start=(15, 2))
    # the cylinder's truth is the placed field: the run's RMSE is computed (not "no truth on this grid")
    assert summary["legs"][0]["rmse_passt"] is not None


@pytest.mark.slow(
    reason="one move of a 6-9 km cell per shipped ocean mission file, ~15-20 min of vehicle time each: ~1-2 min"
)
@pytest.mark.parametrize("name, start", [("north_atlantic", (15, 15)), ("rtofs", (14, 18))])
def test_ocean_mission_files_fly(name, start, tmp_path, monkeypatch):
    # one move of a 6-9 km cell at 8 m/s: ~15-20 min of vehicle time
    rc, summary, sim, wire, out, field = fly(name, tmp_path, monkeypatch, moves=1, speed=8.0)
    check_flight(rc, summary, sim, wire, out, field, moves=1, start=start)


def test_a_field_file_beside_the_mission_is_found_and_recorded_so_that_it_resolves(tmp_path, monkeypatch):
    """``field.source: cyl.nc`` beside the mission file, flown as ``passt-mav run nj1/m.yaml`` from the folder
    above (the working directory is not the mission's): the field is the mission folder's file, and the run
    directory records a path that resolves from anywhere, so that ``report`` finds the truth and ``replay
    RUN_DIR`` works from another working directory."""
    nj1 = tmp_path / "nj1"
    nj1.mkdir()
    resolve_field("builtin:cylinder").to_netcdf(nj1 / "cyl.nc")
    data = yaml.safe_load((MISSIONS / "cylinder.yaml").read_text())
    data["field"]["source"] = "cyl.nc"
    (nj1 / "m.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    monkeypatch.chdir(tmp_path)
    rc, summary, _sim, _wire, out, _field = fly(
        "cylinder",
        tmp_path,
        monkeypatch,
        moves=2,
        speed=3.0,
        extra=("--set", "gp.background=0"),
        mission=Path("nj1") / "m.yaml",
    )
    assert rc == 0 and summary["status"] == "complete"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    for recorded in (
        yaml.safe_load((out / "mission.yaml").read_text())["field"]["source"],
        summary["config"]["field"]["source"],
        summary["field"],
    ):
        assert Path(recorded).is_absolute() and Path(recorded).samefile(nj1 / "cyl.nc"), recorded
    from passt_mav.analysis.report import load_run

    run = load_run(out)
    assert run.field is not None, run.notes.get("field")
    assert main(["replay", str(out), "--json"]) == 0


def test_our_ids_from_the_mission_file_and_the_command_line_reach_the_wire(tmp_path, monkeypatch):
    """vehicle.source_system/source_component in the mission, --source-component on the command line
    (which wins): the companion-computer case, the vehicle's system id with a component of our own."""
    rc, summary, _sim, wire, _out, _field = fly(
        "cylinder",
        tmp_path,
        monkeypatch,
        moves=1,
        speed=3.0,
        extra=(
            "--set",
            "gp.background=0",
            "--set",
            "vehicle.source_system=1",
            "--set",
            "vehicle.source_component=191",
            "--source-component",
            "196",
        ),
    )
    assert rc == 0 and summary["status"] == "complete"
    assert wire.ids == {(1, 196)}


def test_speaking_as_the_autopilot_itself_is_refused_in_one_line(tmp_path, monkeypatch, capsys):
    rc, _summary, _sim, _wire, _out, _field = fly(
        "cylinder", tmp_path, monkeypatch, moves=1, speed=3.0, extra=("--source-system", "1", "--source-component", "1")
    )
    assert rc == 2 and "is the vehicle's own autopilot's" in capsys.readouterr().err


def test_every_shipped_mission_file_is_flown_here():
    """A new file in missions/ must be added to the tests above."""
    assert sorted(p.stem for p in MISSIONS.glob("*.yaml")) == [
        "cylinder",
        "north_atlantic",
        "oscillating_cylinder",
        "rtofs",
    ]


# -- plan and run: one rule for a mission's field on its region ----------------------------------------


@pytest.mark.parametrize("name", ["cylinder", "oscillating_cylinder", "north_atlantic", "rtofs"])
def test_plan_accepts_every_shipped_mission_file(name, tmp_path, capsys):
    assert (
        main(
            [
                "plan",
                str(MISSIONS / f"{name}.yaml"),
                "--model",
                "none",
                "--length",
                "3",
                "--json",
                "--out",
                str(tmp_path / "p"),
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(out["waypoint_cells"]) >= 2


@pytest.mark.parametrize(
    "key, value, needle",
    [
        (
            "x0",
            2.5,
            (
                "the mission's region x0 = 2.5 data m is not the field's (builtin:cylinder: 2.6); use the field's "
                "region (passt-mav data info builtin:cylinder)"
            ),
        ),
        ("rows", 29, "the field builtin:cylinder is a 30x30 grid, the mission's region 29x30"),
    ],
)
def test_plan_and_run_refuse_a_region_off_the_field_with_the_same_line(key, value, needle, tmp_path, capsys):
    data = yaml.safe_load((MISSIONS / "cylinder.yaml").read_text())
    data["region"][key] = value
    if key == "rows":
        data["start_cell"] = [10, 2]
    f = tmp_path / "off.yaml"
    f.write_text(yaml.safe_dump(data))
    lines = []
    for argv in (
        ["plan", str(f), "--model", "none", "--out", str(tmp_path / "p")],
        ["run", str(f), "--connect", "tcp:127.0.0.1:9", "--out", str(tmp_path / "r"), "--no-report"],
    ):
        assert main(argv) == 2
        lines.append(capsys.readouterr().err.strip().splitlines()[-1])
    assert lines[0] == lines[1] == f"passt-mav: error: {needle}"


def test_a_metric_field_takes_the_missions_placement_and_keeps_its_data():
    from passt_mav.fields.datasets import field_on_region, mission_field
    from passt_mav.mission.config import load_mission

    cfg = load_mission(MISSIONS / "cylinder.yaml")
    raw = resolve_field("builtin:cylinder")
    placed = mission_field(cfg)
    assert raw.grid.scale == 1.0 and placed.grid == cfg.grid() and placed.grid.scale == 100.0
    assert placed.data is raw.data or np.array_equal(placed.data, raw.data)
    # one cell of the placed grid: 0.303 data m x 100 = 30.3 m east-west (the mission file's comment)
    assert placed.grid.cell_size_m[1] == pytest.approx((11.4 - 2.6) / 29 * 100, rel=1e-3)
    # a geographic field on its own region is returned as it is; on a metric region it is refused
    ocean = resolve_field("builtin:ocean")
    assert field_on_region(ocean, ocean.grid, source="builtin:ocean") is ocean
    from passt_mav.errors import FieldError

    with pytest.raises(FieldError, match="geographic grid; the mission's region must be 'kind: geographic'"):
        field_on_region(ocean, cfg.grid(), source="builtin:ocean")


def test_resume_goes_on_with_the_runs_own_approve_mode_and_leg_count(tmp_path, monkeypatch, capsys):
    """``run --resume`` continues the run as it was: approve mode (given as ``--approve``), the leg count (``--legs``)
    and the rest of the mission come from the run's records, not from the mission file named again; ``--set``
    changes them and is said. Before, a resume without ``--approve`` flew its legs unapproved and took the leg
    count from the mission file."""
    data = yaml.safe_load((MISSIONS / "cylinder.yaml").read_text())
    field = placed_field(data)
    r0, c0 = data["start_cell"]
    fs = data["field"]
    sim = Simulator(
        field,
        home=tuple(float(x) for x in field.grid.cell_to_latlon(r0, c0)),
        config=SimConfig.fast(params=(("WP_SPEED", 5.0),), current_rate_hz=1.0, seed=1),
        velocity_scale=float(fs.get("velocity_scale", 1.0)),
        time_scale=float(fs.get("time_scale", 1.0)),
        start_time=float(field.times[int(data.get("t0", 0))]),
    )
    sim.serve([], lockstep=True)  # the controller-driven lockstep: the vehicle's clock runs while it waits
    monkeypatch.setattr(link_mod.LinkConfig, "open", lambda self: sim.connect_inprocess().mavlink_connection())
    out = tmp_path / "run"
    common = ["--connect", "tcp:127.0.0.1:5760", "--out", str(out), "--lockstep", "1", "--speedup-hint", "1000000"]
    common += ["--no-report"]

    def summary():
        return json.loads((out / "summary.json").read_text())

    try:
        first = ["--legs", "3", "--approve", "--set", "approve.timeout_s=0.5", "--set", "planner.path_length=3"]
        assert main(["run", str(MISSIONS / "cylinder.yaml"), *common, *first]) == 1  # nobody approves: paused
        assert summary()["status"] == "paused" and summary()["legs_planned"] == 3
        capsys.readouterr()
        # resumed without --approve or --legs: approve mode and the 3 legs go on (the mission file says 5, no approve)
        live: list[dict] = []
        stop = threading.Event()

        def watch():  # the live view's test of a finished run: summary.json's finished_utc
            while not stop.is_set():
                s = summary()
                if s.get("status") == "running" and s.get("finished_utc") is None:
                    live.append(s)
                    return
                time.sleep(0.002)

        th = threading.Thread(target=watch, daemon=True)
        th.start()
        try:
            assert main(["run", str(MISSIONS / "cylinder.yaml"), *common, "--resume"]) == 1
        finally:
            stop.set()
            th.join(5)
        assert live, "the resumed session never said it was running: its live page stayed a record"
        said = capsys.readouterr().out
        assert "resume: the run's own mission" in said and "approve on" in said and "3 legs" in said, said
        assert summary()["status"] == "paused" and summary()["config"]["approve"]["enabled"]
        assert summary()["legs_planned"] == 3 and not summary()["legs"]
        # --set changes it, and says so: the legs fly unapproved, 3 of them, with the first session's path length
        again = ["--resume", "--set", "approve.enabled=false"]
        assert main(["run", str(MISSIONS / "cylinder.yaml"), *common, *again]) == 0
        assert "resume: changed by --set: approve.enabled=false" in capsys.readouterr().out
    finally:
        sim.stop()
    s = summary()
    assert s["status"] == "complete" and [len(leg["path"]) for leg in s["legs"]] == [4, 4, 4]
