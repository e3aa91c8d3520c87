"""passt-mav plan: one leg from a mission file to .plan / .waypoints / path.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import geo
from passt_mav.cli import main
from passt_mav.mission import WaypointMission

MISSIONS = Path(__file__).resolve().parent.parent / "missions"


@pytest.fixture(scope="module")
def na_leg(tmp_path_factory):
    out = tmp_path_factory.mktemp("plan_na")
    rc = main(
        [
            "plan",
            str(MISSIONS / "north_atlantic.yaml"),
            "--model",
            "none",
            "--time",
            "3",
            "--reward",
            "speed",
            "--planner",
            "policy_gradient",
            "--start",
            "10,12",
            "--length",
            "8",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    return out


def test_plan_writes_files_that_agree_with_the_path(na_leg):
    d = json.loads((na_leg / "path.json").read_text())
    g = geo.north_atlantic_grid()
    path = np.array(d["path"])
    assert path.shape == (9, 2) and tuple(path[0]) == (10, 12)
    np.testing.assert_array_equal(geo.validate_path(g, path), path)  # 8-connected, in the grid
    wps = geo.path_to_waypoints(g, path)
    for f in ("leg.plan", "leg.waypoints"):
        m = (WaypointMission.from_plan if f.endswith(".plan") else WaypointMission.from_wpl)(na_leg / f)
        np.testing.assert_allclose(m.waypoints, wps, rtol=0, atol=1e-12)
        assert m.speed == 2.0 and m.wp_radius_m == 10.0
    fenced = WaypointMission.from_plan(na_leg / "leg.plan")
    np.testing.assert_allclose(fenced.fence, g.geofence(500.0), atol=1e-12)  # geofence_margin_m of the mission
    lines = (na_leg / "leg.waypoints").read_text().splitlines()
    assert lines[0] == "QGC WPL 110" and lines[1].split("\t")[:4] == ["0", "1", "0", "16"]


def test_plan_reward_is_the_normalised_speed_of_the_state(na_leg):
    from passt_mav.fields.datasets import load_dataset

    d = json.loads((na_leg / "path.json").read_text())
    state = load_dataset("ocean").data[3].astype(np.float64)
    spd = np.hypot(state[0], state[1])
    expect = np.where(np.isfinite(spd), spd, 0.0) / np.nanmax(spd)
    np.testing.assert_allclose(np.array(d["reward_map"]), expect, atol=2e-6)
    cells = {tuple(c) for c in d["path"][1:]} - {tuple(d["path"][0])}
    assert d["reward_collected"] == pytest.approx(sum(expect[c] for c in cells), abs=1e-4)
    assert "no predictor" in d["note"] and d["model"] is None


def test_plan_cylinder_json_summary(tmp_path, capsys):
    rc = main(
        ["plan", str(MISSIONS / "cylinder.yaml"), "--model", "none", "--length", "5", "--json", "--out", str(tmp_path)]
    )
    assert rc == 0
    s = json.loads(capsys.readouterr().out)
    assert s["start"] == [15, 2] and s["path_length"] == 5 and len(s["files"]) == 3
    assert all(Path(f).exists() for f in s["files"])
    m = WaypointMission.from_plan(tmp_path / "leg.plan")
    from passt_mav.mission import load_mission

    grid = load_mission(MISSIONS / "cylinder.yaml").grid()
    assert np.all(grid.contains(m.waypoints[:, 0], m.waypoints[:, 1]))


@pytest.mark.parametrize(
    "extra, expect",
    [
        (["--start", "30,0"], "outside the 30x30 grid"),
        (["--start", "a,b"], "ROW,COL"),
        (["--time", "100000"], "outside the state's snapshots"),
        (["--length", "0"], "--length must be >= 1"),
        (["--reward", "colour"], "--planner / --reward"),
    ],
)
def test_plan_bad_options_exit_2(tmp_path, capsys, extra, expect):
    rc = main(["plan", str(MISSIONS / "north_atlantic.yaml"), "--model", "none", "--out", str(tmp_path / "o"), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err[-1].startswith("passt-mav: error: ") and expect in err[-1]


def test_plan_from_a_state_file(tmp_path, capsys):
    from passt_mav.fields.datasets import load_dataset

    f = load_dataset("ocean").isel(time=slice(5, 7))
    state = f.to_netcdf(tmp_path / "state.nc")
    rc = main(
        [
            "plan",
            str(MISSIONS / "north_atlantic.yaml"),
            "--state",
            str(state),
            "--time",
            "1",
            "--model",
            "none",
            "--reward",
            "speed",
            "--start",
            "20,5",
            "--length",
            "4",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert rc == 0
    d = json.loads((tmp_path / "o" / "path.json").read_text())
    spd = np.hypot(*f.data[1].astype(np.float64))
    np.testing.assert_allclose(np.array(d["reward_map"]), spd / spd.max(), atol=2e-6)
    assert d["state"] == str(state) and d["time_index"] == 1 and d["path"][0] == [20, 5]
