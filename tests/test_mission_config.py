"""Mission YAML: the shipped scenario files load; broken files give one line naming the key,
both from load_mission and through the command line (exit code 2)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

import geo
from passt_mav.cli import main
from passt_mav.errors import MissionConfigError
from passt_mav.mission import load_mission
from passt_mav.mission.config import MissionConfig, validate_mission

MISSIONS = Path(__file__).resolve().parent.parent / "missions"

GOOD = {
    "name": "t",
    "region": {"south": 39.360065, "west": -64.24, "north": 41.130714, "east": -61.92004, "rows": 30, "cols": 30},
    "field": {"source": "builtin:ocean"},
    "planner": {"name": "greedy", "path_length": 5},
}


def test_shipped_missions_load():
    na = load_mission(MISSIONS / "north_atlantic.yaml")
    assert na.grid() == geo.north_atlantic_grid()
    assert na.field.source == "builtin:ocean" and na.model == "builtin:ocean"
    cyl = load_mission(MISSIONS / "cylinder.yaml")
    g = cyl.grid()
    assert isinstance(g, geo.MetricRegionGrid) and g.shape == (30, 30)
    assert (g.x0, g.x1, g.y0, g.y1) == (2.6, 11.4, -4.7, 4.7)
    assert g.cell_size_m[1] == pytest.approx(8.8 / 29 * cyl.region.scale, rel=1e-4)
    assert cyl.field.source == "builtin:cylinder" and cyl.model == "builtin:cylinder"
    # time_scale documented as scale / velocity_scale
    assert cyl.field.time_scale == pytest.approx(cyl.region.scale / cyl.field.velocity_scale)
    osc = load_mission(MISSIONS / "oscillating_cylinder.yaml")
    assert osc.field.source == "builtin:oscillating" and osc.model == "builtin:cylinder"
    assert osc.grid() == g
    for m in (na, cyl, osc):
        assert (m.planner.name, m.planner.reward) == ("information", "variance_reduction")  # issue 27
        assert m.planner.path_length >= 1 and m.vehicle.speed_mps > 0
        assert m.start_cell is not None and m.grid().contains(*m.grid().cell_to_latlon(*m.start_cell))


def test_defaults_and_normalisation():
    cfg = MissionConfig.model_validate(GOOD)
    assert cfg.model == "builtin:ocean"  # the scenario's shipped model
    assert cfg.vehicle.connect == "tcp:127.0.0.1:5760" and cfg.sensors.u == "CUR_U" and cfg.sensors.v == "CUR_V"
    assert (
        cfg.gp.prior == "forecast"
        and cfg.gp.loop_prior == "forecast"
        and cfg.legs == 1
        and cfg.planner.reward == "speed"
    )
    osc = MissionConfig.model_validate({**GOOD, "field": "builtin:oscillating", "model": "shipped:cylinder"})
    assert osc.field.source == "builtin:oscillating" and osc.model == "builtin:cylinder"
    assert MissionConfig.model_validate({**GOOD, "planner": {"name": "pg"}}).planner.name == "policy_gradient"
    assert MissionConfig.model_validate({**GOOD, "gp": {"prior": "constant"}}).gp.loop_prior == "none"
    assert (
        cfg.gp.background == 200 and MissionConfig.model_validate({**GOOD, "gp": {"background": 0}}).gp.background == 0
    )
    # the blend's fixed share reaches the loop a mission builds (0.05 the default, 0 = off)
    from passt_mav.loop.legstep import build_loop
    from passt_mav.models import make_predictor

    unshared = MissionConfig.model_validate({**GOOD, "gp": {"prior_blend": "bma", "prior_share": 0}})
    loops = [build_loop(c, make_predictor("persistence"), c.grid()) for c in (cfg, unshared)]
    assert [lp.share for lp in loops] == [0.05, 0.0] and loops[1].prior_blend == "bma"
    assert loops[0].prior_blend == "select"


def test_field_file_relative_to_mission_file(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "f.nc").write_bytes(b"")
    p = tmp_path / "m.yaml"
    p.write_text(yaml.safe_dump({**GOOD, "field": {"source": "data/f.nc"}, "model": "persistence"}))
    assert load_mission(p).field.source == str(tmp_path / "data" / "f.nc")


def _with(**changes):
    d = yaml.safe_load(yaml.safe_dump(GOOD))
    for key, val in changes.items():
        *head, last = key.split("__")
        node = d
        for h in head:
            node = node.setdefault(h, {})
        if val is _DROP:
            node.pop(last)
        else:
            node[last] = val
    return yaml.safe_dump(d)


_DROP = object()

BROKEN = [
    # (id, YAML text, text the one-line message must contain)
    ("bad_yaml", "name: t\nregion: {south: 1, west: [\n", "invalid YAML at line"),
    ("tab_yaml", "name: t\n\tregion: 1\n", "invalid YAML"),
    ("not_mapping", "- 1\n- 2\n", "must be a YAML mapping"),
    ("empty", "", "is empty"),
    ("missing_name", _with(name=_DROP), "name: required key is missing"),
    ("missing_field", _with(field=_DROP), "field: required key is missing"),
    ("missing_region_key", _with(region__rows=_DROP), "region.rows: required key is missing"),
    ("wrong_type_rows", _with(region__rows="thirty"), "region.rows:"),
    ("wrong_type_legs", _with(legs=[1, 2]), "legs:"),
    ("negative_speed", _with(vehicle__speed_mps=-1.0), "vehicle.speed_mps: must be > 0 (got -1.0)"),
    ("zero_length", _with(planner__path_length=0), "planner.path_length: must be >= 1 (got 0)"),
    ("unknown_planner", _with(planner__name="astar"), "planner.name: unknown planner 'astar'; choose one of"),
    ("unknown_reward", _with(planner__reward="fun"), "planner.reward: unknown reward 'fun'"),
    ("region_order", _with(region__south=42.0), "region: region needs -90 <= south < north"),
    (
        "metric_order",
        yaml.safe_dump(
            {
                **GOOD,
                "region": {
                    "x0": 5,
                    "x1": 1,
                    "y0": 0,
                    "y1": 1,
                    "rows": 3,
                    "cols": 3,
                    "anchor_lat": 40,
                    "anchor_lon": -63,
                },
            }
        ),
        "region: metric grid needs x0 < x1",
    ),
    ("unknown_field", _with(field__source="builtin:lake"), "field.source: unknown built-in field 'lake'"),
    ("field_not_nc", _with(field__source="data.csv"), "field.source: must be builtin:ocean"),
    ("field_missing_file", _with(field__source="no/such.nc"), "field.source: field file not found"),
    ("extra_key", _with(colour="red"), "colour: unknown key (allowed: name, region"),
    (
        "extra_nested_key",
        _with(vehicle__sped_mps=2),
        "vehicle.sped_mps: unknown key (allowed: connect, speed_mps, wp_radius_m",
    ),
    ("extra_region_key", _with(region__depth=3), "region.depth: unknown key (allowed: kind, south"),
    ("negative_margin", _with(geofence_margin_m=-5), "geofence_margin_m: must be >= 0 (got -5)"),
    ("start_outside", _with(start_cell=[30, 0]), "start_cell [30, 0] lies outside the 30x30 grid"),
    ("start_shape", _with(start_cell=[1, 2, 3]), "start_cell:"),
    ("legs_zero", _with(legs=0), "legs: must be >= 1 (got 0)"),
    ("sensor_name_long", _with(sensors__u="CURRENT_EAST"), "sensors.u:"),
    ("bad_prior", _with(gp__prior="zero"), "gp.prior:"),
    (
        "background_one",
        _with(gp__background=1),
        "gp.background: a background roll-out needs 0 (none) or at least 2 snapshots",
    ),
    ("background_negative", _with(gp__background=-5), "gp.background: must be >= 0 (got -5)"),
    ("share_above_one", _with(gp__prior_share=1.5), "gp.prior_share: must be <= 1 (got 1.5)"),
    ("unknown_model", _with(model="transformer"), "model: unknown model 'transformer'"),
    ("missing_ckpt", _with(model="nope.pt"), "model: model checkpoint not found"),
]


@pytest.mark.parametrize("text, expect", [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN])
def test_broken_mission_file_load_mission(tmp_path, text, expect):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(MissionConfigError) as exc:
        load_mission(p)
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith(f"{p}: ")
    assert expect in msg


@pytest.mark.parametrize("text, expect", [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN])
def test_broken_mission_file_cli_exit_2_one_line(tmp_path, capsys, text, expect):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    rc = main(["plan", str(p), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("passt-mav: error: ") and expect in lines[0]
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_missing_mission_file(tmp_path, capsys):
    with pytest.raises(MissionConfigError, match="no such mission file"):
        load_mission(tmp_path / "nope.yaml")
    assert main(["plan", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert "no such mission file" in capsys.readouterr().err


def test_several_problems_are_counted_on_one_line():
    with pytest.raises(MissionConfigError) as exc:
        validate_mission({"name": "x"}, source="m.yaml")
    msg = str(exc.value)
    assert msg.startswith("m.yaml: ") and "required key is missing" in msg and "more problem" in msg and "\n" not in msg
