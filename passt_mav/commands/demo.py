"""passt-mav demo: Embedded default: start the simulator, run a short PASST mission with the shipped model, write a report.

What it does: starts ``vehicle-sim`` as a subprocess on loopback (a free TCP port)
replaying the wake behind a cylinder that oscillates across the stream
(``builtin:oscillating``, placed on the sea at 100x: 30 m cells, 0.5 m/s inflow) with
the boat at the centre of the start cell, the field clock at snapshot ``t0`` and
``--speedup`` x real time (50x here: :func:`default_speedup`); then runs ``missions/oscillating_cylinder.yaml`` (5 legs of
50 moves, the static-wake KNODE as the model: a process it never saw, so the model
alone drifts and the samples must correct it) with a 5 m/s boat (a leg of ~1.6 km takes
~400 s of simulated time, ~8 s of wall time at 50x) through the same code
as ``passt-mav run``; sets random walks flown offline through the same model + GP loop
over the same legs beside it; writes the run directory and its report; stops the
simulator. ``--field builtin:ocean`` flies the North Atlantic mission instead
(``missions/north_atlantic.yaml``; there the shipped model is within the sensor noise and
sampling rightly leaves it alone), ``--field builtin:rtofs`` real NOAA currents.

The boat speed (``WP_SPEED``) and the sensor rate are set on the simulator to
match the mission (CUR_U/CUR_V every 5 simulated seconds, far more than the GP is
given after thinning).

One boat flies on the simulated clock: the simulator is served in lockstep (``vehicle-sim
--lockstep``) and its time runs only while the controller waits for the boat, :data:`STEP_S`
simulated seconds at a time (:class:`passt_mav.mavlink.link.Lockstep`), at most ``--speedup`` x wall
time. Planning and reconstruction take no simulated time, and what the boat samples where and when
depends on the mission alone, not on the machine's load; the speed-up paces only what a watcher
sees. A fleet (``--boats N``) and ``--inject-link-drop`` run the simulator on the wall clock
(``--speedup``; its boats step one shared clock, and a dropped link cannot answer a step).
"""

from __future__ import annotations

import argparse

HELP = "Embedded default: start the simulator, run a short PASST mission with the shipped model, write a report"
EXAMPLES = """examples:

    passt-mav demo
    passt-mav demo --legs 1 --out runs/demo1
    passt-mav demo --speedup 200 --moves 4
    passt-mav demo --field builtin:rtofs          # real NOAA currents with a coastline (missions/rtofs.yaml)
    passt-mav demo --mission missions/cylinder.yaml
    passt-mav demo --boats 3                      # a fleet: three boats, one shared estimate
    passt-mav demo --boats 3 --view 8765          # its live view on http://127.0.0.1:8765/
    passt-mav demo --inject-link-drop 0:300:900  # boat 0's link down 300 simulated s after it arms, >= 900 s
"""

#: the demo's changes to any base mission: a 5 m/s boat, 25 m waypoint radius
DEMO_OVERRIDES = {"vehicle.speed_mps": 5.0, "vehicle.wp_radius_m": 25.0}
#: legs and moves of a base mission other than the default (``--mission``, ``--field``; the default
#: flies its mission's own 5 legs of 50 moves): 5 moves of the ocean's 6.6 km cells are ~33 km
SHORT_LEGS = {"legs": 3, "planner.path_length": 5}
#: the default base mission (missions/NAME.yaml)
DEFAULT_MISSION = "oscillating_cylinder"
SENSOR_RATE_HZ = 0.2
#: simulated seconds per lockstep step of a one-boat demo (the controller sees the boat at this resolution)
STEP_S = 0.5

#: missions/oscillating_cylinder.yaml (used when the repository's missions/ folder is not beside the package;
#: tests/test_demo.py checks that the two agree)
_EMBEDDED = {
    "name": "oscillating_cylinder",
    "region": {
        "kind": "metric",
        "x0": 2.6,
        "x1": 11.4,
        "y0": -4.7,
        "y1": 4.7,
        "rows": 30,
        "cols": 30,
        "anchor_lat": 40.2,
        "anchor_lon": -63.1,
        "rotation_deg": 0.0,
        "scale": 100.0,
    },
    "field": {"source": "builtin:oscillating", "velocity_scale": 0.5, "time_scale": 200.0},
    "model": "builtin:cylinder",
    "planner": {"name": "information", "path_length": 50, "reward": "variance_reduction"},
    "legs": 5,
    "start_cell": [15, 2],
    "t0": 300,
    "steps_per_leg": 10,
    "vehicle": {"connect": "tcp:127.0.0.1:5760", "speed_mps": 2.0, "wp_radius_m": 3.0},
    "sensors": {"u": "CUR_U", "v": "CUR_V", "noise_std": 0.01},
    "geofence_margin_m": 20.0,
    "gp": {
        "prior": "forecast",
        "hyper": "every_leg",
        "background": 200,
        "bias": True,
        "prior_blend": "select",
        "prior_share": 0.05,
    },
    "seeds": {"planner": 0, "gp": 0, "sensor": 0},
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--legs", type=int, help="legs to fly (default: the default mission's 5; 3 with --mission or --field)"
    )
    p.add_argument(
        "--moves",
        type=int,
        help="grid moves per leg L (default: the default mission's 50; 5 with --mission or --field)",
    )
    p.add_argument("--out", help="run directory (default runs/demo-<UTC>)")
    p.add_argument(
        "--speedup",
        type=float,
        help="simulator speed-up (simulated s per wall s; default 150, or less where the field's "
        "snapshots are short: at most 0.625 snapshot of field time per wall second, 50x on the "
        "oscillating wake's 80 s snapshots). One boat flies in lockstep: the speed-up only paces what "
        "you see, the figures are the same at any speed-up and load. A fleet and --inject-link-drop "
        "run the simulator on the wall clock, where a second of planning on a busy machine lets the "
        "field run on, and the simulated vehicle's mission-transfer timeouts (8 s) run in simulated "
        "time: at 250x and more on two cores uploads are cancelled before the controller can answer",
    )
    p.add_argument("--model", help="predictor instead of the shipped KNODE (dmd, persistence, a .pt)")
    p.add_argument("--mission", help="base mission file instead of missions/oscillating_cylinder.yaml")
    p.add_argument(
        "--field",
        help="field to replay: builtin:NAME uses missions/NAME.yaml when it exists "
        "(builtin:rtofs: real NOAA currents with land); a .nc replaces the base mission's field and "
        "region (model persistence unless --model)",
    )
    p.add_argument(
        "--boats",
        type=int,
        default=1,
        help="a fleet of N boats sharing one estimate (vehicle-sim --boats N, mission vehicles:; default 1)",
    )
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    # live view: served by default, the address printed (no browser is launched)
    from passt_mav.commands.view import port

    p.add_argument(
        "--view",
        nargs="?",
        type=port,
        const=0,
        default=0,
        metavar="PORT",
        help="serve the live view on PORT (default: a free port); the address is printed",
    )
    p.add_argument("--no-view", action="store_true", help="do not serve the live view")
    p.add_argument(
        "--approve",
        action="store_true",
        help="approve each leg on the live page before its upload (mission key approve; docs/console.md)",
    )
    p.add_argument(
        "--view-host",
        default="127.0.0.1",
        metavar="HOST",
        help="address to bind the view to (default 127.0.0.1); any other needs the token printed at start",
    )
    p.add_argument(
        "--inject-link-drop",
        action="append",
        default=[],
        metavar="BOAT:START:DURATION",
        help="a link outage of boat BOAT (0-based) START simulated seconds after the boat first arms, for "
        "DURATION simulated seconds and until the controller has reconnected (vehicle-sim --boat-drop "
        "BOAT:arm+START:DURATION --drops-break-link); repeatable",
    )


def _free_port(boats: int = 1) -> int:
    """A free loopback TCP port P with P + 10*i free too for every boat i (vehicle-sim --boats)."""
    import socket

    for _ in range(200):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port + 10 * (boats - 1) > 65535:
            continue
        ok = True
        for i in range(1, boats):
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t:
                try:
                    t.bind(("127.0.0.1", port + 10 * i))
                except OSError:
                    ok = False
                    break
        if ok:
            return port
    raise OSError("no free loopback ports for the simulator")


def fleet_starts(grid, land, start, boats: int, spacing: int = 6) -> list[tuple[int, int]]:
    """Start cells of a demo fleet: the mission's start, then cells ``spacing`` apart west/east,
    south/north of it (clipped to the grid; land and repeats skipped: the nearest free water cell)."""
    import numpy as np

    r0, c0 = start
    offsets = [
        (0, 0),
        (0, -spacing),
        (0, spacing),
        (-spacing, 0),
        (spacing, 0),
        (-spacing, -spacing),
        (spacing, spacing),
        (-spacing, spacing),
        (spacing, -spacing),
    ]
    water = np.argwhere(~np.asarray(land, bool))
    out: list[tuple[int, int]] = []
    for k in range(boats):
        dr, dc = offsets[k % len(offsets)]
        want = np.array(
            [
                min(max(r0 + dr * (1 + k // len(offsets)), 0), grid.rows - 1),
                min(max(c0 + dc * (1 + k // len(offsets)), 0), grid.cols - 1),
            ]
        )
        order = np.argsort(((water - want) ** 2).sum(axis=1), kind="stable")
        cell = next(tuple(int(x) for x in water[j]) for j in order if tuple(int(x) for x in water[j]) not in out)
        out.append(cell)
    return out


def mission_mapping(mission: str | None = None, field: str | None = None) -> tuple[dict, str]:
    """(mapping, where from) of the demo's base mission.

    Neither: ``missions/oscillating_cylinder.yaml`` (:data:`DEFAULT_MISSION`; its embedded copy
    when missions/ is not beside the package). ``mission``: a mission file; ``field``:
    ``builtin:NAME`` picks ``missions/NAME.yaml`` (``builtin:ocean``: north_atlantic,
    ``builtin:oscillating``: oscillating_cylinder) when it exists; any other field replaces
    ``missions/north_atlantic.yaml``'s ``field.source`` and region (from the field's grid), with
    persistence as the model and the water cell nearest the centre as the start.
    """
    from pathlib import Path

    import yaml

    from passt_mav.errors import UserError

    missions = Path(__file__).resolve().parents[2] / "missions"
    if mission is None and field is not None and field.startswith("builtin:"):
        name = {"ocean": "north_atlantic", "oscillating": "oscillating_cylinder"}.get(
            field.split(":", 1)[1], field.split(":", 1)[1]
        )
        if (missions / f"{name}.yaml").exists():
            mission = str(missions / f"{name}.yaml")
    if mission is not None:
        f = Path(mission)
        if not f.exists():
            raise UserError(f"mission file not found: {f}")
        from passt_mav.mission.config import read_mission_data

        data, origin = read_mission_data(f), str(f)  # not YAML, nested too deep: one line naming it
        if not isinstance(data, dict):
            raise UserError(f"{f}: a mission file is a mapping of keys (name:, region:, field:, ...)")
    elif field is None and (missions / f"{DEFAULT_MISSION}.yaml").exists():
        f = missions / f"{DEFAULT_MISSION}.yaml"
        data, origin = yaml.safe_load(f.read_text()), str(f)
    elif field is None:
        data, origin = dict(_EMBEDDED), f"embedded copy of missions/{DEFAULT_MISSION}.yaml"
    elif (missions / "north_atlantic.yaml").exists():  # another field on the ocean mission's settings
        f = missions / "north_atlantic.yaml"
        data, origin = yaml.safe_load(f.read_text()), str(f)
    else:
        raise UserError(f"--field {field}: missions/north_atlantic.yaml (its base mission) is not beside the package")
    src = (data.get("field") or {}).get("source") if isinstance(data.get("field"), dict) else data.get("field")
    if field is not None and field != src:
        import numpy as np

        from passt_mav.fields.datasets import resolve_field

        fl = resolve_field(field)
        data = dict(data)
        data["field"] = {
            "source": str(Path(field).resolve()) if not field.startswith("builtin:") else field,
            "velocity_scale": 1.0,
            "time_scale": 1.0,
        }
        data["region"] = fl.grid.describe()
        data["model"] = "persistence"
        water = np.argwhere(~fl.land_mask)
        if water.size == 0:
            raise UserError(f"field {field} has no water cell")
        centre = np.array(fl.grid.shape) / 2.0
        data["start_cell"] = [int(x) for x in water[np.argmin(((water - centre) ** 2).sum(axis=1))]]
        data["t0"] = 0
        origin += f" with field {field}"
    return data, origin


def _stamp() -> str:
    """Now in UTC for a run directory's name (``2026-01-01T12-00-00Z``)."""
    import datetime as _dt

    return _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H-%M-%SZ")


#: the demo's speed-up at most, and the field time a wall second may take at most (snapshots)
MAX_SPEEDUP = 150.0
SNAPSHOTS_PER_WALL_S = 0.625


def default_speedup(snapshot_s: float) -> float:
    """The demo's default speed-up for a field whose snapshots are ``snapshot_s`` seconds apart:
    :data:`MAX_SPEEDUP`, or less so that one wall second is at most :data:`SNAPSHOTS_PER_WALL_S` of a
    snapshot. In lockstep (one boat) it only paces the display. On the wall clock (a fleet, injected
    link drops) the controller plans and reconstructs in wall time while the simulated field runs on,
    so a faster simulator starts the legs later in field time than they were planned for; the bound
    keeps that lag a small part of a snapshot (50x on the oscillating wake's 80 s snapshots; the
    ocean's hourly snapshots keep 150x)."""
    return float(min(MAX_SPEEDUP, max(1.0, round(SNAPSHOTS_PER_WALL_S * float(snapshot_s)))))


def run(args: argparse.Namespace) -> int:
    """The demo (module docstring). SIGTERM, SIGINT or SIGHUP at any point end it cleanly: the mission as
    ``run`` ends it (the boat keeps station, summary.json ``stopped``), vehicle-sim and the view stopped, never
    left running; the exit code is 128 + the signal's number."""
    from passt_mav.vehicle.flow import Stopped
    from passt_mav.vehicle.signals import StopSignals, exit_code

    stop = StopSignals(echo=lambda s: print(s, flush=True))
    try:
        with stop:
            return _demo(args, stop)
    except Stopped as exc:  # before the mission began (the simulator starting, connecting): nothing flown
        print(f"demo: stopped by {exc.name} before the mission began; nothing flown", flush=True)
        return exit_code(exc.signum)


def _demo(args: argparse.Namespace, stop) -> int:
    import time
    from pathlib import Path

    from passt_mav.runs.rundir import RunDir

    drops = _drop_args(args.inject_link_drop, args.boats)
    data, config, over, origin = _demo_mission(args)
    grid = config.grid()
    rd = RunDir(args.out or Path("runs") / f"demo-{_stamp()}").create_fresh()
    from passt_mav.fields.datasets import mission_field

    t_start0 = time.monotonic()
    field = mission_field(config)  # the same rule as plan and run
    t_boot0 = float(field.times[config.t0])
    if args.speedup is None:
        args.speedup = default_speedup(float(field.dt) * float(config.field.time_scale))
    r0, c0 = config.start_cell or (grid.rows // 2, grid.cols // 2)
    hlat, hlon = (float(x) for x in grid.cell_to_latlon(r0, c0))
    port = _free_port(args.boats)
    fleet_args: list[str] = []
    if args.boats > 1:
        data, config, fleet_args = _as_fleet(data, config, field, (r0, c0), args.boats, port, origin)
    lockstep = STEP_S if args.boats == 1 and not drops else 0.0
    sim_cmd = _sim_command(args, config, port, fleet_args or ["--home", f"{hlat:.7f},{hlon:.7f}"], t_boot0, drops)
    if lockstep:
        sim_cmd.append("--lockstep")
    print(
        f"demo: mission {config.name} ({origin} + {over}); {config.legs} legs of {config.planner.path_length} moves "
        f"at {config.fleet[0].speed_mps} m/s",
        flush=True,
    )
    clock = f"in lockstep ({lockstep:g} s steps, paced at {args.speedup:g}x)" if lockstep else f"at {args.speedup:g}x"
    print(f"demo: starting vehicle-sim on tcp:127.0.0.1:{port} {clock}", flush=True)
    view = _start_view(args, rd)  # (it exits with this process too, whatever happens)
    fly = (args, config, data, rd, sim_cmd, port, t_boot0, over, origin, view, lockstep)
    summary = _fly_with_simulator(*fly, signals=stop)
    if summary["status"] == "stopped" and stop.received is not None:
        from passt_mav.vehicle.signals import exit_code

        print(f"demo: stopped after {len(summary['legs'])} legs; vehicle-sim stopped; run directory {rd.root}")
        return exit_code(stop.received)
    _print_outcome(args, config, field, summary, rd, view is not None, time.monotonic() - t_start0)
    return 0 if summary["status"] == "complete" else 1


def _sim_command(args: argparse.Namespace, config, port: int, placement: list[str], t_boot0: float, drops) -> list[str]:
    """The vehicle-sim command line of a demo: the mission's field replayed from ``t_boot0`` (field
    seconds) at ``args.speedup``, listening on ``tcp:127.0.0.1:port``, the boats placed by
    ``placement`` (``--home LAT,LON`` or the fleet's arguments), the mission's sensor noise and
    seed, the injected link drops."""
    import sys

    return [
        sys.executable,
        "-c",
        "import sys; from vehicle_sim.cli import main; sys.exit(main())",
        "--field",
        config.field.source,
        "--listen",
        f"tcp:127.0.0.1:{port}",
        *placement,
        "--start-time",
        repr(t_boot0),
        "--speedup",
        repr(args.speedup),
        "--param",
        f"WP_SPEED={config.fleet[0].speed_mps}",
        "--current-noise",
        repr(config.sensors.noise_std),
        "--current-rate",
        repr(SENSOR_RATE_HZ),
        "--seed",
        str(config.seeds.sensor),
        "--quiet",
        *sim_placement(config),
        *drops,
    ]


def _fly_with_simulator(
    args, config, data, rd, sim_cmd, port: int, t_boot0: float, over, origin, view, lockstep: float = 0.0, signals=None
) -> dict:
    """Start vehicle-sim (its output in the run directory's ``vehicle_sim.log``), fly the mission
    against it through :func:`passt_mav.commands.run.execute` (``lockstep`` > 0: the simulator is in
    lockstep, stepped that many simulated seconds at a time), and stop the simulator (and the live
    view) whatever happens (``signals``: the command's StopSignals, passed to the controller); returns the
    run's summary."""
    import contextlib
    import subprocess

    import yaml

    from passt_mav.commands.run import execute
    from passt_mav.mission.config import recorded_mission_text

    sim_log = open(rd.root / "vehicle_sim.log", "w")  # noqa: SIM115 - the simulator child writes it until it ends
    sim = None
    try:
        with signals.critical() if signals is not None else contextlib.nullcontext():
            sim = subprocess.Popen(sim_cmd, stdout=sim_log, stderr=subprocess.STDOUT)  # (a stop waits for `sim`)
        _wait_listening(port, sim, timeout=60.0)
        extra = {
            "demo": {
                "simulator": sim_cmd[3:],
                "overrides": over,
                "base_mission": origin,
                "sensor_rate_hz": SENSOR_RATE_HZ,
                "speedup": args.speedup,
                "lockstep_s": lockstep or None,
            }
        }
        summary = execute(
            config,
            connect=f"tcp:127.0.0.1:{port}",
            run_dir=rd,
            mission_text=recorded_mission_text(yaml.safe_dump(data, sort_keys=False), config),
            speedup=args.speedup,
            field_time_at_boot=t_boot0,
            echo=lambda s: print(s, flush=True),
            extra_summary=extra,
            report=not args.no_report,
            lockstep_s=lockstep,
            signals=signals,
        )
    finally:
        if view is not None:
            view.stop(grace_s=1.5)  # the page gets the last changes first
        if sim is not None:
            sim.terminate()
            try:
                sim.wait(timeout=10)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait()
        sim_log.close()
    return summary


def _demo_mission(args: argparse.Namespace):
    """The demo's mission after its checks and overrides: (mapping, MissionConfig, overrides, origin)."""
    from pathlib import Path

    from passt_mav.errors import UserError
    from passt_mav.mission.config import mission_overrides, validate_mission

    if (args.legs is not None and args.legs < 1) or (args.moves is not None and args.moves < 1):
        raise UserError("--legs and --moves must be >= 1")
    if not 1 <= args.boats <= 9:
        raise UserError("--boats must be 1..9")
    if args.speedup is not None and args.speedup <= 0:
        raise UserError("--speedup must be positive")
    base, origin = mission_mapping(args.mission, args.field)
    over = dict(DEMO_OVERRIDES)
    if args.mission is not None or args.field is not None:
        over.update(SHORT_LEGS)
    if args.legs is not None:
        over["legs"] = args.legs
    if args.moves is not None:
        over["planner.path_length"] = args.moves
    if args.model:
        over["model"] = args.model
    if getattr(args, "approve", False):
        over["approve.enabled"] = True
    data = mission_overrides(base, over)
    config = validate_mission(
        data, source="demo mission", base_dir=Path(origin).parent if origin.endswith(".yaml") else "."
    )
    return data, config, over, origin


def _print_outcome(args, config, field, summary: dict, rd, viewed: bool, wall: float) -> None:
    """The demo's last lines: status, final RMSE (against the counterfactual paths for one boat), report, view."""
    from passt_mav.units import speed_unit

    print(
        f"demo {summary['status']} in {wall:.0f} s: {len(summary['legs'])} legs, {summary['n_samples']} samples; "
        f"run directory {rd.root}",
        flush=True,
    )
    legs = summary["legs"]
    if legs and legs[-1].get("rmse_passt") is not None:
        lawn, walks = _counterfactual(config, field, summary, rd, report=not args.no_report, boats=args.boats)
        # the run's RMSEs are in the field's velocity units (the wake's: inflow = 1): shown in m/s
        ms = speed_unit(config.field.velocity_scale)
        line = final_line(
            ms(legs[-1]["rmse_passt"]), ms(legs[-1]["rmse_model"]), [ms(w) for w in walks], ms(lawn), boats=args.boats
        )
        print(line, flush=True)
        if args.boats > 1:
            print("boats: " + ", ".join(f"{b['boat']} {b['status']}" for b in summary.get("boats", [])), flush=True)
    if summary.get("report"):
        print(f"report: {summary['report']}", flush=True)
    if viewed:
        print(f"live view stopped; reopen it with: passt-mav view {rd.root}", flush=True)


def _start_view(args, rd):
    """The live view of the demo's run directory (None with --no-view or when it cannot start)."""
    from passt_mav.commands.view import start_live_view

    if args.no_view or args.view is None:
        return None
    return start_live_view(rd, args.view, args.view_host, echo=lambda s: print(f"demo: {s}", flush=True))


def _drop_args(specs: list[str], boats: int) -> list[str]:
    """vehicle-sim options of ``--inject-link-drop BOAT:START:DURATION``."""
    from passt_mav.errors import UserError

    out = []
    for spec in specs:
        parts = spec.split(":")
        try:
            b, start, dur = int(parts[0]), float(parts[1]), float(parts[2])
        except (IndexError, ValueError):
            raise UserError(f"--inject-link-drop needs BOAT:START:DURATION, got {spec!r}") from None
        if not 0 <= b < boats or start < 0 or dur <= 0 or len(parts) != 3:
            raise UserError(f"--inject-link-drop {spec}: BOAT must be 0..{boats - 1}, START >= 0, DURATION > 0")
        # counted from the arming, not the simulator's clock: how long the boats took to connect (the
        # machine's load) must not move the outage before the mission starts
        d = f"arm+{start:g}:{dur:g}"
        out += ["--boat-drop", f"{b}:{d}"] if boats > 1 else ["--drop", d]
    # a drop holds until the controller has noticed it and reconnected (the connection it interrupted stays
    # silent): on the wall clock a drop that ended while the controller waited inside a command's retries (a
    # loaded machine) went unnoticed, and a demo that injects one must show it
    return [*out, "--drops-break-link"] if out else out


def sim_placement(config) -> list[str]:
    """vehicle-sim options that put a metric field (the cylinder) where the mission places it and give
    its units (``--anchor/--rotation/--scale``, ``--velocity-scale/--time-scale``); none for a geographic one."""
    g = config.grid()
    if getattr(g, "kind", "") != "metric":
        return []
    return [
        "--anchor",
        f"{g.anchor_lat!r},{g.anchor_lon!r}",
        "--rotation",
        repr(g.rotation_deg),
        "--scale",
        repr(g.scale),
        "--velocity-scale",
        repr(float(config.field.velocity_scale)),
        "--time-scale",
        repr(float(config.field.time_scale)),
    ]


def _as_fleet(data: dict, config, field, start, boats: int, port: int, origin: str):
    """The demo mission as a fleet (``vehicles:``, one per boat on port + 10*i) and vehicle-sim's
    fleet options (--boats, --start-cell per boat)."""
    from pathlib import Path

    from passt_mav.mission.config import validate_mission

    cells = fleet_starts(config.grid(), field.land_mask, start, boats)
    veh = data.get("vehicle") or {}
    data = {k: v for k, v in data.items() if k != "vehicle"}
    data["vehicles"] = [
        {**veh, "connect": f"tcp:127.0.0.1:{port + 10 * i}", "start_cell": list(c)} for i, c in enumerate(cells)
    ]
    config = validate_mission(
        data, source="demo mission", base_dir=Path(origin).parent if origin.endswith(".yaml") else "."
    )
    args = ["--boats", str(boats)]
    for r, c in cells:
        lat, lon = (float(x) for x in config.grid().cell_to_latlon(r, c))
        args += ["--start", f"{lat:.7f},{lon:.7f}"]
    return data, config, args


def final_line(
    passt: float, model: float | None, walks: list[float | None] | None, lawn: float | None, *, boats: int = 1
) -> str:
    """The demo's last line (RMSE in m/s): PASST beside the model alone and the counterfactuals (a fleet: the
    random walks only; ``walks``: each walk's final RMSE, their mean compared), and in words which
    of the comparisons holds (PASST below the model alone, below the same-loop random walks' mean)
    and how many of the single walks PASST is below."""

    def f(x):
        return "n/a" if x is None else f"{x:.4f} m/s"

    done = [w for w in (walks or []) if w is not None]
    walk = sum(done) / len(done) if done and len(done) == len(walks) else None
    verdict = []
    for name, x in (("the model alone", model), ("the random walks' mean", walk)):
        if x is not None:
            # within 0.5 % is "level": a difference in the 4th digit is not a result
            word = (
                "level with"
                if abs(passt - x) <= 0.005 * max(abs(x), 1e-12)
                else ("below" if passt < x else "NOT below")
            )
            verdict.append(f"{word} {name}")
    if walk is not None:
        verdict[-1] += f" (below {sum(passt < w for w in done)} of the {len(done)} walks)"
        spread = f"{walk:.4f} m/s (mean of {len(done)}, {min(done):.4f}-{max(done):.4f})"
    else:
        spread = "n/a"
    if boats > 1:
        what = (
            f"final RMSE: PASST ({boats} boats) {passt:.4f} m/s, model alone {f(model)}, {boats} random walks "
            f"through the same model + GP {spread} (offline counterfactual, synchronous legs over the same span)"
        )
    else:
        what = (
            f"final RMSE: PASST {passt:.4f} m/s, model alone {f(model)}, random walk through the same model + GP "
            f"{spread}, lawnmower+GP {f(lawn)} (both offline counterfactuals over the same legs)"
        )
    return what + (f"; PASST is {' and '.join(verdict)}" if verdict else "")


def _fleet_starts(config, legs: list[dict]) -> list[tuple[int, int]]:
    """Each boat's first start cell (row, col): its first leg's, else where the mission starts it."""
    firsts: dict[int, tuple[int, int]] = {}
    for leg in legs:
        b = int(leg.get("boat", 0))
        if b not in firsts and leg.get("start_cell") is not None:
            firsts[b] = tuple(int(x) for x in leg["start_cell"])
    out = []
    for b, v in enumerate(config.fleet):
        cell = firsts.get(b) or v.start_cell or config.start_cell
        out.append(tuple(int(x) for x in (cell or (config.grid().rows // 2, config.grid().cols // 2))))
    return out


#: random walks set beside a demo run: one walk is one draw from a wide distribution
RANDOM_WALKS = 5


def _counterfactual(
    config, field, summary: dict, rd, *, report: bool, boats: int = 1
) -> tuple[float | None, list[float | None]]:
    """Lawnmower+GP (one boat), and :data:`RANDOM_WALKS` random walks through the run's own model +
    GP loop (a fleet: one per boat, synchronous legs), over the run's legs
    (passt_mav.analysis.counterfactual); stored in summary.json beside PASST and the model alone
    (``rmse.random``: the walks' mean per leg; ``counterfactual.random_walks``: each), and the report
    redrawn with them. Returns the lawnmower's last leg's RMSE (None for a fleet) and each walk's."""
    from passt_mav.analysis.counterfactual import fleet_rounds, lawnmower_counterfactual, same_loop_counterfactuals
    from passt_mav.loop.legstep import build_predictor

    legs = summary["legs"]
    r0, c0 = config.start_cell or (config.grid().rows // 2, config.grid().cols // 2)
    predictor, _ = build_predictor(config.model, field, echo=lambda s: None)
    s = rd.read_summary()
    s.setdefault("rmse", {})
    seeds = [config.seeds.planner + k for k in range(RANDOM_WALKS)]
    walks_of = f"{RANDOM_WALKS} walks (planner seeds {seeds[0]}-{seeds[-1]}; the 'random' curve is their mean)"
    if boats > 1:
        cf = None
        starts = _fleet_starts(config, legs)
        walks = same_loop_counterfactuals(config, field, predictor, legs, seeds=seeds, start_cells=starts)
        s["rmse"]["t_random"] = [t1 for _, t1 in fleet_rounds(legs)]
        how = (
            f"offline: {boats} random walks (keep-out rule) from the boats' first start cells, "
            "synchronous legs of the run's moves per leg spanning each round of the boats' legs, through "
            "the run's own model + GP loop (same model, GP options, sensor and GP seeds), all boats' samples "
            f"in one update per round, sampled from the true field with the mission's sensor noise; {walks_of}"
        )
        s["counterfactual"] = {}
    else:
        cf = lawnmower_counterfactual(
            field,
            legs,
            path_length=config.planner.path_length,
            start_cell=(r0, c0),
            noise_std=config.sensors.noise_std,
            seed=config.seeds.sensor,
            gp_seed=config.seeds.gp,
        )
        walks = same_loop_counterfactuals(config, field, predictor, legs, seeds=seeds, start_cell=(r0, c0))
        s["rmse"]["lawnmower"] = cf
        s["rmse"].setdefault("t", [x.get("t_end") for x in legs])
        how = (
            "offline: random-walk legs of the same length, start and field-time span through the run's own "
            "model + GP loop (same model, GP options, sensor and GP seeds), sampled from the true field with "
            f"the mission's sensor noise; {walks_of}"
        )
        s["counterfactual"] = {
            "lawnmower": cf,
            "how": "offline: lawnmower legs of the same length, start and field-time span, "
            "sampled from the true field with the mission's sensor noise, GP prior none",
        }
    mean = [
        None if any(w[j] is None for w in walks) else sum(w[j] for w in walks) / len(walks)
        for j in range(len(walks[0]))
    ]
    s["counterfactual"].update(random=mean, random_walks=walks, how_random=how)
    s["rmse"]["random"] = mean
    rd.write_summary(s)
    summary.update(rmse=s["rmse"], counterfactual=s["counterfactual"])
    if report:
        from passt_mav.analysis.report import write_report

        summary["report"] = str(write_report(rd.root))
    return (cf[-1] if cf else None), [w[-1] if w else None for w in walks]


def _wait_listening(port: int, proc, timeout: float) -> None:
    """Wait until the simulator accepts TCP connections (it generates the field first)."""
    import socket
    import time

    from passt_mav.errors import PasstError

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise PasstError(f"vehicle-sim exited with code {proc.returncode} before listening (see vehicle_sim.log)")
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise PasstError(f"vehicle-sim did not listen on port {port} within {timeout:.0f} s")
