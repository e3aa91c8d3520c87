"""Replay a mission from its telemetry log: rebuild every leg and recompute every decision offline.

``replay(source)`` takes a run directory (``passt-mav run``/``demo``) or a bare
``.tlog`` plus the mission file, and

1. rebuilds the mission from the telemetry log alone: per leg the position and
   vehicle time the controller planned from, the samples it collected, the
   waypoints it uploaded. Samples are rebuilt by feeding the logged frames, in
   order, through the controller's own :class:`~passt_mav.mavlink.SampleCollector`
   (so the pairing of CUR_U/CUR_V with positions is the controller's, not an
   approximation of it). Leg windows follow the controller's: a leg's samples are
   those emitted between the GCS's switch to AUTO and the controller's mark of the
   leg's end (:func:`~passt_mav.runs.legs.leg_statustext`; in logs without marks its
   next mode command, HOLD). The wait of an operator's Pause, marked too, stays in the
   leg, as in the controller's store;
2. re-runs the between-leg step offline with the controller's own code,
   :class:`~passt_mav.loop.legstep.LegStep` (``plan`` / ``absorb``), legs in order through one
   loop (its GP hyper-parameters, posterior std and planner seed carry from leg to leg
   exactly as in the controller);
3. compares leg by leg: the re-planned grid path against the recorded one
   (``leg.json``, or for a bare tlog the uploaded waypoints expanded back into
   cells), the RMSE figures against ``summary.json``.

With ``model``/``planner``/``reward`` overrides it is a counterfactual: the same
legs and samples, planned with another choice (the samples are still the ones the
vehicle collected on its real path: a counterfactual path's reward is collected on
the replayed forecast, its RMSE uses the real samples).

The clock. The controller sends, right before planning a leg, a STATUSTEXT with the
vehicle clock reading it planned from and the snapshots it forecast before planning
(:func:`~passt_mav.runs.legs.clock_statustext`); the replay uses it. Logs of older
controllers lack it: the reading is then only bracketed by the log (between the previous
leg's end and the upload). For a run directory the recorded ``forecast_steps_before`` is
used (and checked against the log's bracket); for a bare log every value in the bracket
is tried and the one whose plan is the uploaded path is kept (said in the leg's notes).
The start cell likewise: ``leg.json``'s, else the first uploaded waypoint's.

A bare ArduPilot DataFlash ``.bin`` (the autopilot's own log; ``--mission`` needed) is
replayed the same way, its legs rebuilt by
:func:`~passt_mav.runs.dataflash_legs.rebuild_from_dataflash` (mission blocks, mode
changes, the clock STATUSTEXT as a MSG, NVF readings with POS/GPS positions).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from passt_mav.errors import UserError
from passt_mav.runs.legs import LoggedLeg, LogRebuild, rebuild_from_tlog  # noqa: F401 - re-exported
from passt_mav.units import SpeedUnit, speed_unit

__all__ = ["ReplayError", "ReplayLeg", "ReplayResult", "waypoints_to_path", "replay"]


class ReplayError(UserError):
    """The replay's input is missing, not a run, or does not hold what a replay needs."""


def waypoints_to_path(grid, waypoints) -> np.ndarray | None:
    """(L+1, 2) grid path from merged waypoints (the inverse of :func:`geo.path_to_waypoints`).

    Waypoints are the corners of straight 8-neighbour runs, so each segment expands
    exactly into unit steps. None if a segment is not a straight 8-direction run.
    """
    wp = np.asarray(waypoints, float).reshape(-1, 2)
    if len(wp) == 0:
        return None
    r, c = grid.latlon_to_cell(wp[:, 0], wp[:, 1], clip=True)
    cells = np.column_stack([np.asarray(r, int).reshape(-1), np.asarray(c, int).reshape(-1)])
    out = [cells[0]]
    for a, b in itertools.pairwise(cells):
        d = b - a
        n = int(max(abs(d[0]), abs(d[1])))
        if n == 0:
            continue
        if d[0] and d[1] and abs(d[0]) != abs(d[1]):
            return None
        step = np.sign(d)
        out.extend(a + step * k for k in range(1, n + 1))
    return np.array(out, int)


def _clock_bracket(lg, clock, t_state: float, dt: float) -> list[int]:
    """Forecast steps the controller may have taken before planning ``lg`` (see :class:`LoggedLeg`)."""
    k_lo = max(0, int(round((float(clock.field_time(lg.t_lo_ms)) - t_state) / dt)))
    k_hi = max(k_lo, int(round((float(clock.field_time(lg.t_now_ms)) - t_state) / dt)))
    return list(range(k_lo, k_hi + 1))


def _search_clock(step, clock, state, t_state, legs, starts, paths, budget: int = 200):
    """Forecast steps per leg such that every leg's plan is its uploaded path (depth first).

    For logs without the controller's clock STATUSTEXT. A wrong choice on one leg can still
    plan the same path but leaves another state, which shows on a later leg: hence the
    search over the whole sequence. Returns a list (one per leg, None where nothing
    matched) or None when the budget of plans ran out.
    """
    import copy

    left = [budget]

    def dfs(i, st_, x, ts):
        if i == len(legs):
            return []
        cands = _clock_bracket(legs[i], clock, ts, st_.dt)
        mid = (cands[0] + cands[-1]) / 2
        cands.sort(key=lambda c: abs(c - mid))
        for cand in cands:
            if left[0] <= 0:
                return None
            left[0] -= 1
            planned = st_.plan(i, x, ts, starts[i], k=cand)
            if paths[i] is not None and planned.plan.path.tolist() != paths[i]:
                continue
            nxt = copy.deepcopy(st_, {id(st_.loop.predictor): st_.loop.predictor, id(st_.field): st_.field})
            ab = nxt.absorb(planned, legs[i].samples, clock, strict=False)
            rest = dfs(i + 1, nxt, ab.state, ab.t_state)
            if rest is not None:
                return [cand] + rest
        return None

    return dfs(
        0,
        copy.deepcopy(step, {id(step.loop.predictor): step.loop.predictor, id(step.field): step.field}),
        state,
        t_state,
    )


# -- results --------------------------------------------------------------------------------------
@dataclass
class ReplayLeg:
    """Replay of one leg. Paths are lists of [row, col]; RMSE in field units (None = not known)."""

    index: int
    n_samples: int
    n_gp_points: int
    start_cell: list[int]
    t_start: float
    steps: int
    forecast_steps_before: int
    path: list[list[int]]
    recorded_path: list[list[int]] | None
    path_identical: bool | None
    differing_cells: list[dict]
    reward_collected: float
    rmse_passt: float | None
    rmse_model: float | None
    rmse_passt_recorded: float | None = None
    rmse_model_recorded: float | None = None
    rmse_identical: bool | None = None
    notes: list[str] = field(default_factory=list)


@dataclass
class ReplayResult:
    """Replay of a run: per-leg results, what the log reader skipped, and the verdict.

    ``reproduced``: every leg's path equals the recorded one and every recorded RMSE is
    matched within ``rmse_tol`` (None for a counterfactual, which is not expected to).
    ``first_divergence``: index of the first leg that differs, or None.
    """

    source: str
    kind: str
    counterfactual: dict[str, str]
    legs: list[ReplayLeg]
    log: dict[str, Any]
    reproduced: bool | None
    first_divergence: int | None
    rmse_tol: float
    settings: dict[str, Any]
    out_dir: str | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        """0 reproduced or counterfactual, 1 diverged with the run's own settings."""
        return 1 if self.reproduced is False else 0

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["exit_code"] = self.exit_code
        return d


# -- replay ---------------------------------------------------------------------------------------
def _load_config(mission, summary: dict | None, rd) -> tuple[Any, str]:
    """The mission to replay with, and where it came from; a run's own GP settings as it ran them."""
    cfg, src = _mission_of(mission, summary, rd)
    return (cfg if mission is not None else _as_recorded(cfg, summary)), src


def _as_recorded(cfg, summary: dict | None):
    """``cfg`` with ``gp.bias``, ``gp.prior_blend`` and ``gp.prior_share`` as the run resolved them (summary.json ``config``):
    a default that changed since (both became mission defaults later) must not make an older run's
    replay diverge. A run whose recorded config lacks one ran before it was a mission default: ``bias``
    off, ``prior_blend`` "off", ``prior_share`` 0 (the key came with the fixed share); one whose planner
    lacks ``current_aware`` planned every move as in still water: ``current_aware`` false."""
    from passt_mav.loop.passt import PRIOR_BLENDS

    recorded = (summary or {}).get("config")
    if not isinstance(recorded, dict) or not isinstance(recorded.get("gp"), dict):
        return cfg
    as_run = {
        "bias": bool(recorded["gp"].get("bias", False)),
        "prior_blend": recorded["gp"].get("prior_blend", "off"),
        "prior_share": float(recorded["gp"].get("prior_share", 0.0) or 0.0),
    }
    if as_run["prior_blend"] not in PRIOR_BLENDS:
        as_run["prior_blend"] = "off"
    changed = {k: v for k, v in as_run.items() if getattr(cfg.gp, k) != v}
    cfg = cfg if not changed else cfg.model_copy(update={"gp": cfg.gp.model_copy(update=changed)})
    planner = recorded.get("planner")
    if isinstance(planner, dict) and "current_aware" not in planner and cfg.planner.current_aware:
        # a run from before legs were planned in the current timed every move as in still water
        cfg = cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"current_aware": False})})
    return cfg


def _mission_of(mission, summary: dict | None, rd) -> tuple[Any, str]:
    from passt_mav.mission.config import load_mission, validate_mission

    if mission is not None:
        p = Path(mission)
        if not p.is_file():
            raise ReplayError(f"mission file not found: {p}")
        return load_mission(p), str(p)
    if rd is not None and rd.mission_file.is_file():
        return load_mission(rd.mission_file), str(rd.mission_file)
    if summary and isinstance(summary.get("config"), dict):
        return validate_mission(summary["config"], source=f"{rd.summary_file}:config"), f"{rd.summary_file}:config"
    raise ReplayError(
        "no mission: the run directory has neither mission.yaml nor a config in summary.json; pass --mission M.yaml"
    )


def _diff_paths(rec, new) -> list[dict]:
    rec = [list(map(int, x)) for x in rec]
    new = [list(map(int, x)) for x in new]
    out = []
    for k in range(max(len(rec), len(new))):
        a = rec[k] if k < len(rec) else None
        b = new[k] if k < len(new) else None
        if a != b:
            out.append({"step": k, "recorded": a, "replayed": b})
    return out


def replay(
    source,
    *,
    out=None,
    model: str | None = None,
    planner: str | None = None,
    reward: str | None = None,
    mission=None,
    rmse_tol: float = 1e-6,
    echo=None,
    progress: bool = False,
) -> ReplayResult:
    """Replay ``source`` (run directory, or ``.tlog`` with ``mission``); see the module docstring.

    Args:
        source: run directory or telemetry log path.
        out: directory for ``replay.json`` (default ``RUN_DIR/replay``, or ``FILE.replay/`` beside a log);
            ``False`` writes nothing.
        model, planner, reward: counterfactual choices (predictor spec, planner name, reward name).
        mission: mission file (required for a bare log; overrides the run's own otherwise).
        rmse_tol: largest |recorded - replayed| RMSE still counted as reproduced.
        progress: show the legs' progress on stderr (:mod:`passt_mav.progress`).

    Raises:
        ReplayError / UserError: bad input (the CLI prints one line, exit 2).
    """
    say = echo or (lambda s: None)
    inp = _open_source(Path(source), mission)
    cfg, mission_src = _load_config(mission, inp.summary, inp.rd)
    cfg, cf = _counterfactual(cfg, model, planner, reward)
    setup = _build_setup(cfg, mission_src, inp, cf, say)
    if inp.kind == "fleet":
        if cf:
            raise ReplayError("counterfactual replays (--model/--planner/--reward) of a fleet run are not supported")
        result = _fleet_result(inp, setup, rmse_tol, say)
    else:
        result = _LogReplay(inp, setup, cf, rmse_tol, say).result(progress)
    return _write_result(result, out, inp.rd, inp.src)


# -- inputs ---------------------------------------------------------------------------------------
@dataclass
class _Source:
    """What a replay reads: ``src`` as given; ``kind`` "run", "fleet", "tlog" or "dataflash"; ``tlog`` the log
    to rebuild (a fleet's first boat log); for a run directory its :class:`RunDir` and summary.json (None if
    it has none)."""

    src: Path
    kind: str
    tlog: Path
    rd: Any = None
    summary: dict | None = None


def _open_source(src: Path, mission) -> _Source:
    """The replay's input from ``source``: a run directory, or a bare ``.tlog``/``.bin`` (which needs ``mission``)."""
    if not src.exists():
        raise ReplayError(f"replay source not found: {src}")
    if src.is_dir():
        return _run_dir_source(src)
    if src.suffix.lower() not in (".tlog", ".bin"):
        raise ReplayError(f"{src}: expected a run directory, a .tlog or an ArduPilot DataFlash .bin file")
    if mission is None:
        raise ReplayError(f"replaying a bare log needs --mission M.yaml (region, model, planner): {src}")
    return _Source(src, "dataflash" if src.suffix.lower() == ".bin" else "tlog", src)


def _run_dir_source(src: Path) -> _Source:
    """A run directory's log (a fleet's boat logs) and summary.json, checked to hold what a replay needs."""
    from passt_mav.runs.records import RunRecords
    from passt_mav.runs.rundir import RunDir, RunDirError

    rd = RunDir(src)
    if not rd.is_run_dir():
        raise ReplayError(f"{src} is not a run directory")
    fleet_logs = rd.boat_tlogs()
    if not rd.tlog.is_file() and not fleet_logs:
        raise ReplayError(f"{rd.tlog} not found: the run has no telemetry log to replay")
    try:
        summary = RunRecords(rd).summary_dict()
    except RunDirError as exc:
        raise ReplayError(str(exc)) from None
    kind = "fleet" if fleet_logs else "run"
    if kind == "fleet" and not (summary or {}).get("boats"):
        raise ReplayError(f"{src}: a fleet run (flight_boatN.tlog) needs its summary.json (the boats' clocks)")
    return _Source(src, kind, rd.tlog if not fleet_logs else fleet_logs[0], rd, summary)


def _counterfactual(cfg, model: str | None, planner: str | None, reward: str | None) -> tuple[Any, dict[str, str]]:
    """``cfg`` with the counterfactual choices applied, and those choices (empty: replay as the run ran)."""
    from passt_mav.planning import PLANNERS, REWARDS

    if planner is not None and planner not in PLANNERS:
        raise ReplayError(f"unknown planner {planner!r}; choose one of {', '.join(PLANNERS)}")
    if reward is not None and reward not in REWARDS:
        raise ReplayError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
    cf = {k: v for k, v in (("model", model), ("planner", planner), ("reward", reward)) if v is not None}
    if not cf:
        return cfg, cf
    upd: dict[str, Any] = {}
    if "model" in cf:
        upd["model"] = model
    if planner is not None or reward is not None:
        pl = {"name": planner or cfg.planner.name, "reward": reward or cfg.planner.reward}
        if planner is not None and planner != cfg.planner.name:
            pl["options"] = {}  # the run's planner options belong to its planner
        upd["planner"] = cfg.planner.model_copy(update=pl)
    return cfg.model_copy(update=upd), cf


@dataclass
class _Setup:
    """The controller rebuilt offline: the mission ``cfg`` replayed (counterfactual applied) and where it came
    from, its ``field``, the vehicle-to-field ``clock``, the between-leg ``step`` and the predictor's info
    (``pinfo["used"]``: the model it runs)."""

    cfg: Any
    mission_src: str
    field: Any
    clock: Any
    step: Any
    pinfo: dict

    def settings(self) -> dict[str, Any]:
        """The settings a replay reports (mission, model, planner, reward, path length), in that order."""
        return {
            "mission": self.mission_src,
            "model": self.pinfo.get("used"),
            "planner": self.cfg.planner.name,
            "reward": self.cfg.planner.reward,
            "path_length": self.cfg.planner.path_length,
            # the legs' RMSEs here are in field units; times this is m/s (passt_mav.units)
            "velocity_scale": float(self.cfg.field.velocity_scale),
        }

    def unit(self) -> SpeedUnit:
        """How the replay shows RMSEs: m/s (the mission's ``field.velocity_scale``)."""
        return speed_unit(self.cfg.field.velocity_scale)


def _build_setup(cfg, mission_src: str, inp: _Source, cf: dict, say) -> _Setup:
    """Field, predictor, clock and :class:`~passt_mav.loop.legstep.LegStep` as the run had them (the model it fell
    back to, its clock from summary.json, else the mission's start time and time scale)."""
    from passt_mav.fields.datasets import mission_field
    from passt_mav.loop.legstep import LegStep, build_loop, build_predictor

    summary = inp.summary
    field = mission_field(cfg, _field_source(cfg, inp.rd))  # the same rule as plan and run
    if field.n_times < 2:
        raise ReplayError("the mission's field needs at least 2 snapshots (dt)")
    spec = cfg.model
    if summary and not cf.get("model") and summary.get("model") and summary.get("model_fallback"):
        spec = summary["model"]  # the run fell back (e.g. to dmd): replay what it used
    predictor, pinfo = build_predictor(spec, field, echo=say)
    clock = _field_clock((summary or {}).get("clock") or {}, field.times[cfg.t0], cfg.field.time_scale)
    loop = build_loop(cfg, predictor, field.grid, land=field.land_mask)
    step = LegStep(cfg, field, loop, truth_known=summary is None or summary.get("rmse") is not None)
    return _Setup(cfg, mission_src, field, clock, step, pinfo)


def _field_source(cfg, rd) -> str:
    """The mission's field source; a relative file path resolved against the run directory where it exists."""
    base = None if rd is None else rd.root
    fsrc = cfg.field.source
    if base is not None and not str(fsrc).startswith("builtin:") and not Path(fsrc).is_absolute():
        fsrc = str(base / fsrc) if (base / fsrc).exists() else fsrc
    return fsrc


def _field_clock(clk: dict, t_boot0, time_scale):
    """:class:`~passt_mav.loop.legstep.FieldClock` from a summary.json ``clock`` record (``t_boot0``: field time s at
    the vehicle's boot, ``time_scale``: field s per vehicle s, ``later_boots``), the defaults where it has none."""
    from passt_mav.loop.legstep import FieldClock

    return FieldClock(
        float(clk.get("t_boot0", t_boot0)),
        float(clk.get("time_scale", time_scale)),
        later_boots=tuple(float(x) for x in clk.get("later_boots") or ()),
    )


def _read_log(inp: _Source, cfg):
    """The legs rebuilt from the source's telemetry or DataFlash log (a reader's error as a :class:`ReplayError`)."""
    from passt_mav.runs.tlog import LogReadError

    try:
        if inp.kind == "dataflash":
            from passt_mav.runs.dataflash_legs import rebuild_from_dataflash

            return rebuild_from_dataflash(inp.tlog, u_name=cfg.sensors.u, v_name=cfg.sensors.v)
        return rebuild_from_tlog(inp.tlog, u_name=cfg.sensors.u, v_name=cfg.sensors.v)
    except LogReadError as exc:
        raise ReplayError(str(exc)) from None


def _recorded_legs(rd) -> dict[int, dict]:
    """The run directory's leg records by leg index (none for a bare log)."""
    from passt_mav.runs.records import RunRecords
    from passt_mav.runs.rundir import RunDirError

    if rd is None:
        return {}
    try:
        return {r["index"]: r for r in RunRecords(rd).leg_dicts()}
    except RunDirError as exc:
        raise ReplayError(str(exc)) from None


def _stored_samples(rd, notes: list[str] | None = None) -> dict[int, set]:
    """The run's sample store by leg: sets of (time_boot_ms, lat, lon, u, v); empty without a store, or with a
    damaged one (said in ``notes``: the replay then rests on the log alone, which is what it rebuilds from)."""
    import sqlite3

    from passt_mav.runs.store import SampleStoreError

    store_legs: dict[int, set] = {}
    if rd is not None and rd.samples_db.is_file():
        from passt_mav.runs.store import SampleStore

        try:
            st = SampleStore(rd.samples_db, readonly=True)
            try:
                for x in st.all():
                    store_legs.setdefault(int(x.leg), set()).add((int(x.time_boot_ms), x.lat, x.lon, x.u, x.v))
            finally:
                st.close()
        except (SampleStoreError, sqlite3.DatabaseError) as exc:
            if notes is not None:
                notes.append(f"damaged run: {rd.SAMPLES} unreadable ({exc}); replayed from the telemetry log alone")
            return {}
    return store_legs


def _log_notes(log) -> list[str]:
    """What the log reader had to skip, and a log without legs."""
    notes: list[str] = []
    if log.bad_frames:
        notes.append(
            f"the log is damaged: {log.bad_frames} bad stretch(es), {log.skipped_bytes} byte(s) skipped; "
            "replayed what was readable"
        )
    if not log.legs:
        notes.append("no leg (upload followed by AUTO) found in the log")
    return notes


def _log_info(path, logs) -> dict[str, Any]:
    """The log reader's account: ``path``, and messages, damaged stretches, skipped bytes, bytes and samples
    outside any leg summed over ``logs``."""
    return {
        "path": path,
        "n_messages": sum(x.n_messages for x in logs),
        "bad_frames": sum(x.bad_frames for x in logs),
        "skipped_bytes": sum(x.skipped_bytes for x in logs),
        "n_bytes": sum(x.n_bytes for x in logs),
        "samples_outside_legs": sum(x.n_samples_outside_legs for x in logs),
    }


# -- leg by leg -----------------------------------------------------------------------------------
def _cell_of(grid, latlon) -> tuple[int, int]:
    """The grid cell (row, col) holding ``latlon`` (deg), clipped to the grid."""
    r, c = grid.latlon_to_cell(latlon[0], latlon[1], clip=True)
    return int(r), int(c)


def _uploaded_path(grid, lg) -> tuple[list[list[int]] | None, tuple[int, int]]:
    """The leg's uploaded waypoints expanded into a grid path (None if they do not expand) and the cell the
    controller planned from: the path's first, else the cell of the leg's start position."""
    p = waypoints_to_path(grid, lg.waypoints)
    path = None if p is None else p.tolist()
    return path, (tuple(path[0]) if path else _cell_of(grid, lg.start_latlon))


def _rmse_match(pairs, tol: float) -> bool:
    """Every (recorded, replayed) RMSE pair matches within ``tol``; a recorded None matches anything."""
    return all(a is None or (b is not None and abs(a - b) <= tol) for a, b in pairs)


def _progress_line(label: str, n_samples: int, same: bool | None, rmse: float | None, unit: SpeedUnit) -> str:
    """The one line a replay prints per leg: samples, path verdict, replayed RMSE (field units, shown in
    ``unit``: m/s for a mission)."""
    verdict = "identical" if same else "differs" if same is False else "?"
    return f"{label}: {n_samples} samples, path {verdict}" + (
        "" if rmse is None else f", RMSE {unit.text(rmse, '.6f')}"
    )


def _skipped_leg(lg) -> ReplayLeg:
    """A leg the log gives no position or vehicle time before the upload for: not replayed."""
    return ReplayLeg(
        index=lg.index,
        n_samples=len(lg.samples),
        n_gp_points=0,
        start_cell=[],
        t_start=float("nan"),
        steps=0,
        forecast_steps_before=0,
        path=[],
        recorded_path=None,
        path_identical=None,
        differing_cells=[],
        reward_collected=0.0,
        rmse_passt=None,
        rmse_model=None,
        notes=["no position or vehicle time before the upload: leg skipped"],
    )


def _replay_model_update(loop, rec: dict | None) -> None:
    """A leg whose run updated the model online (``leg.json`` ``gp.model_update``) takes the recorded number of
    gradient steps: a budget in seconds would take as many as this machine manages, and decide differently."""
    mu = ((rec or {}).get("gp") or {}).get("model_update")
    online = getattr(loop, "online", None)
    if online is not None and mu is not None:
        online.replay_steps[loop.leg_index] = int(mu["steps"])


class _LogReplay:
    """Replay of one log (a run directory's, a bare tlog or DataFlash log): its legs in order through the
    setup's :class:`~passt_mav.loop.legstep.LegStep`, the GP state carried from leg to leg."""

    def __init__(self, inp: _Source, setup: _Setup, cf: dict[str, str], rmse_tol: float, say):
        self.inp, self.setup, self.cf, self.rmse_tol, self.say = inp, setup, cf, rmse_tol, say
        self.grid = setup.field.grid
        self.dt = float(setup.field.dt)
        self.recorded: dict[int, dict] = {}
        self.store_legs: dict[int, set] = {}
        self.compared: set[int] = set()  # the legs whose store samples were compared with the log's
        self.chosen: list | None = None

    def result(self, progress: bool) -> ReplayResult:
        """Read the log, replay its legs, compare them with the run's records."""
        log = _read_log(self.inp, self.setup.cfg)
        self.recorded = _recorded_legs(self.inp.rd)
        notes = _log_notes(log)
        self.store_legs = _stored_samples(self.inp.rd, notes)
        state, t_state = self.setup.step.initial_state()
        # what the controller computes from the initial state before its first leg (the model background's
        # roll-out, the information reward's prior), from the same state: planning the first leg from a
        # forecast state instead would roll the background out from that one
        self.setup.step.prepare(state)
        if self.inp.rd is None:
            self.chosen = self._search_clocks(log, state, t_state, notes)
        legs, first_div = self._replay_legs(log, state, t_state, progress)
        notes.extend(_store_notes(self.store_legs, self.compared, log.n_samples_outside_legs))
        reproduced, first_div = self._verdict(legs, first_div, notes)
        return ReplayResult(
            source=str(self.inp.src),
            kind=self.inp.kind,
            counterfactual=self.cf,
            legs=legs,
            log=_log_info(str(self.inp.tlog), [log]),
            reproduced=reproduced,
            first_divergence=None if self.cf else first_div,
            rmse_tol=float(self.rmse_tol),
            settings={
                **self.setup.settings(),
                "clock": self.setup.clock.describe(),
                "field": str(self.setup.cfg.field.source),
            },
            notes=notes,
        )

    def _search_clocks(self, log, state, t_state, notes: list[str]) -> list | None:
        """For a bare log of a controller without the clock STATUSTEXT: the forecast steps per leg whose plans
        are the uploaded paths (:func:`_search_clock`); None when not needed, or not found (then a note)."""
        usable = [lg for lg in log.legs if lg.start_latlon is not None and lg.t_now_ms is not None]
        if not (usable and len(usable) == len(log.legs) and any(lg.clock is None for lg in usable)):
            return None
        uploaded = [_uploaded_path(self.grid, lg) for lg in usable]
        paths, starts = [p for p, _ in uploaded], [s for _, s in uploaded]
        chosen = _search_clock(self.setup.step, self.setup.clock, state, t_state, usable, starts, paths)
        if chosen is None:
            notes.append(
                "no sequence of clock readings in the log's brackets reproduces every uploaded path; "
                "each leg takes the first that reproduces its own"
            )
        return chosen

    def _replay_legs(self, log, state, t_state, progress: bool) -> tuple[list[ReplayLeg], int | None]:
        """Every leg in order until one the log cannot place (the state after it is unknown); the first that
        differs from its record.

        A leg the controller planned more than once (it was stopped in flight and the run resumed: the log
        holds the leg's clock STATUSTEXT once per attempt) is replayed per attempt: an interrupted attempt is
        planned from the same state and compared with its record (``leg.json``'s ``attempts``), and absorbs
        nothing; the last attempt absorbs the samples of every attempt, as the resumed controller did (its
        store keeps them all under the leg)."""
        from passt_mav.progress import progress as _progress

        logged = [(lg.index if lg.planned_index is None else int(lg.planned_index), lg) for lg in log.legs]
        last = {key: n for n, (key, _) in enumerate(logged)}
        restarts = self._session_starts([key for key, _ in logged])
        earlier: dict[int, list] = {}
        legs: list[ReplayLeg] = []
        first_div = None
        for n, (key, lg) in enumerate(_progress(logged, "replay", "leg", quiet=not progress, every_pct=1)):
            if lg.start_latlon is None or lg.t_now_ms is None:
                legs.append(_skipped_leg(lg))
                if not self.cf and first_div is None:
                    first_div = key
                break  # the state after it is unknown
            if n in restarts:  # the run was resumed here: the controller started again from the leg's records
                state, t_state = self._restart(restarts[n])
            tries = len(earlier.get(key, []))
            if n != last[key]:  # an interrupted attempt: planned, never absorbed
                leg, _, _ = self._replay_leg(lg, state, t_state, key=key, attempt=tries)
                earlier.setdefault(key, []).append(lg)
            else:
                if tries:
                    lg = dataclasses.replace(lg, samples=[x for a in earlier[key] for x in a.samples] + lg.samples)
                leg, state, t_state = self._replay_leg(lg, state, t_state, key=key)
            legs.append(leg)
            if first_div is None and (leg.path_identical is False or leg.rmse_identical is False):
                first_div = key
        return legs, first_div

    def _verdict(
        self, legs: list[ReplayLeg], first_div: int | None, notes: list[str]
    ) -> tuple[bool | None, int | None]:
        """(reproduced, first divergence): None for a counterfactual; a run whose records hold more legs than
        the log is not reproduced."""
        missing = self.inp.rd is not None and len(self.recorded) > len(legs)
        if missing:
            notes.append(f"{len(self.recorded)} legs recorded, {len(legs)} rebuilt from the log")
        if self.cf:
            return None, first_div
        reproduced = first_div is None and bool(legs) and all(x.path_identical is not False for x in legs)
        if missing:
            reproduced = False
            if first_div is None:
                first_div = len(legs)
        return reproduced, first_div

    def _session_starts(self, keys: list[int]) -> dict[int, int]:
        """Where in the log's legs (``keys``: the controller's leg numbers in log order) a resumed controller
        session began, and at which leg: from summary.json's ``sessions`` (the legs each planned), when they
        account for the log's legs exactly; else none (the replay runs through, as one session)."""
        sessions = (self.inp.summary or {}).get("sessions") or []
        if len(sessions) < 2 or [k for s in sessions for k in s.get("planned", [])] != keys:
            return {}
        out, n = {}, 0
        for s in sessions[:-1]:
            n += len(s.get("planned", []))
            out[n] = None
        for pos, s in zip(sorted(out), sessions[1:]):
            out[pos] = int(s["first_leg"])
        return out

    def _restart(self, first: int):
        """A controller resumed at leg ``first``: a new between-leg step (its loop as a new controller builds
        it), the state of leg ``first - 1``'s ``estimate.nc`` (or the mission's start), prepared from it.
        Returns (state, t_state)."""
        from passt_mav.fields.field import load_field
        from passt_mav.loop.legstep import LegStep, build_loop

        old, field = self.setup.step, self.setup.field
        # the model as loaded (a resumed controller loads it anew: an online update is not carried over)
        loop = build_loop(self.setup.cfg, old.loop.initial_predictor, field.grid, land=field.land_mask)
        step = self.setup.step = LegStep(self.setup.cfg, field, loop, truth_known=old.truth_known)
        if first == 0:
            state, t_state = step.initial_state()
        else:
            est = self.inp.rd.estimate_file(first - 1)
            if not est.exists():
                raise ReplayError(f"{est} is missing: the run resumed from it")
            state = np.array(load_field(est).data[0], dtype=np.float32)
            t_state = float(self.recorded[first - 1]["t_state"])
            step.resume_after(first, t_state)  # as the resumed controller
        step.prepare(state)
        return state, t_state

    def _replay_leg(self, lg, state, t_state, *, key: int | None = None, attempt: int | None = None):
        """Plan and absorb one leg from ``state`` (field time ``t_state`` s); (its replay, the state after it).

        ``key``: the controller's leg number (default the log's order); ``attempt``: replay the leg's
        interrupted attempt of that number (0-based) against its record instead."""
        step, clock = self.setup.step, self.setup.clock
        lnotes: list[str] = []
        key = lg.index if key is None else key
        rec = self.recorded.get(key)
        if attempt is not None:
            tries = (rec or {}).get("attempts") or []
            rec = {**tries[attempt], "rmse_passt": None, "rmse_model": None} if attempt < len(tries) else None
            lnotes.append(
                f"interrupted attempt {attempt + 1} of leg {key} (the run was resumed): planned, not absorbed"
            )
        pos_cell = _cell_of(self.grid, lg.start_latlon)
        if not lg.closed:
            lnotes.append("the log ends inside this leg (no HOLD after it): its samples may be incomplete")
        # the controller's clock reading before planning lies between two log times (see LoggedLeg)
        bracket = _clock_bracket(lg, clock, t_state, self.dt)
        k_lo, k_hi = bracket[0], bracket[-1]
        if rec is not None:
            rec_path, start, ks = self._recorded_target(lg, rec, pos_cell, k_lo, k_hi, lnotes)
        else:
            rec_path, start, ks = self._uploaded_target(lg, k_lo, k_hi, lnotes)
        planned, k = self._plan(lg, state, t_state, start, ks, rec_path, key)
        if rec is None and lg.clock is None and k_hi > k_lo:
            lnotes.append(f"the log brackets the controller's clock reading by {k_lo}..{k_hi} forecast steps; used {k}")
        if attempt is None:
            _replay_model_update(step.loop, rec)
            ab = step.absorb(planned, _absorbed(lg.samples, rec), clock, strict=False)
        else:  # never absorbed: the state goes on unchanged to the next attempt
            ab = SimpleNamespace(samples=[], rmse_passt=None, rmse_model=None, note=None)
        if ab.note:
            lnotes.append(ab.note + " (the controller would have stopped)")
        plan = planned.plan
        diffs = [] if rec_path is None else _diff_paths(rec_path, plan.path.tolist())
        same = None if rec_path is None else not diffs
        rp_rec = None if rec is None else rec.get("rmse_passt")
        rm_rec = None if rec is None else rec.get("rmse_model")
        r_same = None
        if rp_rec is not None or rm_rec is not None:
            r_same = _rmse_match(((rp_rec, ab.rmse_passt), (rm_rec, ab.rmse_model)), self.rmse_tol)
        if attempt is None:  # (an attempt's samples are in the store with the last attempt's)
            lnotes.extend(self._sample_notes(lg, rec, key))
        leg = ReplayLeg(
            index=key,
            n_samples=len(lg.samples),
            n_gp_points=len(ab.samples),
            start_cell=list(start),
            t_start=float(plan.t_start),
            steps=int(plan.steps),
            forecast_steps_before=int(k),
            path=plan.path.tolist(),
            recorded_path=rec_path,
            path_identical=same,
            differing_cells=diffs,
            reward_collected=_path_reward(plan),
            rmse_passt=ab.rmse_passt,
            rmse_model=ab.rmse_model,
            rmse_passt_recorded=rp_rec,
            rmse_model_recorded=rm_rec,
            rmse_identical=r_same,
            notes=lnotes,
        )
        self.say(_progress_line(f"leg {key + 1}", len(lg.samples), same, ab.rmse_passt, self.setup.unit()))
        return (leg, None, None) if attempt is not None else (leg, ab.state, ab.t_state)

    def _recorded_target(self, lg, rec: dict, pos_cell, k_lo: int, k_hi: int, lnotes: list[str]):
        """(recorded path, start cell, forecast steps to try) from the run's leg record, checked against the log."""
        rec_path = rec.get("path")
        start = tuple(int(x) for x in (rec.get("start_cell") or pos_cell))
        if start != pos_cell:
            lnotes.append(
                f"recorded start cell {list(start)}, the log's last position before the upload is in {list(pos_cell)}"
            )
        if rec.get("forecast_steps_before") is None:
            return rec_path, start, list(range(k_lo, k_hi + 1))
        ks = [int(rec["forecast_steps_before"])]
        if lg.clock is not None and int(lg.clock[2]) != ks[0]:
            lnotes.append(
                f"recorded forecast steps before planning {ks[0]}, the log's clock STATUSTEXT says {lg.clock[2]}"
            )
        elif not k_lo <= ks[0] <= k_hi:
            lnotes.append(f"recorded forecast steps before planning {ks[0]} outside the log's [{k_lo}, {k_hi}]")
        return rec_path, start, ks

    def _uploaded_target(self, lg, k_lo: int, k_hi: int, lnotes: list[str]):
        """(uploaded path, start cell, forecast steps to try) for a bare log: the clock STATUSTEXT's steps,
        else the searched ones, else the bracket from its middle out."""
        rec_path, start = _uploaded_path(self.grid, lg)  # the uploaded path starts at the cell planned from
        if rec_path is None:
            lnotes.append("no recorded path (no uploaded waypoints that expand into a grid path)")
        ks = sorted(range(k_lo, k_hi + 1), key=lambda x: abs(x - (k_lo + k_hi) / 2))
        if lg.clock is not None:
            ks = [int(lg.clock[2])]  # the controller said which (its clock STATUSTEXT)
        elif self.chosen is not None:
            ks = [self.chosen[lg.index]]
        return rec_path, start, ks

    def _plan(self, lg, state, t_state, start, ks: list[int], rec_path, key: int):
        """(plan, forecast steps): the first candidate whose plan is the recorded path, else the first's
        (``key``: the controller's leg number)."""
        planned, k = None, ks[0]
        for cand in ks:  # the clock reading whose plan is the uploaded one
            pl = self.setup.step.plan(key, state, t_state, start, k=cand)
            if planned is None:
                planned, k = pl, cand
            if rec_path is not None and pl.plan.path.tolist() == rec_path:
                planned, k = pl, cand
                break
        return planned, k

    def _sample_notes(self, lg, rec: dict | None, key: int) -> list[str]:
        """Where the log's samples disagree with the run's store or with the recorded count (``key``: the
        controller's leg number)."""
        notes = []
        self.compared.add(key)
        if key in self.store_legs:  # the controller's own store: the log must give the same measurements
            a = self.store_legs[key]
            b = {(int(x["time_boot_ms"]), x["lat"], x["lon"], x["u"], x["v"]) for x in lg.samples}
            if a != b:
                notes.append(
                    f"samples differ from the run's store: {len(a - b)} only in the store, {len(b - a)} only in the log"
                )
        if rec is not None and rec.get("n_samples") is not None and int(rec["n_samples"]) != len(lg.samples):
            notes.append(f"{len(lg.samples)} samples rebuilt from the log, {rec['n_samples']} recorded")
        return notes + _pause_notes(lg, rec)


def _pause_notes(lg, rec: dict | None) -> list[str]:
    """The operator's pauses of a leg: those the log marks (their waits kept inside the leg), and those its record
    holds (``leg.json`` ``waits`` of kind ``pause``) that the log does not mark: a log of a controller that did
    not mark them ends the leg at the pause's mode command, and leaves the rest of the leg's readings out."""
    marked = sum(1 for m, _ in lg.marks if m == "pause")
    recorded = sum(1 for w in (rec or {}).get("waits") or [] if w.get("kind") == "pause")
    notes = []
    if marked:
        notes.append(f"paused by the operator {marked} time(s) (the log's marks): the waits' readings kept in the leg")
    if recorded > marked:
        notes.append(
            f"{recorded} operator pause(s) recorded, {marked} marked in the log: a log without the marks "
            "ends the leg at the pause"
        )
    return notes


def _store_notes(store_legs: dict[int, set], compared: set[int], outside: int) -> list[str]:
    """The store's readings the replay did not compare with the log: those of legs the log does not hold or the
    replay did not reach (a leg ``compared`` says its own differences, :meth:`_LogReplay._sample_notes`), and those
    outside any leg (store leg -1) when the log has fewer of them (``outside``; the log may have more: it begins
    before the controller's collector and ends after it)."""
    missing = {k: len(v) for k, v in sorted(store_legs.items()) if k >= 0 and k not in compared and v}
    notes = []
    if missing:
        legs = ", ".join(f"leg {k + 1}: {n}" for k, n in missing.items())
        notes.append(
            f"{sum(missing.values())} readings of the run's store not compared with the log: no leg replayed ({legs})"
        )
    n_out = len(store_legs.get(-1, ()))
    if store_legs and n_out > outside:
        notes.append(f"{n_out} readings outside any leg in the run's store, {outside} in the log")
    return notes


def _absorbed(samples: list, rec: dict | None) -> list:
    """The readings of a leg's log that the boat's state absorbed: the first ``n_samples`` of its
    record (arrival order), those in the store when the controller absorbed the leg; a reading whose
    pair completed on the wire after that moment (the other half still in flight) was logged but
    not absorbed. All of them without a record."""
    n_rec = None if rec is None else rec.get("n_samples")
    return samples if n_rec is None else samples[: int(n_rec)]


def _path_reward(plan) -> float:
    """The reward a plan collects along its path."""
    from passt_mav.planning import path_reward

    return float(path_reward(plan.reward, plan.path))


def _write_result(result: ReplayResult, out, rd, src: Path) -> ReplayResult:
    from passt_mav.runs.rundir import write_json_atomic

    if out is not False:
        od = Path(out) if out is not None else ((rd.root / "replay") if rd is not None else src.with_suffix(".replay"))
        od.mkdir(parents=True, exist_ok=True)
        result.out_dir = str(od)
        write_json_atomic(od / "replay.json", result.to_dict())
    return result


# -- fleet ----------------------------------------------------------------------------------------
def _fleet_result(inp: _Source, setup: _Setup, rmse_tol: float, say) -> ReplayResult:
    """Replay of a fleet run directory (:func:`_replay_fleet`)."""
    legs, info, notes, first_div = _replay_fleet(inp.rd, inp.summary, setup.cfg, setup.step, rmse_tol, say)
    return ReplayResult(
        source=str(inp.src),
        kind=inp.kind,
        counterfactual={},
        legs=legs,
        log=info,
        reproduced=first_div is None and bool(legs),
        first_divergence=first_div,
        rmse_tol=float(rmse_tol),
        settings={**setup.settings(), "field": str(setup.cfg.field.source), "boats": len(inp.summary["boats"])},
        notes=notes,
    )


def _replay_fleet(rd, summary: dict, cfg, step, rmse_tol: float, say):
    """A fleet run (:mod:`passt_mav.vehicle.fleet_controller`): each boat's legs and samples from its own tlog,
    the fleet's plans and updates repeated in the order they were made (``fleet_seq`` of the leg
    records) through :class:`~passt_mav.loop.legstep.FleetStep`. A leg planned again (the operator's re-plan, a
    rejected leg: its record's ``attempts`` with their ``fleet_seq``) is planned at each of its steps, and absorbs
    the samples of all its attempts, as the boat did. Returns (legs, log info, notes, first divergence)."""
    from passt_mav.loop.legstep import FleetStep

    records = _fleet_records(rd)
    logs = [rebuild_from_tlog(p, u_name=cfg.sensors.u, v_name=cfg.sensors.v) for p in rd.boat_tlogs()]
    info = _log_info([str(p) for p in rd.boat_tlogs()], logs)
    logged: dict[int, Any] = {}
    for lg in (lg for log in logs for lg in log.legs if lg.planned_index is not None):
        key = int(lg.planned_index)  # (a leg planned again: its attempts' samples first, in the order logged)
        old = logged.get(key)
        again = old is not None and (records.get(key) or {}).get("attempts")
        logged[key] = dataclasses.replace(lg, samples=old.samples + lg.samples) if again else lg
    clocks = {int(b["boat"]): _field_clock(b.get("clock") or {}, 0.0, 1.0) for b in summary["boats"]}
    notes: list[str] = []
    step.prepare(step.initial_state()[0])  # as the fleet controller does before its boats fly
    fs, planned, out, first_div = FleetStep(step), {}, {}, None
    for _, kind, i, attempt in _fleet_events(records):
        rec = records[i]
        boat = int(rec["boat"])
        if kind == 0:
            plan = rec if attempt is None else rec["attempts"][attempt]
            planned[i] = fs.plan_for(
                boat, i, tuple(int(x) for x in plan["start_cell"]), k=int(plan["forecast_steps_before"])
            )
            continue
        lg = logged.get(i)
        if lg is None:
            notes.append(f"leg {i + 1} (boat {boat}): not found in flight_boat{boat}.tlog; the replay stops there")
            first_div = i if first_div is None else first_div
            break
        out[i] = leg = _fleet_leg(fs, i, rec, lg, planned[i], clocks[boat], rmse_tol)
        if (leg.differing_cells or not leg.rmse_identical) and first_div is None:
            first_div = i
        say(
            _progress_line(
                f"leg {i + 1} (boat {boat})",
                len(lg.samples),
                leg.path_identical,
                leg.rmse_passt,
                speed_unit(cfg.field.velocity_scale),
            )
        )
    return [out[i] for i in sorted(out)], info, notes, first_div


def _fleet_records(rd) -> dict[int, dict]:
    """A fleet run's leg records (those with a ``fleet_seq``) by leg index."""
    from passt_mav.runs.records import RunRecords
    from passt_mav.runs.rundir import RunDirError

    try:
        return {r["index"]: r for r in RunRecords(rd).leg_dicts() if r.get("fleet_seq")}
    except RunDirError as exc:
        raise ReplayError(str(exc)) from None


def _fleet_events(records: dict[int, dict]) -> list[tuple[int, int, int, int | None]]:
    """The fleet's plans (kind 0) and updates (kind 1) as (sequence number, kind, leg, attempt) in the order made;
    ``attempt``: the index in the record's ``attempts`` of an earlier plan of the leg, else None."""
    earlier = [
        (int(a["fleet_seq"]["plan"]), 0, i, k)
        for i, r in records.items()
        for k, a in enumerate(r.get("attempts") or [])
        if (a.get("fleet_seq") or {}).get("plan") is not None
    ]
    return sorted(
        earlier
        + [(int(r["fleet_seq"]["plan"]), 0, i, None) for i, r in records.items()]
        + [(int(r["fleet_seq"]["absorb"]), 1, i, None) for i, r in records.items()],
        key=lambda e: e[:2],
    )


def _fleet_leg(fs, i: int, rec: dict, lg, pl, clock, rmse_tol: float) -> ReplayLeg:
    """Absorb fleet leg ``i`` (planned ``pl``) into the boat's state; its replay against the record ``rec``."""
    boat = int(rec["boat"])
    ab = fs.absorb(boat, pl, _absorbed(lg.samples, rec), clock)
    diffs = _diff_paths(rec["path"], pl.plan.path.tolist())
    r_same = _rmse_match(((rec.get("rmse_passt"), ab.rmse_passt), (rec.get("rmse_model"), ab.rmse_model)), rmse_tol)
    lnotes = [f"boat {boat}"] + ([] if rec.get("status") == "complete" else [f"status {rec.get('status')}"])
    return ReplayLeg(
        index=i,
        n_samples=len(lg.samples),
        n_gp_points=len(ab.samples),
        start_cell=list(rec["start_cell"]),
        t_start=float(pl.t_start),
        steps=int(ab.steps),
        forecast_steps_before=int(pl.k),
        path=pl.plan.path.tolist(),
        recorded_path=rec["path"],
        path_identical=not diffs,
        differing_cells=diffs,
        reward_collected=_path_reward(pl.plan),
        rmse_passt=ab.rmse_passt,
        rmse_model=ab.rmse_model,
        rmse_passt_recorded=rec.get("rmse_passt"),
        rmse_model_recorded=rec.get("rmse_model"),
        rmse_identical=r_same,
        notes=lnotes,
    )
