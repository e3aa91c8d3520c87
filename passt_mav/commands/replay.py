"""passt-mav replay: Rebuild a run from its logs and recompute every decision."""

from __future__ import annotations

import argparse

HELP = "Rebuild a run from its logs and recompute every decision"
EXAMPLES = """examples:
  passt-mav replay runs/2026-05-01_ocean                      # same settings: does it reproduce?
  passt-mav replay runs/2026-05-01_ocean --planner lawnmower  # what lawnmower would have planned
  passt-mav replay flight.tlog --mission missions/ocean.yaml  # a bare telemetry log (ours, MAVProxy, QGC)
  passt-mav replay 00000042.BIN --mission missions/ocean.yaml # the autopilot's own ArduPilot DataFlash log
  passt-mav replay runs/2026-05-01_ocean --json

The legs, the samples and the vehicle's clock are rebuilt from the telemetry log
alone; the between-leg step (GP reconstruction, model forecast, planning) is re-run
with the controller's own code and compared leg by leg with the recorded paths and
RMSE figures. Writes replay.json under --out (default RUN_DIR/replay).
Exit 0: reproduced (or a counterfactual run), 1: diverged with the same settings,
2: bad input.
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "source",
        metavar="RUN_DIR|FILE.tlog|FILE.bin",
        help="run directory, or a telemetry log or ArduPilot DataFlash log (needs --mission)",
    )
    p.add_argument(
        "--mission",
        metavar="M.yaml",
        default=None,
        help="mission file (region, field, model, planner); required for a bare log",
    )
    p.add_argument(
        "--model", metavar="SPEC", default=None, help="counterfactual predictor (registry name, builtin:*, .pt)"
    )
    p.add_argument("--planner", metavar="NAME", default=None, help="counterfactual planner")
    p.add_argument("--reward", metavar="NAME", default=None, help="counterfactual reward map")
    p.add_argument("--out", metavar="DIR", default=None, help="output directory (default RUN_DIR/replay)")
    p.add_argument("--json", action="store_true", help="print the result as JSON instead of a table")


def _f(x, unit) -> str:
    """An RMSE (field units) in ``unit``'s numbers (m/s for a mission), or "-"."""
    return "-" if x is None else f"{unit(x):.6f}"


def run(args: argparse.Namespace) -> int:
    import json

    from passt_mav.analysis.replay import replay
    from passt_mav.units import speed_unit

    res = replay(
        args.source,
        out=args.out,
        model=args.model,
        planner=args.planner,
        reward=args.reward,
        mission=args.mission,
        progress=True,
    )
    if args.json:
        print(json.dumps(res.to_dict(), indent=2))
        return res.exit_code
    cf = ", ".join(f"{k}={v}" for k, v in res.counterfactual.items())
    print(
        f"replay of {res.source} ({res.settings['planner']}, model {res.settings['model']}"
        + (f"; counterfactual {cf}" if cf else "")
        + ")"
    )
    unit = speed_unit(res.settings.get("velocity_scale"))
    print(f"RMSE in {unit.label}")
    print(f"{'leg':>3}  {'samples':>7}  {'path':<9}  {'rmse rec':>9}  {'rmse replay':>11}  {'reward':>8}")
    for leg in res.legs:
        same = {True: "identical", False: "differs", None: "?"}[leg.path_identical]
        print(
            f"{leg.index + 1:>3}  {leg.n_samples:>7}  {same:<9}  {_f(leg.rmse_passt_recorded, unit):>9}  "
            f"{_f(leg.rmse_passt, unit):>11}  {leg.reward_collected:>8.4f}"
        )
        if leg.path_identical is False:
            print(f"     recorded {leg.recorded_path}")
            print(f"     replayed {leg.path}")
        for n in leg.notes:
            print(f"     note: {n}")
    for n in res.notes:
        print(f"note: {n}")
    if res.reproduced is None:
        print("counterfactual: paths above are what that choice would have planned on the same data")
    elif res.reproduced:
        print(f"reproduced: every path identical, every RMSE within {unit(res.rmse_tol):g} {unit.label}")
    else:
        print(f"DIVERGED: first at leg {res.first_divergence + 1}")
    if res.out_dir:
        print(f"written: {res.out_dir}/replay.json")
    return res.exit_code
