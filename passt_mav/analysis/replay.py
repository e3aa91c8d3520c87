"""Replay a mission from its telemetry log: rebuild every leg and recompute every decision offline.

``replay(source)`` takes a run directory (``passt-mav run``/``demo``) or a bare
``.tlog`` plus the mission file, and

1. rebuilds the mission from the telemetry log alone: per leg the position and
   vehicle time the controller planned from, the samples it collected, the
   waypoints it uploaded. Samples are rebuilt by feeding the logged frames, in
   order, through the controller's own :class:`~passt_mav.mavlink.SampleCollector`
   (so the pairing of CUR_U/CUR_V with positions is the controller's, not an
   approximation of it). Leg windows follow the controller's: a leg's samples are
   those emitted between the GCS's switch to AUTO and its next mode command (HOLD);
2. re-runs the between-leg step offline with the controller's own code,
   :class:`~passt_mav.legstep.LegStep` (``plan`` / ``absorb``), legs in order through one
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

import itertools
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from passt_mav.errors import UserError
from passt_mav.runs.legs import LoggedLeg, LogRebuild, rebuild_from_tlog  # noqa: F401 - re-exported

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
    """``cfg`` with ``gp.bias`` as the run resolved it (summary.json ``config``): a default that changed
    since (bias became the mission default in issue 27) must not make an older run's replay diverge. A run
    whose recorded config has no ``bias`` ran before the option existed: without it."""
    recorded = (summary or {}).get("config")
    if not isinstance(recorded, dict) or not isinstance(recorded.get("gp"), dict):
        return cfg
    bias = bool(recorded["gp"].get("bias", False))
    return cfg if cfg.gp.bias == bias else cfg.model_copy(update={"gp": cfg.gp.model_copy(update={"bias": bias})})


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
    from passt_mav.fields.datasets import mission_field
    from passt_mav.legstep import FieldClock, LegStep, build_loop, build_predictor
    from passt_mav.planning import PLANNERS, REWARDS, path_reward
    from passt_mav.runs.rundir import RunDir, RunDirError

    say = echo or (lambda s: None)
    src = Path(source)
    if not src.exists():
        raise ReplayError(f"replay source not found: {src}")
    rd = summary = None
    if src.is_dir():
        rd = RunDir(src)
        if not rd.is_run_dir():
            raise ReplayError(f"{src} is not a run directory")
        fleet_logs = rd.boat_tlogs()
        if not rd.tlog.is_file() and not fleet_logs:
            raise ReplayError(f"{rd.tlog} not found: the run has no telemetry log to replay")
        tlog = rd.tlog if not fleet_logs else fleet_logs[0]
        if rd.summary_file.exists():
            try:
                summary = rd.read_summary()
            except RunDirError as exc:
                raise ReplayError(str(exc)) from None
        kind = "fleet" if fleet_logs else "run"
        if kind == "fleet" and not (summary or {}).get("boats"):
            raise ReplayError(f"{src}: a fleet run (flight_boatN.tlog) needs its summary.json (the boats' clocks)")
    else:
        if src.suffix.lower() not in (".tlog", ".bin"):
            raise ReplayError(f"{src}: expected a run directory, a .tlog or an ArduPilot DataFlash .bin file")
        if mission is None:
            raise ReplayError(f"replaying a bare log needs --mission M.yaml (region, model, planner): {src}")
        tlog, kind = src, "dataflash" if src.suffix.lower() == ".bin" else "tlog"
    cfg, mission_src = _load_config(mission, summary, rd)
    if planner is not None and planner not in PLANNERS:
        raise ReplayError(f"unknown planner {planner!r}; choose one of {', '.join(PLANNERS)}")
    if reward is not None and reward not in REWARDS:
        raise ReplayError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
    cf = {k: v for k, v in (("model", model), ("planner", planner), ("reward", reward)) if v is not None}
    if cf:
        upd: dict[str, Any] = {}
        if "model" in cf:
            upd["model"] = model
        if planner is not None or reward is not None:
            pl = {"name": planner or cfg.planner.name, "reward": reward or cfg.planner.reward}
            if planner is not None and planner != cfg.planner.name:
                pl["options"] = {}  # the run's planner options belong to its planner
            upd["planner"] = cfg.planner.model_copy(update=pl)
        cfg = cfg.model_copy(update=upd)

    base = None if rd is None else rd.root
    fsrc = cfg.field.source
    if base is not None and not str(fsrc).startswith("builtin:") and not Path(fsrc).is_absolute():
        fsrc = str(base / fsrc) if (base / fsrc).exists() else fsrc
    field = mission_field(cfg, fsrc)  # the same rule as plan and run
    grid = field.grid
    if field.n_times < 2:
        raise ReplayError("the mission's field needs at least 2 snapshots (dt)")
    spec = cfg.model
    if summary and not cf.get("model") and summary.get("model") and summary.get("model_fallback"):
        spec = summary["model"]  # the run fell back (e.g. to dmd): replay what it used
    predictor, pinfo = build_predictor(spec, field, echo=say)
    dt = float(field.dt)
    clk = (summary or {}).get("clock") or {}
    clock = FieldClock(
        float(clk.get("t_boot0", field.times[cfg.t0])),
        float(clk.get("time_scale", cfg.field.time_scale)),
        later_boots=tuple(float(x) for x in clk.get("later_boots") or ()),
    )
    loop = build_loop(cfg, predictor, grid, land=field.land_mask)
    step = LegStep(cfg, field, loop, truth_known=summary is None or summary.get("rmse") is not None)

    from passt_mav.runs.tlog import LogReadError

    if kind == "fleet":
        if cf:
            raise ReplayError("counterfactual replays (--model/--planner/--reward) of a fleet run are not supported")
        legs, info, notes, first_div = _replay_fleet(rd, summary, cfg, step, rmse_tol, say)
        reproduced = first_div is None and bool(legs)
        settings = {
            "mission": mission_src,
            "model": pinfo.get("used"),
            "planner": cfg.planner.name,
            "reward": cfg.planner.reward,
            "path_length": cfg.planner.path_length,
            "field": str(cfg.field.source),
            "boats": len(summary["boats"]),
        }
        result = ReplayResult(
            str(src), kind, cf, legs, info, reproduced, first_div, float(rmse_tol), settings, notes=notes
        )
        return _write_result(result, out, rd, src)
    try:
        if kind == "dataflash":
            from passt_mav.runs.dataflash_legs import rebuild_from_dataflash

            log = rebuild_from_dataflash(tlog, u_name=cfg.sensors.u, v_name=cfg.sensors.v)
        else:
            log = rebuild_from_tlog(tlog, u_name=cfg.sensors.u, v_name=cfg.sensors.v)
    except LogReadError as exc:
        raise ReplayError(str(exc)) from None
    recorded = {}
    if rd is not None:
        try:
            recorded = {int(r["index"]): r for r in rd.read_legs()}
        except RunDirError as exc:
            raise ReplayError(str(exc)) from None
    notes: list[str] = []
    store_legs: dict[int, set] = {}
    if rd is not None and rd.samples_db.is_file():
        from passt_mav.runs.store import SampleStore

        st = SampleStore(rd.samples_db, readonly=True)
        try:
            for x in st.all():
                store_legs.setdefault(int(x.leg), set()).add((int(x.time_boot_ms), x.lat, x.lon, x.u, x.v))
        finally:
            st.close()
    if log.bad_frames:
        notes.append(
            f"the log is damaged: {log.bad_frames} bad stretch(es), {log.skipped_bytes} byte(s) skipped; "
            "replayed what was readable"
        )
    if not log.legs:
        notes.append("no leg (upload followed by AUTO) found in the log")

    state, t_state = step.initial_state()
    chosen = None
    usable = [lg for lg in log.legs if lg.start_latlon is not None and lg.t_now_ms is not None]
    if rd is None and usable and len(usable) == len(log.legs) and any(lg.clock is None for lg in usable):
        starts, paths = [], []
        for lg in usable:
            p = waypoints_to_path(grid, lg.waypoints)
            paths.append(None if p is None else p.tolist())
            pr, pc = grid.latlon_to_cell(lg.start_latlon[0], lg.start_latlon[1], clip=True)
            starts.append(tuple(paths[-1][0]) if paths[-1] else (int(pr), int(pc)))
        chosen = _search_clock(step, clock, state, t_state, usable, starts, paths)
        if chosen is None:
            notes.append(
                "no sequence of clock readings in the log's brackets reproduces every uploaded path; "
                "each leg takes the first that reproduces its own"
            )
    from passt_mav.progress import progress as _progress

    legs: list[ReplayLeg] = []
    first_div = None
    for lg in _progress(log.legs, "replay", "leg", quiet=not progress, every_pct=1):
        lnotes: list[str] = []
        rec = recorded.get(lg.index)
        if lg.start_latlon is None or lg.t_now_ms is None:
            lnotes.append("no position or vehicle time before the upload: leg skipped")
            legs.append(
                ReplayLeg(
                    lg.index,
                    len(lg.samples),
                    0,
                    [],
                    float("nan"),
                    0,
                    0,
                    [],
                    None,
                    None,
                    [],
                    0.0,
                    None,
                    None,
                    notes=lnotes,
                )
            )
            if not cf and first_div is None:
                first_div = lg.index
            break  # the state after it is unknown
        r, c = grid.latlon_to_cell(lg.start_latlon[0], lg.start_latlon[1], clip=True)
        pos_cell = (int(r), int(c))
        if not lg.closed:
            lnotes.append("the log ends inside this leg (no HOLD after it): its samples may be incomplete")
        # the controller's clock reading before planning lies between two log times (see LoggedLeg)
        bracket = _clock_bracket(lg, clock, t_state, dt)
        k_lo, k_hi = bracket[0], bracket[-1]
        if rec is not None:
            rec_path = rec.get("path")
            start = tuple(int(x) for x in (rec.get("start_cell") or pos_cell))
            if start != pos_cell:
                lnotes.append(
                    f"recorded start cell {list(start)}, the log's last position before the upload is in "
                    f"{list(pos_cell)}"
                )
            if rec.get("forecast_steps_before") is not None:
                ks = [int(rec["forecast_steps_before"])]
                if lg.clock is not None and int(lg.clock[2]) != ks[0]:
                    lnotes.append(
                        f"recorded forecast steps before planning {ks[0]}, the log's clock STATUSTEXT "
                        f"says {lg.clock[2]}"
                    )
                elif not k_lo <= ks[0] <= k_hi:
                    lnotes.append(f"recorded forecast steps before planning {ks[0]} outside the log's [{k_lo}, {k_hi}]")
            else:
                ks = list(range(k_lo, k_hi + 1))
        else:
            p = waypoints_to_path(grid, lg.waypoints)
            rec_path = None if p is None else p.tolist()
            if rec_path is None:
                lnotes.append("no recorded path (no uploaded waypoints that expand into a grid path)")
            # the uploaded path starts at the cell the controller planned from
            start = tuple(rec_path[0]) if rec_path else pos_cell
            ks = sorted(range(k_lo, k_hi + 1), key=lambda x: abs(x - (k_lo + k_hi) / 2))
            if lg.clock is not None:
                ks = [int(lg.clock[2])]  # the controller said which (its clock STATUSTEXT)
            elif chosen is not None:
                ks = [chosen[lg.index]]
        planned, k = None, ks[0]
        for cand in ks:  # the clock reading whose plan is the uploaded one
            pl = step.plan(lg.index, state, t_state, start, k=cand)
            if planned is None:
                planned, k = pl, cand
            if rec_path is not None and pl.plan.path.tolist() == rec_path:
                planned, k = pl, cand
                break
        if rec is None and lg.clock is None and k_hi > k_lo:
            lnotes.append(f"the log brackets the controller's clock reading by {k_lo}..{k_hi} forecast steps; used {k}")
        ab = step.absorb(planned, lg.samples, clock, strict=False)
        plan, samples, new_state, t_new, r_p, r_m = (
            planned.plan,
            ab.samples,
            ab.state,
            ab.t_state,
            ab.rmse_passt,
            ab.rmse_model,
        )
        if ab.note:
            lnotes.append(ab.note + " (the controller would have stopped)")
        diffs = [] if rec_path is None else _diff_paths(rec_path, plan.path.tolist())
        same = None if rec_path is None else not diffs
        rp_rec = None if rec is None else rec.get("rmse_passt")
        rm_rec = None if rec is None else rec.get("rmse_model")
        r_same = None
        if rp_rec is not None or rm_rec is not None:
            r_same = all(
                a is None or (b is not None and abs(a - b) <= rmse_tol) for a, b in ((rp_rec, r_p), (rm_rec, r_m))
            )
        if lg.index in store_legs:  # the controller's own store: the log must give the same measurements
            a = store_legs[lg.index]
            b = {(int(x["time_boot_ms"]), x["lat"], x["lon"], x["u"], x["v"]) for x in lg.samples}
            if a != b:
                lnotes.append(
                    f"samples differ from the run's store: {len(a - b)} only in the store, {len(b - a)} only in the log"
                )
        if rec is not None and rec.get("n_samples") is not None and int(rec["n_samples"]) != len(lg.samples):
            lnotes.append(f"{len(lg.samples)} samples rebuilt from the log, {rec['n_samples']} recorded")
        leg = ReplayLeg(
            lg.index,
            len(lg.samples),
            len(samples),
            list(start),
            float(plan.t_start),
            int(plan.steps),
            int(k),
            plan.path.tolist(),
            rec_path,
            same,
            diffs,
            float(path_reward(plan.reward, plan.path)),
            r_p,
            r_m,
            rp_rec,
            rm_rec,
            r_same,
            lnotes,
        )
        legs.append(leg)
        if first_div is None and (same is False or r_same is False):
            first_div = lg.index
        state, t_state = new_state, t_new
        say(
            f"leg {lg.index}: {len(lg.samples)} samples, path {'identical' if same else 'differs' if same is False else '?'}"
            + ("" if r_p is None else f", RMSE {r_p:.6f}")
        )
    if rd is not None and len(recorded) > len(legs):
        notes.append(f"{len(recorded)} legs recorded, {len(legs)} rebuilt from the log")
    if cf:
        reproduced = None
    else:
        reproduced = first_div is None and bool(legs) and all(x.path_identical is not False for x in legs)
        if rd is not None and len(recorded) > len(legs):
            reproduced = False
            if first_div is None:
                first_div = len(legs)
    settings = {
        "mission": mission_src,
        "model": pinfo.get("used"),
        "planner": cfg.planner.name,
        "reward": cfg.planner.reward,
        "path_length": cfg.planner.path_length,
        "clock": clock.describe(),
        "field": str(cfg.field.source),
    }
    result = ReplayResult(
        str(src),
        kind,
        cf,
        legs,
        {
            "path": str(tlog),
            "n_messages": log.n_messages,
            "bad_frames": log.bad_frames,
            "skipped_bytes": log.skipped_bytes,
            "n_bytes": log.n_bytes,
            "samples_outside_legs": log.n_samples_outside_legs,
        },
        reproduced,
        None if cf else first_div,
        float(rmse_tol),
        settings,
        notes=notes,
    )
    return _write_result(result, out, rd, src)


def _write_result(result: ReplayResult, out, rd, src: Path) -> ReplayResult:
    from passt_mav.runs.rundir import write_json_atomic

    if out is not False:
        od = Path(out) if out is not None else ((rd.root / "replay") if rd is not None else src.with_suffix(".replay"))
        od.mkdir(parents=True, exist_ok=True)
        result.out_dir = str(od)
        write_json_atomic(od / "replay.json", result.to_dict())
    return result


def _replay_fleet(rd, summary: dict, cfg, step, rmse_tol: float, say):
    """A fleet run (:mod:`passt_mav.fleet_controller`): each boat's legs and samples from its own tlog,
    the fleet's plans and updates repeated in the order they were made (``fleet_seq`` of the leg
    records) through :class:`~passt_mav.legstep.FleetStep`. Returns (legs, log info, notes, first divergence)."""
    from passt_mav.legstep import FieldClock, FleetStep
    from passt_mav.planning import path_reward
    from passt_mav.runs.rundir import RunDirError

    try:
        records = {int(r["index"]): r for r in rd.read_legs() if r.get("fleet_seq")}
    except RunDirError as exc:
        raise ReplayError(str(exc)) from None
    notes: list[str] = []
    logged: dict[int, Any] = {}
    info = {
        "path": [str(p) for p in rd.boat_tlogs()],
        "n_messages": 0,
        "bad_frames": 0,
        "skipped_bytes": 0,
        "n_bytes": 0,
        "samples_outside_legs": 0,
    }
    for p in rd.boat_tlogs():
        log = rebuild_from_tlog(p, u_name=cfg.sensors.u, v_name=cfg.sensors.v)
        for key in ("n_messages", "bad_frames", "skipped_bytes", "n_bytes"):
            info[key] += getattr(log, key)
        info["samples_outside_legs"] += log.n_samples_outside_legs
        for lg in log.legs:
            if lg.planned_index is not None:
                logged[int(lg.planned_index)] = lg
    clocks = {}
    for b in summary["boats"]:
        c = b.get("clock") or {}
        clocks[int(b["boat"])] = FieldClock(
            float(c.get("t_boot0", 0.0)),
            float(c.get("time_scale", 1.0)),
            later_boots=tuple(float(x) for x in c.get("later_boots") or ()),
        )
    events = sorted(
        [(int(r["fleet_seq"]["plan"]), 0, i) for i, r in records.items()]
        + [(int(r["fleet_seq"]["absorb"]), 1, i) for i, r in records.items()]
    )
    fs, planned, out, first_div = FleetStep(step), {}, {}, None
    for _, kind, i in events:
        rec = records[i]
        boat = int(rec["boat"])
        if kind == 0:
            planned[i] = fs.plan_for(
                boat, i, tuple(int(x) for x in rec["start_cell"]), k=int(rec["forecast_steps_before"])
            )
            continue
        lg = logged.get(i)
        if lg is None:
            notes.append(f"leg {i} (boat {boat}): not found in flight_boat{boat}.tlog; the replay stops there")
            first_div = i if first_div is None else first_div
            break
        pl = planned[i]
        # the state saw the leg's first n_samples readings (arrival order), those in the store when the
        # boat absorbed its leg; a reading that completed in the log after that moment (the other half
        # of a pair still on the wire) was logged but not absorbed
        n_rec = rec.get("n_samples")
        samples = lg.samples if n_rec is None else lg.samples[: int(n_rec)]
        ab = fs.absorb(boat, pl, samples, clocks[boat])
        diffs = _diff_paths(rec["path"], pl.plan.path.tolist())
        r_same = all(
            a is None or (b is not None and abs(a - b) <= rmse_tol)
            for a, b in ((rec.get("rmse_passt"), ab.rmse_passt), (rec.get("rmse_model"), ab.rmse_model))
        )
        lnotes = [f"boat {boat}"] + ([] if rec.get("status") == "complete" else [f"status {rec.get('status')}"])
        out[i] = ReplayLeg(
            i,
            len(lg.samples),
            len(ab.samples),
            list(rec["start_cell"]),
            float(pl.t_start),
            int(ab.steps),
            int(pl.k),
            pl.plan.path.tolist(),
            rec["path"],
            not diffs,
            diffs,
            float(path_reward(pl.plan.reward, pl.plan.path)),
            ab.rmse_passt,
            ab.rmse_model,
            rec.get("rmse_passt"),
            rec.get("rmse_model"),
            r_same,
            lnotes,
        )
        if (diffs or not r_same) and first_div is None:
            first_div = i
        say(
            f"leg {i} (boat {boat}): {len(lg.samples)} samples, path {'identical' if not diffs else 'differs'}"
            + ("" if ab.rmse_passt is None else f", RMSE {ab.rmse_passt:.6f}")
        )
    return [out[i] for i in sorted(out)], info, notes, first_div
