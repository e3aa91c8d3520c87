"""The run records' schema (passt_mav.runs.records) on a run directory written by today's controller.

One 1-leg mission is flown once per module with the controller's in-process test setup
(tests/test_controller.py: vehicle_sim at 50x, 8x8 grid, greedy planner, persistence model). Its
``summary.json``, ``leg.json`` and ``events.jsonl`` must load through the models with every key kept;
the same directory with ``schema_version`` removed (a run from before the schema) must load too; a
wrong type in a known field is refused with one line naming the file and the field.
"""

from __future__ import annotations

import json
import shutil

import pytest
import test_controller as tc
from mavlink_helpers import served

from passt_mav.analysis.export import load_run as export_load_run
from passt_mav.analysis.report import load_run as report_load_run
from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.runs.records import (
    SCHEMA_VERSION,
    EventRecord,
    LegRecord,
    RunRecords,
    SummaryRecord,
    parse_record,
    record_schemas,
)
from passt_mav.runs.rundir import RunDir, RunDirError
from passt_mav.view.state import RunState


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    """The RunDir of a 1-leg mission flown against the simulator."""
    tmp = tmp_path_factory.mktemp("records")
    field = tc.wave_field()
    cfg = tc.mission(tmp, field, legs=1)
    rd = RunDir(tmp / "run").create()
    with served(tc.sim_config(), field=field, speedup=tc.SPEEDUP, link_kw={"stream_rates_hz": LEAN_STREAMS}) as (
        _sim,
        link,
    ):
        summary = tc.controller(cfg, field, link, rd, echo=None).run()
    assert summary["status"] == "complete" and len(summary["legs"]) == 1
    return rd


def _json(path):
    return json.loads(path.read_text())


def _events(rd):
    return [json.loads(line) for line in (rd.root / "events.jsonl").read_text().splitlines()]


def test_todays_run_loads_with_every_key_kept(flown):
    recs = RunRecords.load(flown)
    raw_summary, raw_leg = _json(flown.summary_file), _json(flown.leg_file(0))
    assert raw_summary["schema_version"] == raw_leg["schema_version"] == SCHEMA_VERSION
    assert all(e["schema_version"] == SCHEMA_VERSION for e in _events(flown))
    assert isinstance(recs.summary, SummaryRecord) and recs.summary.status == "complete"
    (leg,) = recs.legs
    assert isinstance(leg, LegRecord) and leg.index == 0 and leg.status == "complete"
    assert leg.t_end is not None and leg.t_start is not None and leg.t_end > leg.t_start  # field time
    assert leg.duration_vehicle_s is not None and leg.duration_vehicle_s > 0  # vehicle s
    assert [x[0] for x in leg.path] == [c[0] for c in raw_leg["path"]]
    # nothing lost: every key written comes back, equal to what was written
    assert recs.leg_dicts() == [raw_leg]
    assert recs.summary_dict() == raw_summary
    assert [e.as_dict() for e in recs.events] == _events(flown)
    kinds = [e.kind for e in recs.events]
    assert kinds[0] == "leg_start" and "leg_end" in kinds and kinds[-1] == "run_end"
    assert all(isinstance(e, EventRecord) and e.utc for e in recs.events)


def test_every_key_written_today_is_a_field_of_its_model(flown):
    """The models name every key today's writers write (extra keys are kept, but a key the writers add belongs
    in the schema, with its unit)."""
    recs = RunRecords.load(flown)
    assert set(_json(flown.leg_file(0))) <= set(LegRecord.model_fields)
    assert set(_json(flown.summary_file)) <= set(SummaryRecord.model_fields)
    assert {k for e in _events(flown) for k in e} <= set(EventRecord.model_fields)
    assert recs.legs[0].model_extra == {} and recs.summary.model_extra == {}


def test_a_run_without_schema_version_loads(flown, tmp_path):
    old = RunDir(shutil.copytree(flown.root, tmp_path / "old"))
    for f in [old.summary_file, old.leg_file(0)]:
        rec = _json(f)
        rec.pop("schema_version")
        rec["written_by_a_later_version"] = {"kept": [1, 2]}  # an unknown key: kept, not refused
        f.write_text(json.dumps(rec))
    lines = _events(old)
    (old.root / "events.jsonl").write_text(
        "".join(json.dumps({k: v for k, v in e.items() if k != "schema_version"}) + "\n" for e in lines)
    )
    recs = RunRecords.load(old)
    assert recs.summary.schema_version is None and recs.legs[0].schema_version is None
    assert recs.legs[0].model_extra == {"written_by_a_later_version": {"kept": [1, 2]}}
    assert recs.leg_dicts()[0]["written_by_a_later_version"] == {"kept": [1, 2]}
    assert len(recs.events) == len(lines) and recs.events[0].schema_version is None
    # the readers built on the records take it as they take today's
    assert report_load_run(old.root).legs[0]["index"] == 0
    assert export_load_run(old.root).legs[0]["status"] == "complete"
    assert RunState(old.root).snapshot()["legs"][0]["status"] == "complete"


def test_a_bare_old_leg_record_loads_with_defaults(tmp_path):
    """A leg record with none of today's keys (a run from long ago): every field takes its default."""
    rd = RunDir(tmp_path / "r").create()
    rd.leg_dir(4)
    rd.leg_file(4).write_text(json.dumps({"path": [[0, 0], [1, 1]]}))
    (leg,) = RunRecords.load(rd).legs
    assert leg.index == 4 and leg.status is None and leg.rmse_passt is None and leg.boat is None
    assert RunRecords.load(rd).summary is None and RunRecords.load(rd).events == []


def test_a_wrong_type_in_a_known_field_is_one_clear_error(flown, tmp_path):
    bad = RunDir(shutil.copytree(flown.root, tmp_path / "bad"))
    rec = _json(bad.leg_file(0))
    rec["t_start"] = "noon"
    bad.leg_file(0).write_text(json.dumps(rec))
    with pytest.raises(RunDirError) as err:
        RunRecords.load(bad)
    msg = str(err.value)
    assert len(msg.splitlines()) == 1
    assert msg.startswith(f"{bad.leg_file(0)}: field 't_start': ") and "valid number" in msg and '"noon"' in msg
    # the same error from export and replay's readers; the live view leaves the leg out and goes on
    with pytest.raises(RunDirError, match="field 't_start'"):
        export_load_run(bad.root)
    assert RunState(bad.root).snapshot()["legs"] == []


def test_a_wrong_type_deep_in_the_summary_names_its_path():
    with pytest.raises(RunDirError, match=r"^summary.json: field 'legs\[1\]\.path\[0\]\[1\]': .*\(got \"x\"\)$"):
        parse_record(SummaryRecord, {"legs": [{}, {"path": [[0, "x"]]}]}, "summary.json")
    with pytest.raises(RunDirError, match="^leg.json does not hold a leg record"):
        parse_record(LegRecord, [1, 2], "leg.json")


def test_every_field_is_described_with_its_unit_where_it_has_one():
    for name, schema in record_schemas().items():
        for key, prop in schema["properties"].items():
            assert prop.get("description"), f"{name}: {key} has no description"
    leg = LegRecord.model_fields
    assert "field time" in leg["t_start"].description.lower()
    assert (
        "vehicle s" in leg["duration_vehicle_s"].description.lower()
        and "wall s" in leg["duration_s"].description.lower()
    )
    assert "m/s" in leg["planned_ground_speed_m_s"].description
