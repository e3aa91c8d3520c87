"""passt-mav plan: one leg - state -> reward map -> grid path -> mission files.

Reads a mission YAML, takes snapshot ``--time`` (default the mission's ``t0``) of
``--state FILE.nc`` (default the mission's field) as the current state, predicts
one step with the mission's model, builds the configured reward map on that
prediction, plans ``L`` moves from the start cell with the configured planner, and
writes under ``--out``:

* ``leg.plan``      - QGroundControl plan (waypoints, speed, geofence)
* ``leg.waypoints`` - the same mission as QGC WPL 110 (home placeholder at seq 0)
* ``path.json``     - grid path, waypoint cells, lat/lon, reward map and provenance

Without a usable predictor (``--model none``, or the predictors package not
installed) the reward is computed on the state itself (persistence), and the
command says so.
"""

from __future__ import annotations

import argparse
import sys

HELP = "Plan one leg: state -> path -> mission file (.plan / .waypoints)"
EXAMPLES = """examples:
  passt-mav plan missions/north_atlantic.yaml --out runs/plan_na
  passt-mav plan missions/cylinder.yaml --time 320 --start 15,2 --length 40 --out runs/plan_cyl
  passt-mav plan missions/north_atlantic.yaml --state estimate.nc --time 0 --model none --json --out runs/leg3
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("mission", help="mission YAML file (see missions/)")
    p.add_argument(
        "--state", default=None, help="field file (.nc) holding the state snapshot (default: the mission's field)"
    )
    p.add_argument("--time", type=int, default=None, help="snapshot index of the state (default: the mission's t0)")
    p.add_argument(
        "--start", default=None, help="start cell ROW,COL (default: the mission's start_cell, else the centre)"
    )
    p.add_argument(
        "--length", type=int, default=None, help="moves in the leg L (default: the mission's planner.path_length)"
    )
    p.add_argument("--model", default=None, help="override the mission's model; 'none' plans on the state itself")
    p.add_argument("--planner", default=None, help="override the mission's planner (e.g. policy_gradient, information)")
    p.add_argument("--reward", default=None, help="override the mission's reward (e.g. speed, variance_reduction)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--out", required=True, help="output directory")


def _parse_start(s: str, shape) -> tuple[int, int]:
    from passt_mav.errors import PlannerError

    try:
        r, c = (int(x) for x in s.split(","))
    except ValueError:
        raise PlannerError(f"--start must be ROW,COL (two integers), got {s!r}") from None
    if not (0 <= r < shape[0] and 0 <= c < shape[1]):
        raise PlannerError(f"--start {r},{c} lies outside the {shape[0]}x{shape[1]} grid")
    return r, c


def _nearest_water(start, land):
    import numpy as np

    if not land[start]:
        return start
    water = np.argwhere(~land)
    if len(water) == 0:
        from passt_mav.errors import FieldError

        raise FieldError("the state has no water cell to start from")
    d = np.abs(water - np.asarray(start)).max(axis=1)
    return tuple(int(x) for x in water[int(np.argmin(d))])


def _predictor(spec: str | None, field) -> tuple[object | None, str]:
    """(predictor or None, note). A missing predictors package or a shipped (``builtin:``)
    checkpoint not built yet falls back to planning on the state, with a note; a bad
    user checkpoint or name is the user's error and propagates."""
    if spec is None or spec == "none":
        return None, "no predictor (--model none): reward computed on the state itself"
    try:
        from passt_mav.models.base import PREDICTORS, load_predictor, make_predictor
    except ImportError as exc:
        return None, f"predictors unavailable ({exc}); reward computed on the state itself (persistence)"
    from passt_mav.errors import ModelError

    try:
        if spec in PREDICTORS:
            return make_predictor(spec).fit(field), f"predictor {spec!r} fitted on the field"
        return load_predictor(spec), f"predictor {spec}"
    except ImportError as exc:  # a predictor module of a partial install
        return None, f"predictor {spec} unavailable ({exc}); reward computed on the state itself (persistence)"
    except ModelError as exc:
        if not spec.startswith("builtin:"):
            raise  # the user's own checkpoint: their error, stop
        # a shipped model not built in this checkout yet: plan anyway, and say so
        return None, f"{spec} unavailable ({exc}); reward computed on the state itself (persistence)"


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from passt_mav.errors import FieldError, PlannerError
    from passt_mav.fields.datasets import mission_field, speed_warning
    from passt_mav.mission import WaypointMission
    from passt_mav.mission.config import load_mission

    cfg = load_mission(args.mission)
    grid = cfg.grid()
    field = mission_field(cfg, args.state)  # the same rule as run, replay and report
    fast = speed_warning(field, args.state or cfg.field.source)
    if fast:
        print(f"warning: {fast}", file=sys.stderr)
    k = cfg.t0 if args.time is None else int(args.time)
    if not (0 <= k < field.n_times):
        raise FieldError(f"--time {k} is outside the state's snapshots 0..{field.n_times - 1}")
    L = cfg.planner.path_length if args.length is None else int(args.length)
    if L < 1:
        raise PlannerError(f"--length must be >= 1, got {L}")
    start = _leg_start(args.start, cfg, grid, field.land_mask)
    predictor, note = _predictor(args.model if args.model is not None else cfg.model, field)
    print(f"note: {note}", file=sys.stderr)
    loop = _mission_loop(args, cfg, predictor, grid, field.land_mask, L)
    state = field.state_at(k)  # gaps that come and go: FlowField.state_at
    leg = loop.plan_leg(state, start, float(field.times[k]), 1.0, steps=1)
    mission = WaypointMission.from_path(
        grid,
        leg.path,
        speed=cfg.vehicle.speed_mps,
        wp_radius_m=cfg.vehicle.wp_radius_m,
        fence_margin_m=cfg.geofence_margin_m,
    )

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    f_plan = mission.to_plan(out / "leg.plan")
    f_wpl = mission.to_wpl(out / "leg.waypoints")
    summary = _plan_summary(args, cfg, k, start, L, model=None if predictor is None else (args.model or cfg.model))
    summary.update(_leg_record(leg, mission, note=note, seed=cfg.seeds.planner, grid=grid))
    f_json = out / "path.json"
    f_json.write_text(json.dumps(summary) + "\n")
    if args.json:
        print(
            json.dumps(
                {
                    k2: summary[k2]
                    for k2 in ("mission", "start", "path_length", "reward_collected", "waypoint_cells", "note")
                }
                | {"out": str(out), "files": [str(f_plan), str(f_wpl), str(f_json)]}
            )
        )
    else:
        print(
            f"planned {L} moves from {start} with {cfg.planner.name} on the {cfg.planner.reward} reward: "
            f"{len(mission.waypoints)} waypoints, reward collected {summary['reward_collected']:.3f} "
            "(dimensionless: the sum over the path's cells of the reward map, at most 1 per cell)"
        )
        print(f"wrote {f_plan}, {f_wpl}, {f_json}")
        print(f"results written to {out}")
    return 0


def _leg_start(spec: str | None, cfg, grid, land) -> tuple[int, int]:
    """The leg's start cell (row, col): ``--start`` (a water cell), else the mission's start cell or the
    grid's centre, moved to the nearest water cell."""
    from passt_mav.errors import PlannerError

    if spec is not None:
        start = _parse_start(spec, grid.shape)
        if land[start]:
            raise PlannerError(f"--start {start[0]},{start[1]} is a land cell")
        return start
    start = tuple(cfg.start_cell) if cfg.start_cell is not None else (grid.rows // 2, grid.cols // 2)
    return _nearest_water(start, land)


def _mission_loop(args: argparse.Namespace, cfg, predictor, grid, land, L: int):
    """The mission's own loop (GP noise, background, prior blend, seeds), as ``run`` builds it, with
    legs of ``L`` moves and the planner and reward ``--planner`` / ``--reward`` name."""
    from passt_mav.errors import PlannerError
    from passt_mav.loop.legstep import build_loop
    from passt_mav.planning import PLANNERS, REWARDS

    pl = {"path_length": L}
    if args.planner is not None:
        pl.update(name=args.planner, options={})
    if args.reward is not None:
        pl["reward"] = args.reward
    if pl.get("name", cfg.planner.name) not in PLANNERS or pl.get("reward", cfg.planner.reward) not in REWARDS:
        raise PlannerError(
            f"--planner / --reward: choose a planner of {', '.join(PLANNERS)} and a reward of {', '.join(REWARDS)}"
        )
    return build_loop(cfg.model_copy(update={"planner": cfg.planner.model_copy(update=pl)}), predictor, grid, land=land)


def _plan_summary(args: argparse.Namespace, cfg, k: int, start, L: int, *, model) -> dict:
    """The head of ``path.json``: which mission, state (snapshot ``k``), start, leg length and model."""
    return {
        "mission": cfg.name,
        "mission_file": str(args.mission),
        "state": str(args.state) if args.state else cfg.field.source,
        "time_index": k,
        "start": list(start),
        "path_length": L,
        "planner": cfg.planner.name,
        "reward": cfg.planner.reward,
        "model": model,
    }


def _leg_record(leg, mission, *, note: str, seed, grid) -> dict:
    """The rest of ``path.json``: the planned leg (cells, reward collected and map), its waypoints
    (cells, lat/lon degrees, mission item seqs), the grid and the planning timings (s)."""
    import numpy as np

    from passt_mav.planning import path_reward

    return {
        "note": note,
        "seed": seed,
        "reward_collected": float(path_reward(leg.reward, leg.path)),
        "path": leg.path.tolist(),
        "waypoint_cells": mission.meta["cells"],
        "waypoints_latlon": mission.waypoints.tolist(),
        "waypoint_seqs": mission.waypoint_seqs(),
        "grid": grid.describe(),
        "reward_map": np.asarray(leg.reward, dtype=float).round(6).tolist(),
        "timings_s": leg.timings,
    }
