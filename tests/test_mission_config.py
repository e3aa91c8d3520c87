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


def test_relative_paths_resolve_from_the_mission_files_folder_not_the_working_directory(tmp_path, monkeypatch):
    """``nj1/m.yaml`` read from the folder above: its ``f.nc`` and ``k.pt`` are nj1's, held absolute (not
    ``nj1/f.nc``, which another working directory would not find), and the text a run directory keeps names
    them absolute too (the rest of the mission unchanged); a mission without relative paths is kept as written."""
    from passt_mav.mission.config import recorded_mission_text

    nj1 = tmp_path / "nj1"
    nj1.mkdir()
    for name in ("f.nc", "k.pt"):
        (nj1 / name).write_bytes(b"")
    (nj1 / "m.yaml").write_text(yaml.safe_dump({**GOOD, "field": "f.nc", "model": "k.pt"}, sort_keys=False))
    monkeypatch.chdir(tmp_path)
    cfg = load_mission(Path("nj1") / "m.yaml")
    assert cfg.field.source == str(nj1 / "f.nc") and cfg.model == str(nj1 / "k.pt")
    kept = yaml.safe_load(recorded_mission_text((nj1 / "m.yaml").read_text(), cfg))
    assert kept == {**GOOD, "field": str(nj1 / "f.nc"), "model": str(nj1 / "k.pt")}
    monkeypatch.chdir(nj1)  # the kept text validates to the same config from anywhere (here: base_dir elsewhere)
    assert validate_mission(kept, base_dir=tmp_path / "elsewhere") == cfg
    text = "# a comment\n" + yaml.safe_dump(GOOD)
    assert recorded_mission_text(text, validate_mission(GOOD)) == text


def _with(**changes):
    d = yaml.safe_load(yaml.safe_dump(GOOD))
    for key, val in changes.items():
        if key == "region" and val is _METRIC:
            d["region"] = dict(_METRIC)
            continue
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
_INF, _NAN = float("inf"), float("nan")
_METRIC = {"x0": 2.6, "x1": 11.4, "y0": -4.7, "y1": 4.7, "rows": 30, "cols": 30, "anchor_lat": 40, "anchor_lon": -63}
#: a "billion laughs": 9 levels of 9 aliases (10**9 strings expanded) in 10 short lines
_BOMB = "lol0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"lol{k}: &l{k} [" + ", ".join([f"*l{k - 1}"] * 9) + "]\n" for k in range(1, 10)
)

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
] + [
    # issue 55: every number finite and within physical bounds, options known, keys once, aliases bounded
    ("speed_inf", _with(vehicle__speed_mps=_INF), "vehicle.speed_mps: input should be a finite number (got inf)"),
    ("speed_nan", _with(vehicle__speed_mps=_NAN), "vehicle.speed_mps: input should be a finite number (got nan)"),
    ("speed_too_fast", _with(vehicle__speed_mps=25), "vehicle.speed_mps: must be <= 20 (got 25)"),
    ("water_speed_too_fast", _with(vehicle__max_water_speed_mps=50.0), "vehicle.max_water_speed_mps: must be <= 20"),
    ("wp_radius_inf", _with(vehicle__wp_radius_m=_INF), "vehicle.wp_radius_m: input should be a finite number"),
    (
        "link_window_nan",
        _with(vehicle__link_loss_window_s=_NAN),
        "vehicle.link_loss_window_s: input should be a finite",
    ),
    ("path_length_huge", _with(planner__path_length=10**6), "planner.path_length: must be <= 1000 (got 1000000)"),
    ("legs_huge", _with(legs=10**9), "legs: must be <= 10000 (got 1000000000)"),
    ("steps_per_leg_huge", _with(steps_per_leg=10**7), "steps_per_leg: must be <= 10000"),
    ("t0_huge", _with(t0=10**12), "t0: must be <= 10000"),
    ("rows_huge", _with(region__rows=100_000), "region.rows: must be <= 1000 (got 100000)"),
    ("cols_huge", _with(region__cols=5000), "region.cols: must be <= 1000 (got 5000)"),
    ("south_beyond_pole", _with(region__south=-100.0), "region.south: must be >= -90 (got -100.0)"),
    ("east_inf", _with(region__east=_INF), "region.east: input should be a finite number (got inf)"),
    ("time_scale_zero", _with(field__time_scale=0), "field.time_scale: must be > 0 (got 0)"),
    ("time_scale_inf", _with(field__time_scale=_INF), "field.time_scale: input should be a finite number"),
    ("time_scale_huge", _with(field__time_scale=1e30), "field.time_scale: must be <= 1000000 (got 1e+30)"),
    ("velocity_scale_nan", _with(field__velocity_scale=_NAN), "field.velocity_scale: input should be a finite"),
    ("velocity_scale_huge", _with(field__velocity_scale=1e6), "field.velocity_scale: must be <= 100"),
    ("noise_inf", _with(sensors__noise_std=_INF), "sensors.noise_std: input should be a finite number"),
    ("margin_nan", _with(geofence_margin_m=_NAN), "geofence_margin_m: input should be a finite number"),
    ("budget_time_inf", _with(budget__max_time_s=_INF), "budget.max_time_s: input should be a finite number"),
    ("budget_distance_huge", _with(budget__max_distance_m=1e300), "budget.max_distance_m: must be <= 100000000"),
    ("approve_timeout_inf", _with(approve__timeout_s=_INF), "approve.timeout_s: input should be a finite number"),
    ("forgetting_nan", _with(gp__forgetting=_NAN), "gp.forgetting: input should be a finite number"),
    ("background_huge", _with(gp__background=10**8), "gp.background: must be <= 10000"),
    ("lr_inf", _with(model_update__lr=_INF), "model_update.lr: input should be a finite number"),
    ("window_huge", _with(model_update__window=10**9), "model_update.window: must be <= 10000"),
    ("seed_negative", _with(seeds__planner=-1), "seeds.planner: must be >= 0 (got -1)"),
    ("seed_huge", _with(seeds__gp=2**40), "seeds.gp: must be <= 4294967295"),
    ("metric_scale_inf", _with(region=_METRIC, region__scale=_INF), "region.scale: input should be a finite number"),
    ("metric_rotation_nan", _with(region=_METRIC, region__rotation_deg=_NAN), "region.rotation_deg: input should be"),
    ("metric_x1_huge", _with(region=_METRIC, region__x1=1e12), "region.x1: must be <= 10000000"),
    (
        "fleet_too_large",
        _with(vehicles=[{"connect": f"tcp:127.0.0.1:{5760 + 10 * k}"} for k in range(65)]),
        "vehicles: list should have at most 64 items",
    ),
    (
        "planner_option_unknown",
        _with(planner__options={"lookahaed": 3}),
        "planner: options: unknown option 'lookahaed' of planner 'greedy' (allowed: lookahead)",
    ),
    ("planner_option_inf", _with(planner__options={"lookahead": _INF}), "planner: options.lookahead: must be a finite"),
    (
        "gp_option_unknown",
        _with(gp__options={"kernle": "rbf"}),
        "gp: options: unknown option 'kernle' of GPReconstructor",
    ),
    ("gp_option_internal", _with(gp__options={"grid_xy": [1]}), "gp: options: unknown option 'grid_xy'"),
    ("gp_option_nan", _with(gp__options={"alpha": _NAN}), "gp: options.alpha: must be a finite number (got nan)"),
    ("duplicate_key", _with() + "legs: 2\nlegs: 3\n", "duplicate key 'legs' (first given at line"),
    (
        "duplicate_nested_key",
        _with() + "vehicle: {speed_mps: 2.0, wp_radius_m: 3, speed_mps: 30}\n",
        "duplicate key 'speed_mps' (first given at line",
    ),
    ("alias_bomb", _with() + _BOMB, "its aliases expand it past 100,000 values (an alias bomb?)"),
    ("alias_loop", _with() + "x-loop: &a [1, *a]\n", "an alias refers to the value that holds it"),
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


RUN_CASES = ("speed_inf", "path_length_huge", "rows_huge", "time_scale_zero", "duplicate_key", "alias_bomb")


@pytest.mark.parametrize("text, expect", [b[1:] for b in BROKEN if b[0] in RUN_CASES], ids=RUN_CASES)
def test_broken_mission_file_run_exit_2_one_line_before_connecting(tmp_path, capsys, text, expect):
    """``passt-mav run`` refuses them before it connects (nothing listens on port 9: had it gone on, it would try)."""
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    rc = main(["run", str(p), "--connect", "tcp:127.0.0.1:9", "--out", str(tmp_path / "out")])
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("passt-mav: error: ") and expect in lines[0], cap.err
    assert "connect" not in cap.out.lower() and not (tmp_path / "out").exists()


def test_an_alias_bomb_is_refused_at_once_and_merge_keys_still_work(tmp_path):
    import time

    p = tmp_path / "bomb.yaml"
    p.write_text(_with() + _BOMB)
    t0 = time.perf_counter()
    with pytest.raises(MissionConfigError, match="alias bomb"):
        load_mission(p)
    assert time.perf_counter() - t0 < 2.0
    # a few aliases and a merge key (its keys overridden by the mapping's own) are fine: no duplicate
    p.write_text(
        _with(planner=_DROP)
        + "x-boat: &boat {speed_mps: 2.0, wp_radius_m: 3.0}\n"
        + "vehicle:\n  <<: *boat\n  speed_mps: 4.0\n"
        + "planner: {name: greedy, path_length: 5, options: {lookahead: 3}}\n"
    )
    with pytest.raises(MissionConfigError, match="x-boat: unknown key"):  # (an unknown top-level key all the same)
        load_mission(p)
    from passt_mav.mission.config import read_mission_data

    data = read_mission_data(p)
    assert data["vehicle"] == {"speed_mps": 4.0, "wp_radius_m": 3.0}
    del data["x-boat"]
    cfg = validate_mission(data)
    assert (cfg.vehicle.speed_mps, cfg.vehicle.wp_radius_m, cfg.planner.options) == (4.0, 3.0, {"lookahead": 3})


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
