"""The run records with a schema: ``leg.json``, ``summary.json`` and one line of ``events.jsonl``.

:class:`LegRecord`, :class:`SummaryRecord` and :class:`EventRecord` are pydantic models of what the
controller writes (:mod:`passt_mav.runs.rundir`, :mod:`passt_mav.runs.live`). Every field is optional
with a default, so a run written before a field existed still loads; keys the models do not name are
kept as they are (``extra="allow"``), so a newer run read by older code loses nothing. A known field
holding the wrong type is refused with one line naming the file and the field (:class:`RunDirError`).

:class:`RunRecords` is the one reader of a run directory's records that the report, the exports, the
live view and the replay share::

    recs = RunRecords.load("runs/2026-05-01T10-00-00Z_ocean")
    recs.summary        # SummaryRecord, None while the first leg runs
    recs.legs           # [LegRecord] of legs/NNN/leg.json, by index
    recs.events         # [EventRecord] of events.jsonl

Clocks and units in the field descriptions: *field time* is the time of the mission's current field
(seconds from its ``time_origin`` for a geographic field, non-dimensional for the cylinder);
*vehicle s* are seconds of the autopilot's clock (``time_boot_ms`` / 1000); *wall s* are seconds of
the controller's computer. RMSEs are in field units (times ``config.field.velocity_scale`` = m/s).
"""

from __future__ import annotations

import json
import logging
from functools import cached_property
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from passt_mav.runs.live import EVENTS, read_jsonl
from passt_mav.runs.rundir import SCHEMA_VERSION, RunDir, RunDirError, read_json

__all__ = [
    "SCHEMA_VERSION",
    "LegRecord",
    "SummaryRecord",
    "EventRecord",
    "RunRecords",
    "parse_record",
    "read_event_records",
    "record_schemas",
    "plain_text",
]

log = logging.getLogger(__name__)


class _Record(BaseModel):
    """Fields every record shares; unknown keys are kept."""

    model_config = ConfigDict(extra="allow", use_attribute_docstrings=True)

    schema_version: int | None = None
    """Version of the record schema the writer followed; absent (null) in runs written before the records had a
    schema."""

    def as_dict(self) -> dict[str, Any]:
        """The record as the JSON object it was read from: the keys it had (defaults not filled in), extra keys
        included, values in the types of the schema."""
        return self.model_dump(exclude_unset=True)


class LegRecord(_Record):
    """One leg: ``legs/NNN/leg.json`` (and ``summary.json`` ``legs[i]``)."""

    index: int = 0
    """Leg index, 0-based, in the order the legs were planned (a fleet counts all boats' legs); the folder NNN."""
    boat: int | None = None
    """A fleet run: the boat (0-based) that flew the leg; absent in a one-boat run."""
    sysid: int | None = None
    """A fleet run: the MAVLink system id of that boat."""
    status: str | None = None
    """``flying`` (planned, uploaded, not finished), ``complete``, ``interrupted``, ``awaiting_approval``,
    ``rejected`` or ``drifted`` (approved after the boat had drifted out of its start cell: planned again)."""
    start_cell: list[int] | None = None
    """Grid cell ``[row, col]`` the leg starts from (row 0 is the southern edge, col 0 the western)."""
    start_latlon: list[float] | None = None
    """The boat's position when the leg was planned, ``[lat, lon]`` in degrees (WGS84)."""
    path: list[list[int]] | None = None
    """The planned grid path, ``[[row, col], ...]``; consecutive cells are 8-neighbours."""
    waypoints: list[list[float]] | None = None
    """The uploaded waypoints, ``[[lat, lon], ...]`` in degrees (WGS84)."""
    waypoint_seqs: list[int] | None = None
    """The mission item sequence number of each waypoint in the uploaded mission."""
    t_start: float | None = None
    """Field time of the leg's start (the state it was planned from)."""
    t_end: float | None = None
    """Field time of the leg's end as planned; once complete, the field time of the estimate after it."""
    t_now: float | None = None
    """Field time when the leg was planned (the vehicle's clock through the run's clock)."""
    t_state: float | None = None
    """Field time of the estimate made from the leg's samples (the leg's last sample)."""
    steps: int | None = None
    """Field snapshots (time steps of ``dt`` field time) the leg spans."""
    forecast_steps_before: int | None = None
    """Field snapshots the state was forecast forward before planning the leg."""
    planning_s: float | None = None
    """Wall s spent planning the leg (forecast, reward map, planner)."""
    planning_timings: dict[str, float] | None = None
    """Wall s of each part of the planning (``predict``, ``reward``, ``plan``)."""
    reward_map: list[list[float]] | None = None
    """The reward map the path was planned on, ``(rows, cols)``, row 0 south; 0 = land or nothing to gain."""
    clock_reading: dict[str, Any] | None = None
    """The vehicle's clock when the leg was planned: ``time_boot_ms`` (vehicle ms) and ``boot`` (0 = first)."""
    planned_arrival_vehicle_s: list[float] | None = None
    """Vehicle s from the leg's start at which the boat should reach each path cell in the forecast current
    (-1: never); null when the leg was timed in still water."""
    planned_ground_speed_m_s: list[float] | None = None
    """Ground speed of each move of the path in the forecast current, m/s; null when timed in still water."""
    planned_duration_vehicle_s: float | None = None
    """Vehicle s the leg was expected to take (the overrun rule's expectation)."""
    upload_s: float | None = None
    """Wall s the mission upload took."""
    upload_tries: int | None = None
    """Upload attempts made (1 = the first went through)."""
    duration_s: float | None = None
    """Wall s from AUTO to the leg's end."""
    duration_vehicle_s: float | None = None
    """Vehicle s from AUTO to the leg's end (flown)."""
    gp_s: float | None = None
    """Wall s of the GP reconstruction after the leg."""
    n_samples: int | None = None
    """Samples the leg's update used (the leg's samples in the store)."""
    n_samples_new: int | None = None
    """Samples stored during this leg."""
    n_gp_points: int | None = None
    """Points the GP was fitted to after thinning."""
    rmse_passt: float | None = None
    """RMSE of the estimate after the leg against the truth at ``t_state``, field units over water cells;
    null when the truth is unknown."""
    rmse_model: float | None = None
    """RMSE of the model alone (from the true state at the mission's start), field units; null when unknown."""
    gp: dict[str, Any] | None = None
    """The GP's fit: noise and nugget std (field units), time-scale factors, prior weights and likelihoods."""
    guard: dict[str, Any] | None = None
    """The guard's record: the loop's and the open-loop forecast's RMSE against the samples (field units and
    ``*_m_s`` in m/s), whether the loop fell behind, its ``message``."""
    calibration: dict[str, Any] | None = None
    """The estimate's posterior std against the truth (coverage95, nlpd, z_rms, reliability); null when unknown."""
    baselines: dict[str, Any] | None = None
    """RMSE of trivial maps (``zero``, ``forecast_mean``) beside the map's (field units) and ``beaten_by``."""
    link: dict[str, Any] | None = None
    """The link during the leg: ``rtt_ms`` (ms), ``loss`` (fraction), ``messages``, ``drops``, ``vehicle_bytes``,
    ``vehicle_bytes_per_s`` (bytes per vehicle s)."""
    readings: dict[str, Any] | None = None
    """The sensor readings of the leg: ``received``, ``used``, ``dropped_gap``, ``missing``, ``fraction_used``,
    ``max_gap_ms`` (vehicle ms), ``lost_in_outages_vehicle_s`` (vehicle s)."""
    outages: list[dict[str, Any]] | None = None
    """Link outages during the leg, each with its UTC start/end and length in vehicle s."""
    overrun: dict[str, Any] | None = None
    """The leg was cut for running over: ``expected_vehicle_s``, ``factor``, ``cut_at_item``, ``items``; null when
    not cut."""
    waits: list[dict[str, Any]] | None = None
    """The boat's waits (HOLD/LOITER) before and during the leg and its drift in them (m)."""
    attempts: list[dict[str, Any]] | None = None
    """Earlier attempts at this leg (interrupted or re-planned), each with its path, start cell and clock."""
    approval: dict[str, Any] | None = None
    """Approve mode: ``distance_m`` (m along the waypoints), ``expected_s`` (vehicle s), the operator's ``answer``."""
    budget_shortened: dict[str, Any] | None = None
    """The safety budget shortened the leg before its upload: the ``path`` flown (grid cells) and why."""
    budget_cut: dict[str, Any] | None = None
    """The safety budget ended the leg in flight: its ``reason`` and the mission item (``at_item``) it was at."""
    operator: dict[str, Any] | None = None
    """The operator ended the leg in flight: ``action`` (``skip`` or ``replan``) and the mission item ``at_item``."""
    fleet_seq: dict[str, Any] | None = None
    """A fleet run: the fleet step at which the leg was planned (``plan``) and absorbed (``absorb``)."""


class SummaryRecord(_Record):
    """The run: ``summary.json`` (rewritten after each leg and at the end)."""

    mission: str | None = None
    """The mission's name."""
    status: str | None = None
    """``running``, ``complete``, ``aborted``, ``stopped``, ``paused``, ``ended``, ``partial`` (a fleet)."""
    started_utc: str | None = None
    """UTC of the run's start, ISO-8601."""
    finished_utc: str | None = None
    """UTC of the run's end, ISO-8601; null while it runs."""
    field: str | None = None
    """The truth/current field: ``builtin:NAME`` or a ``.nc`` path (absolute or relative to the run directory)."""
    field_time_origin: str | None = None
    """UTC of field time 0 (ISO-8601); null for a field without UTC (the cylinder)."""
    grid: dict[str, Any] | None = None
    """The region grid (``RegionGrid.describe()``: corner cell centres in degrees, rows, cols)."""
    model: str | None = None
    """The predictor the run used."""
    model_requested: str | None = None
    """The predictor the mission asked for."""
    model_fallback: str | None = None
    """Why the run fell back from the requested predictor; null when it did not."""
    planner: str | None = None
    """The planner's name."""
    reward: str | None = None
    """The reward map's name."""
    path_length: int | None = None
    """Moves per leg (grid steps)."""
    seeds: dict[str, Any] | None = None
    """Every seed of the run (field, model, planner, sensor, gp)."""
    config: dict[str, Any] | None = None
    """The mission as run (every key, defaults filled in)."""
    legs_planned: int | None = None
    """Legs the run meant to fly (all boats' together in a fleet)."""
    legs: list[LegRecord] | None = None
    """The completed legs' records, as in ``leg.json``."""
    n_samples: int | None = None
    """Samples in the store at the end."""
    readings_used: list[float | None] | None = None
    """Per leg, the fraction of sensor readings that became samples."""
    stopped_by: str | None = None
    """What stopped the run early (a signal, the operator); null when it was not stopped."""
    machine_faults: dict[str, Any] | None = None
    """What the machine failed (not the boat): ``store`` (``reason``, e.g. ``disk full: PATH``;
    ``readings_kept``, ``rescued_from_old_file``, ``spare``: the JSON-lines file ``--resume`` imports) and ``tlog``
    (``frames``, ``bytes``, ``error``: messages the telemetry log could not write); null when nothing failed."""
    sessions: list[dict[str, Any]] | None = None
    """One entry per controller session (a resume adds one): ``started_utc``, ``first_leg``, ``planned`` legs."""
    outages: list[dict[str, Any]] | None = None
    """Every link outage of the run (UTC start/end, vehicle s)."""
    budget: dict[str, Any] | None = None
    """The safety budget's figures (distance m, time vehicle s, used and left); null when no limit was set."""
    end: dict[str, Any] | None = None
    """How the run left the boat (loitering or disarmed) and where."""
    link_vehicle_bytes_per_s: list[float | None] | None = None
    """Per leg, the bytes the vehicle sent per vehicle s."""
    rmse: dict[str, Any] | None = None
    """RMSE over time where the truth is known: ``t`` (field time of each leg's end), ``passt``, ``model`` (field
    units, null = not evaluated), and counterfactual curves (``lawnmower``, ``random``) where computed."""
    rmse_note: str | None = None
    """What the RMSE figures compare."""
    rmse_units: str | None = None
    """The unit of the RMSE figures (field units; times ``config.field.velocity_scale`` = m/s)."""
    pod: dict[str, Any] | None = None
    """Cumulative POD energy fraction of modes 1..k of ``truth``, ``passt`` and ``model``."""
    clock: dict[str, Any] | None = None
    """The run's clock: ``t_boot0`` (field time at the vehicle's boot), ``time_scale`` (vehicle s per field time
    unit), ``source`` (``utc``/``boot``), ``later_boots`` (field time at each later boot)."""
    thinning: str | None = None
    """How samples are thinned before the GP."""
    dt: float | None = None
    """Field time between the field's snapshots."""
    connect: str | list[str] | None = None
    """The MAVLink connection string (a fleet: one per boat)."""
    events: list[str] | None = None
    """The run's notable events, one line of text each (the live view's are in ``events.jsonl``)."""
    boats: list[dict[str, Any]] | None = None
    """A fleet run: per boat ``boat``, ``sysid``, ``connect``, ``status``, ``legs`` (done) and its ``clock``."""
    lost_boats: list[int] | None = None
    """A fleet run: boats that did not finish."""
    counterfactual: dict[str, Any] | None = None
    """The demo's counterfactual RMSE curves (lawnmower, random walks; field units) and how they were made."""
    demo: dict[str, Any] | None = None
    """``passt-mav demo``: the simulator's command line and settings."""


class EventRecord(_Record):
    """One line of ``events.jsonl`` (what the live view shows)."""

    utc: str | None = None
    """UTC when the event was written, ISO-8601 with milliseconds."""
    field_time: float | None = None
    """Field time of the event; null when the vehicle's clock was not known yet."""
    boat: int = 0
    """The boat (0-based) the event is about."""
    kind: str | None = None
    """What happened: one of ``passt_mav.runs.live.KINDS`` (``leg_start``, ``link_lost``, ...)."""
    level: str | None = None
    """``info``, ``ok``, ``warn`` or ``alert`` (the page shows warn and alert as banners)."""
    text: str | None = None
    """The event in words."""
    command_id: str | None = None
    """The operator's command this event answers (``live/commands.jsonl`` ``id``)."""


def _field_path(loc: tuple, data: Any) -> str:
    """``loc`` of a validation error as ``legs[2].t_start``, without the union member names pydantic adds."""
    out = ""
    for part in loc:
        if isinstance(part, int) and isinstance(data, list) and 0 <= part < len(data):
            out, data = f"{out}[{part}]", data[part]
        elif isinstance(part, str) and isinstance(data, dict) and part in data:
            out, data = f"{out}.{part}" if out else part, data[part]
        else:
            break
    return out or "(the record)"


def parse_record(cls: type[_Record], obj: Any, source: str | Path) -> Any:
    """``obj`` (a decoded JSON value) as record ``cls``; :class:`RunDirError` naming ``source`` and the field when
    it does not fit the schema."""
    if not isinstance(obj, dict):
        what = {LegRecord: "leg record", SummaryRecord: "run summary", EventRecord: "event"}.get(cls, cls.__name__)
        raise RunDirError(f"{source} does not hold a {what} (a JSON object)")
    try:
        return cls.model_validate(obj)
    except ValidationError as exc:
        errs = exc.errors(include_url=False)
        fields = list(dict.fromkeys(_field_path(e["loc"], obj) for e in errs))
        first = errs[0]
        got = json.dumps(first.get("input"), default=str)
        got = got if len(got) <= 60 else got[:57] + "..."
        more = f" (also: {', '.join(fields[1:4])}{', ...' if len(fields) > 4 else ''})" if len(fields) > 1 else ""
        raise RunDirError(f"{source}: field {fields[0]!r}: {first['msg'].lower()} (got {got}){more}") from None


def read_event_records(root: str | Path, offset: int = 0, *, strict: bool = True) -> tuple[list[EventRecord], int]:
    """(the events after byte ``offset`` of ``ROOT/events.jsonl``, the new offset): a half-written last line
    waits, a line that is not JSON is skipped (logged); a line that does not fit :class:`EventRecord` raises
    :class:`RunDirError`, or with ``strict=False`` is skipped (logged)."""
    path = Path(root) / EVENTS
    raw, end = read_jsonl(path, offset)
    out = []
    for k, obj in enumerate(raw):
        where = f"line {k + 1}" if offset == 0 else f"event {k + 1} after byte {offset}"
        try:
            out.append(parse_record(EventRecord, obj, f"{path} ({where})"))
        except RunDirError as exc:
            if strict:
                raise
            log.warning("skipped an event: %s", exc)
    return out, end


class RunRecords:
    """The records of one run directory, each read (and checked against its schema) when first asked for.

    ``strict=True`` (the report, the exports, the replay): a record that cannot be read or does not fit its
    schema raises :class:`RunDirError` naming the file and the field. ``strict=False`` (the live view, which
    reads a run while it is written): such a record is left out (logged): the summary is None, the leg or the
    event is skipped.
    """

    def __init__(self, root: str | Path | RunDir, *, strict: bool = True):
        self.rundir = root if isinstance(root, RunDir) else RunDir(root)
        self.strict = strict

    @classmethod
    def load(cls, root: str | Path | RunDir, *, strict: bool = True) -> RunRecords:
        """Read every record now (summary, legs, events); raises :class:`RunDirError` as described above."""
        recs = cls(root, strict=strict)
        _ = recs.summary, recs.legs, recs.events
        return recs

    def _read(self, cls: type[_Record], path: Path, fill: dict[str, Any] | None = None) -> Any:
        try:
            obj = read_json(path)
            if isinstance(obj, dict) and fill:
                obj = {**fill, **obj}
            return parse_record(cls, obj, path)
        except RunDirError as exc:
            if self.strict:
                raise
            log.debug("record left out: %s", exc)
            return None

    @cached_property
    def summary(self) -> SummaryRecord | None:
        """``summary.json``; None when the run has none (yet)."""
        f = self.rundir.summary_file
        return self._read(SummaryRecord, f) if f.exists() else None

    @cached_property
    def legs(self) -> list[LegRecord]:
        """The records of ``legs/NNN/leg.json`` by index (folders without one are skipped; a record without an
        ``index`` takes its folder's)."""
        recs = (self.leg(i) for i in self.rundir.leg_indices())
        return sorted((r for r in recs if r is not None), key=lambda r: r.index)

    def leg(self, i: int) -> LegRecord | None:
        """The record of ``legs/NNN/leg.json`` of leg ``i`` alone (read now), None when it has none."""
        f = self.rundir.leg_file(i)
        return self._read(LegRecord, f, {"index": int(i)}) if f.exists() else None

    @cached_property
    def events(self) -> list[EventRecord]:
        """Every line of ``events.jsonl`` (empty without one)."""
        return read_event_records(self.rundir.root, strict=self.strict)[0]

    def summary_dict(self) -> dict[str, Any] | None:
        """:attr:`summary` as a plain dict (:meth:`LegRecord.as_dict`), None without one."""
        return None if self.summary is None else self.summary.as_dict()

    def leg_dicts(self) -> list[dict[str, Any]]:
        """:attr:`legs` as plain dicts, by index."""
        return [r.as_dict() for r in self.legs]


def record_schemas() -> dict[str, dict[str, Any]]:
    """The JSON Schema of each record, by file: ``leg.json``, ``summary.json``, ``events.jsonl`` (one line); each
    description on one line, its literals in Markdown's single backticks."""
    models: dict[str, type[BaseModel]] = {
        "leg.json": LegRecord,
        "summary.json": SummaryRecord,
        "events.jsonl": EventRecord,
    }
    return {name: _plain(cls.model_json_schema()) for name, cls in models.items()}


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: plain_text(v) if k == "description" else _plain(v) for k, v in x.items()}
    return [_plain(v) for v in x] if isinstance(x, list) else x


def plain_text(text: str) -> str:
    """A docstring as one line of Markdown (``x`` -> `x`)."""
    return " ".join(text.split()).replace("``", "`")
