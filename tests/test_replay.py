"""Replaying a run from its telemetry log (passt_mav.analysis.replay, ``passt-mav replay``).

One real run is flown once per module with the controller's in-process test setup
(tests/test_controller.py: vehicle_sim at 50x, 8x8 grid of ~40 m cells, greedy
planner, persistence model, 2 legs of 3 moves; ~6-10 s on two loaded cores), with
the link writing ``flight.tlog``. The replay must reproduce every planned path
exactly and the recorded RMSE figures to 1e-6, from the log alone; its rebuilt
samples must equal the controller's sample store.
"""

from __future__ import annotations

import json
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
import test_controller as tc
import yaml
from mavlink_helpers import served

from passt_mav.analysis.replay import ReplayError, rebuild_from_tlog, replay, waypoints_to_path
from passt_mav.cli import main
from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.mission.config import validate_mission
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore
from passt_mav.runs.tlog import TlogScanner


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    """(run_dir, mission.yaml path, summary) of a 2-leg mission flown against the simulator."""
    tmp = tmp_path_factory.mktemp("replay")
    field = tc.wave_field()
    tc.mission(tmp, field)  # writes wave.nc
    g = field.grid
    data = {
        "name": "wave",
        "region": {"south": g.south, "west": g.west, "north": g.north, "east": g.east, "rows": tc.N, "cols": tc.N},
        "field": {"source": str(tmp / "wave.nc")},
        "model": "persistence",
        "planner": {"name": "greedy", "path_length": 3},
        "legs": 2,
        "t0": 0,
        "vehicle": {"speed_mps": 5.0, "wp_radius_m": 3.0},
        "sensors": {"noise_std": tc.NOISE},
        "geofence_margin_m": 30.0,
        "gp": {"hyper": "first_leg"},
    }
    text = yaml.safe_dump(data)
    mfile = tmp / "wave.yaml"
    mfile.write_text(text)
    cfg = validate_mission(data, source="test")
    rd = RunDir(tmp / "run").create()
    with served(
        tc.sim_config(),
        field=field,
        speedup=tc.SPEEDUP,
        link_kw={"stream_rates_hz": LEAN_STREAMS, "tlog": str(rd.tlog)},
    ) as (_sim, link):
        summary = tc.controller(cfg, field, link, rd, echo=None, mission_text=text).run()
    assert summary["status"] == "complete" and len(summary["legs"]) == 2
    return rd, mfile, summary


def _store_legs(rd):
    st = SampleStore(rd.samples_db, readonly=True)
    try:
        return {i: sorted((s.time_boot_ms, s.lat, s.lon, s.u, s.v) for s in st.for_leg(i)) for i in range(2)}
    finally:
        st.close()


def _tuples(recs):
    return sorted((r["time_boot_ms"], r["lat"], r["lon"], r["u"], r["v"]) for r in recs)


def test_tampered_record_diverges_exit_1(flown, tmp_path, capsys):
    """A leg record whose path is not what the code plans: exit 1, the leg and the cells named."""
    rd, _, summary = flown
    rd2 = RunDir(tmp_path / "run")
    shutil.copytree(rd.root, rd2.root, ignore=shutil.ignore_patterns("replay"))
    rec = rd2.read_leg(1)
    path = [list(x) for x in rec["path"]]
    last = path[-1]
    alt = next(
        [last[0] + a, last[1] + b]
        for a in (-1, 0, 1)
        for b in (-1, 0, 1)
        if (a or b) and [last[0] + a, last[1] + b] != path[-2] and 0 <= last[0] + a < tc.N and 0 <= last[1] + b < tc.N
    )
    path[-1] = alt
    rec["path"] = path
    rd2.write_leg(1, rec)
    rc = main(["replay", str(rd2.root), "--json"])
    res = json.loads(capsys.readouterr().out)
    assert rc == 1 and res["reproduced"] is False and res["first_divergence"] == 1
    assert res["legs"][0]["path_identical"] is True
    assert res["legs"][1]["differing_cells"] == [
        {"step": 3, "recorded": alt, "replayed": summary["legs"][1]["path"][3]}
    ]
    assert (rd2.root / "replay" / "replay.json").exists()


def _is_path(p, start, L):
    p = np.asarray(p)
    return (
        p.shape == (L + 1, 2)
        and tuple(p[0]) == tuple(start)
        and bool((np.abs(np.diff(p, axis=0)).max(axis=1) == 1).all())
    )


def test_replay_reproduces_paths_rmse_and_samples(flown, tmp_path, capsys):
    rd, _, summary = flown
    rc = main(["replay", str(rd.root), "--out", str(tmp_path / "rep")])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "reproduced" in out and "identical" in out
    res = json.loads((tmp_path / "rep" / "replay.json").read_text())
    assert res["reproduced"] is True and res["first_divergence"] is None and res["exit_code"] == 0
    assert len(res["legs"]) == 2
    for got, want in zip(res["legs"], summary["legs"]):
        assert got["path"] == want["path"] and got["path_identical"] is True and got["differing_cells"] == []
        assert got["start_cell"] == want["start_cell"] and got["forecast_steps_before"] == want["forecast_steps_before"]
        assert got["rmse_passt"] == pytest.approx(want["rmse_passt"], abs=1e-6)
        assert got["rmse_model"] == pytest.approx(want["rmse_model"], abs=1e-6)
        assert got["n_samples"] == want["n_samples"] and got["n_gp_points"] == want["n_gp_points"]
    assert [x["rmse_passt"] for x in res["legs"]] == pytest.approx(summary["rmse"]["passt"], abs=1e-6)
    assert not any("differ from the run's store" in n for x in res["legs"] for n in x["notes"])
    # the samples rebuilt from the log through the controller's collector = the controller's store
    log = rebuild_from_tlog(rd.tlog)
    store = _store_legs(rd)
    assert [_tuples(lg.samples) for lg in log.legs] == [store[0], store[1]]
    # the uploaded waypoints expand back into the planned grid paths
    for lg, want in zip(log.legs, summary["legs"]):
        assert waypoints_to_path(rd_grid(flown), lg.waypoints).tolist() == want["path"]


def rd_grid(flown):
    from passt_mav.mission.config import load_mission

    return load_mission(flown[1]).grid()


def test_counterfactual_planner_gives_other_paths(flown, tmp_path, capsys):
    rd, _, summary = flown
    rc = main(["replay", str(rd.root), "--planner", "lawnmower", "--json", "--out", str(tmp_path)])
    res = json.loads(capsys.readouterr().out)
    assert rc == 0 and res["reproduced"] is None and res["counterfactual"] == {"planner": "lawnmower"}
    assert res["settings"]["planner"] == "lawnmower"
    differ = 0
    for got, want in zip(res["legs"], summary["legs"]):
        assert got["recorded_path"] == want["path"]
        assert _is_path(got["path"], want["start_cell"], 3)
        if got["path"] != want["path"]:
            differ += 1
            assert got["path_identical"] is False and got["differing_cells"]
            k = got["differing_cells"][0]["step"]
            assert got["path"][k] != want["path"][k] and got["path"][:k] == want["path"][:k]
        assert got["reward_collected"] > 0
    assert differ >= 1
    # the same data, the recorded start cells, the recorded sample counts
    assert [x["n_samples"] for x in res["legs"]] == [x["n_samples"] for x in summary["legs"]]


def test_bare_tlog_with_mission_reproduces_from_waypoints(flown, tmp_path):
    rd, mfile, summary = flown
    log = tmp_path / "flight.tlog"
    shutil.copy(rd.tlog, log)
    res = replay(log, mission=mfile, out=tmp_path / "o")
    assert res.kind == "tlog" and res.reproduced is True and (tmp_path / "o" / "replay.json").exists()
    assert [x.path for x in res.legs] == [x["path"] for x in summary["legs"]]
    assert [x.path_identical for x in res.legs] == [True, True]
    # no summary: RMSE recomputed against the mission's field. The controller's clock STATUSTEXT in the
    # log says which vehicle time it planned from: no search, the recorded forecast steps, RMSE to 1e-6
    log_legs = rebuild_from_tlog(log).legs
    assert all(lg.clock is not None for lg in log_legs)
    for got, want, lg in zip(res.legs, summary["legs"], log_legs):
        assert got.forecast_steps_before == want["forecast_steps_before"] == lg.clock[2]
        assert lg.clock[0] == want["clock_reading"]["time_boot_ms"]
        assert not any("brackets" in n for n in got.notes)
        assert got.rmse_passt == pytest.approx(want["rmse_passt"], abs=1e-6)
        assert got.rmse_model == pytest.approx(want["rmse_model"], abs=1e-6)


def test_bare_tlog_of_an_older_controller_searches_the_clock_bracket(flown, tmp_path):
    """A log without the clock STATUSTEXT (controllers before it was sent): the replay tries the
    forecast steps the log brackets and keeps those whose plans are the uploaded paths."""
    rd, mfile, summary = flown
    data = rd.tlog.read_bytes()
    keep, n_cut, pos = bytearray(), 0, 0
    for _, m in TlogScanner(data):
        buf = m.get_msgbuf()
        at = data.index(buf, pos)
        rec = data[at - 8 : at + len(buf)]  # 8-byte timestamp + frame
        pos = at + len(buf)
        if m.get_type() == "STATUSTEXT" and "PASST leg" in str(m.text):
            n_cut += 1
            continue
        keep += rec
    assert n_cut >= len(summary["legs"])  # (leg 0 sends it again after arming: see MissionController._swap)
    old = tmp_path / "old.tlog"
    old.write_bytes(bytes(keep))
    assert all(lg.clock is None for lg in rebuild_from_tlog(old).legs)
    res = replay(old, mission=mfile, out=False)
    assert res.reproduced is True
    assert [x.path for x in res.legs] == [x["path"] for x in summary["legs"]]


def test_pymavlink_logger_tlog_replays_into_the_same_samples(flown, tmp_path):
    """Re-record the flight through pymavlink's own tlog writer (as MAVProxy logs)."""
    rd, mfile, summary = flown
    frames = [m.get_msgbuf() for _, m in TlogScanner(rd.tlog.read_bytes())]
    from test_tlog import _record_tlog  # pymavlink's own tlog writer, as MAVProxy records

    out = _record_tlog([bytes(f) for f in frames], tmp_path, name="mavproxy.tlog")
    log = rebuild_from_tlog(out)
    store = _store_legs(rd)
    assert [_tuples(lg.samples) for lg in log.legs] == [store[0], store[1]]
    res = replay(out, mission=mfile, out=False)
    assert res.reproduced is True and [x.path for x in res.legs] == [x["path"] for x in summary["legs"]]
    # and as a run directory whose tlog is the re-recorded one: paths and RMSE to 1e-6
    rd2 = RunDir(tmp_path / "run2")
    shutil.copytree(rd.root, rd2.root, ignore=shutil.ignore_patterns("replay"))
    shutil.copy(out, rd2.tlog)
    res2 = replay(rd2.root, out=False)
    assert res2.reproduced is True
    assert [x.rmse_passt for x in res2.legs] == pytest.approx([x["rmse_passt"] for x in summary["legs"]], abs=1e-6)


def _record_ends(data: bytes) -> list[int]:
    ends, p = [], 0
    for _, m in TlogScanner(data):
        p += 8 + len(m.get_msgbuf())
        ends.append(p)
    return ends


def test_truncated_tlog_replays_what_is_readable(flown, tmp_path):
    rd, mfile, summary = flown
    data = rd.tlog.read_bytes()
    log0 = rebuild_from_tlog(rd.tlog)
    # cut in the middle of the record of a CUR_U sent half-way through the second leg
    mid_tb = sorted(r["time_boot_ms"] for r in log0.legs[1].samples)[len(log0.legs[1].samples) // 2]
    p, cut = 0, None
    for _, m in TlogScanner(data):
        p += 8 + len(m.get_msgbuf())
        if m.get_type() == "NAMED_VALUE_FLOAT" and m.time_boot_ms == mid_tb:
            cut = p - 5
            break
    bad = tmp_path / "cut.tlog"
    bad.write_bytes(data[:cut])
    res = replay(bad, mission=mfile, out=False)
    assert res.log["bad_frames"] == 1 and res.log["skipped_bytes"] == 8 + len(m.get_msgbuf()) - 5
    assert any("damaged" in n for n in res.notes)
    assert len(res.legs) == 2
    assert res.legs[0].path == summary["legs"][0]["path"] and res.legs[0].path_identical
    assert res.legs[0].n_samples == len(log0.legs[0].samples)
    # the second leg is open at the end of the log: said so, about half its samples, its path still replayed
    assert 0 < res.legs[1].n_samples < len(log0.legs[1].samples)
    assert any("ends inside this leg" in n for n in res.legs[1].notes)
    assert res.legs[1].path == summary["legs"][1]["path"]


def test_readings_of_the_store_the_log_does_not_hold_are_counted_in_the_notes(flown, tmp_path):
    """A run directory whose telemetry log ends before its second leg: the store's readings of that leg are not in
    the log, and the replay says how many, by leg."""
    rd, _, _ = flown
    cut = RunDir(tmp_path / "run")
    shutil.copytree(rd.root, cut.root, ignore=shutil.ignore_patterns("replay"))
    data, p = rd.tlog.read_bytes(), 0
    for _, m in TlogScanner(data):
        if m.get_type() == "STATUSTEXT" and str(m.text).startswith("PASST leg 1 tb"):
            break
        p += 8 + len(m.get_msgbuf())
    cut.tlog.write_bytes(data[:p])
    res = replay(cut.root, out=False)
    assert len(res.legs) == 1 and res.reproduced is False
    n1 = len(_store_legs(rd)[1])
    assert n1 > 0 and f"{n1} readings of the run's store not compared with the log: no leg replayed (leg 2: {n1})" in (
        res.notes
    ), res.notes


@pytest.mark.parametrize("seed", [1, 2])
def test_random_bytes_inserted(flown, tmp_path, seed):
    rd, mfile, _summary = flown
    data = bytearray(rd.tlog.read_bytes())
    rng = random.Random(seed)
    ends = _record_ends(bytes(data))
    inserted = 0
    for pos in sorted(rng.sample(ends[:-1], 4), reverse=True):  # junk between records
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(5, 40)))
        data[pos:pos] = junk
        inserted += len(junk)
    bad = tmp_path / "junk.tlog"
    bad.write_bytes(bytes(data))
    res = replay(bad, mission=mfile, out=False)
    assert res.log["bad_frames"] >= 1 and res.log["skipped_bytes"] >= inserted
    full = rebuild_from_tlog(rd.tlog)
    assert len(res.legs) == 2
    # at most the 4 records swallowed with the junk are lost
    lost = sum(len(a.samples) for a in full.legs) - sum(x.n_samples for x in res.legs)
    assert 0 <= lost <= 4


def test_bad_inputs_exit_2(flown, tmp_path, capsys):
    rd, mfile, _ = flown
    (tmp_path / "empty").mkdir()
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(random.Random(0).randrange(256) for _ in range(3000)))
    (tmp_path / "x.bin").write_bytes(b"\xa3\x95\x80")
    cases = [
        [str(tmp_path / "missing")],
        [str(tmp_path / "empty")],
        [str(rd.tlog)],  # a bare log without --mission
        [str(tmp_path / "x.bin"), "--mission", str(mfile)],
        [str(junk), "--mission", str(mfile)],
        [str(rd.root), "--planner", "nope"],
        [str(rd.root), "--reward", "nope"],
        [str(rd.tlog), "--mission", str(tmp_path / "none.yaml")],
    ]
    for argv in cases:
        rc = main(["replay", *argv])
        err = capsys.readouterr().err.strip()
        assert rc == 2, argv
        assert err.count("\n") == 0 and err.startswith("passt-mav: error:"), (argv, err)
    with pytest.raises(ReplayError, match="no vehicle messages"):
        replay(junk, mission=mfile, out=False)


def test_a_run_replays_with_the_gp_bias_it_ran_with():
    """gp.bias became the mission default (issue 27): a run whose recorded config has no ``bias`` ran
    without it and replays without it; a recorded value wins over today's default either way."""
    from passt_mav.analysis.replay import _as_recorded
    from passt_mav.mission.config import BIAS_DEFAULT, load_mission

    cfg = load_mission(Path(__file__).resolve().parents[1] / "missions" / "north_atlantic.yaml")
    assert cfg.gp.bias is True and BIAS_DEFAULT is True
    old_run = {"config": {"gp": {"prior": "forecast", "background": 200}}}
    assert _as_recorded(cfg, old_run).gp.bias is False
    assert _as_recorded(cfg, {"config": {"gp": {"bias": True}}}).gp.bias is True
    assert (
        _as_recorded(
            cfg.model_copy(update={"gp": cfg.gp.model_copy(update={"bias": False})}), {"config": {"gp": {"bias": True}}}
        ).gp.bias
        is True
    )
    assert _as_recorded(cfg, None) is cfg


def test_a_run_replays_with_the_prior_blend_it_ran_with():
    """gp.prior_blend became the mission default "select" (issue 27): a run whose recorded config has no
    ``prior_blend``, or "off", replays with the model-only prior; one recorded with a blend keeps it."""
    from passt_mav.analysis.replay import _as_recorded
    from passt_mav.mission.config import PRIOR_BLEND_DEFAULT, load_mission

    cfg = load_mission(Path(__file__).resolve().parents[1] / "missions" / "north_atlantic.yaml")
    assert cfg.gp.prior_blend == "select" == PRIOR_BLEND_DEFAULT
    assert _as_recorded(cfg, {"config": {"gp": {"bias": True}}}).gp.prior_blend == "off"
    assert _as_recorded(cfg, {"config": {"gp": {"bias": True, "prior_blend": "off"}}}).gp.prior_blend == "off"
    kept = _as_recorded(cfg, {"config": {"gp": {"bias": True, "prior_blend": "select", "prior_share": 0.05}}})
    assert kept is cfg and kept.gp.prior_blend == "select"
    assert _as_recorded(cfg, {"config": {"gp": {"bias": True, "prior_blend": "bma"}}}).gp.prior_blend == "bma"


def test_a_run_replays_with_the_prior_share_it_ran_with():
    """gp.prior_share (issue 27's fixed share, a mission default of 0.05 since): a run recorded without it
    ran without a share and replays so although the mission file now sets one; a recorded share is kept."""
    from passt_mav.analysis.replay import _as_recorded
    from passt_mav.mission.config import PRIOR_SHARE_DEFAULT, load_mission

    cfg = load_mission(Path(__file__).resolve().parents[1] / "missions" / "north_atlantic.yaml")
    assert cfg.gp.prior_share == 0.05 == PRIOR_SHARE_DEFAULT
    assert _as_recorded(cfg, {"config": {"gp": {"bias": True, "prior_blend": "select"}}}).gp.prior_share == 0.0
    unshared = cfg.model_copy(update={"gp": cfg.gp.model_copy(update={"prior_share": 0.0})})
    rec = {"config": {"gp": {"bias": True, "prior_blend": "bma", "prior_share": 0.02}}}
    assert _as_recorded(unshared, rec).gp.prior_share == pytest.approx(0.02)
