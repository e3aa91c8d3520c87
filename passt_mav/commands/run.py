"""passt-mav run: Run a PASST mission on a vehicle (real or simulated) over MAVLink."""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

HELP = "Run a PASST mission on a vehicle (real or simulated) over MAVLink"
EXAMPLES = """examples:

    vehicle-sim --field builtin:ocean --listen tcp:127.0.0.1:5760 --speedup 300 &
    passt-mav run missions/north_atlantic.yaml --connect tcp:127.0.0.1:5760 --speedup-hint 300
    passt-mav run missions/cylinder.yaml --connect /dev/ttyUSB0,57600 --out runs/cyl1
    passt-mav run missions/cylinder.yaml --connect /dev/ttyUSB0,57600 --out runs/cyl1 --resume
    passt-mav run missions/cylinder.yaml --connect udpin:127.0.0.1:14551 --source-system 245 --source-component 195
    passt-mav run missions/cylinder.yaml --legs 1 --set planner.path_length=8 --set gp.background=0
    passt-mav run missions/rtofs.yaml --connect /dev/ttyUSB0,57600 --link-loss-window 900

exit codes: 0 complete; 1 paused, ended from the live page, or aborted (summary.json says why; continue with --resume);
2 bad input or no vehicle (nothing flown, nothing written: no run folder is left); 128 + N stopped by signal N (SIGINT 130, SIGTERM 143,
SIGHUP 129): the vehicle to HOLD (vehicle.on_signal), the store flushed, status "stopped".

    # the same numbers whatever the machine's load: the simulator's clock runs only while the controller waits
    vehicle-sim --field builtin:ocean --listen tcp:127.0.0.1:5760 --lockstep &
    passt-mav run missions/north_atlantic.yaml --connect tcp:127.0.0.1:5760 --lockstep 0.5 --speedup-hint 150

    # the cylinder missions place a CFD crop on the sea: give vehicle-sim the same placement
    vehicle-sim --field builtin:cylinder --anchor 40.2,-63.1 --scale 100 --velocity-scale 0.5 --time-scale 200 \
        --start-time 240 --listen tcp:127.0.0.1:5760 --speedup 50 &
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("mission", help="mission file (YAML, see missions/)")
    p.add_argument(
        "--connect",
        help="MAVLink connection: tcp:HOST:PORT, udpin:HOST:PORT, DEVICE,BAUD (default: the mission's vehicle.connect)",
    )
    p.add_argument(
        "--out", help="run directory (default runs/<UTC>_<mission name>); with --resume: the run to continue"
    )
    p.add_argument("--legs", type=int, help="number of legs (default: the mission's legs)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out after the controller stopped")
    p.add_argument(
        "--speedup-hint",
        type=float,
        default=1.0,
        help="simulated seconds per wall second of a simulator (scales wall-clock timeouts; default 1)",
    )
    p.add_argument(
        "--lockstep",
        type=float,
        default=0.0,
        metavar="STEP_S",
        help="the vehicle is a simulator served with vehicle-sim --lockstep: its clock runs only while the "
        "controller waits for it, STEP_S vehicle seconds at a time (e.g. 0.5), at most --speedup-hint x wall "
        "time, so the run does not depend on the machine's load; default 0: the vehicle keeps its own clock",
    )
    p.add_argument(
        "--field-time-at-boot",
        type=float,
        help="field time at vehicle boot, for simulators without a clock: field time = this + "
        "time_boot_ms/1000/field.time_scale (default: the mission's field.clock: the vehicle's UTC "
        "when it lies inside the field's snapshots, else snapshot t0)",
    )
    p.add_argument("--signing-key", help="MAVLink 2 signing passphrase or 64 hex digits")
    p.add_argument(
        "--link-loss-window",
        type=float,
        default=None,
        metavar="S",
        help="seconds of vehicle time a lost link is tried again (back-off capped, one line per attempt) while "
        "the vehicle flies its uploaded leg on, before the run stops for --resume (default: the mission's "
        "vehicle.link_loss_window_s, 600)",
    )
    p.add_argument(
        "--pause-timeout",
        type=float,
        default=300.0,
        help="wall seconds to wait for AUTO after a pilot takes over before stopping in HOLD (default 300)",
    )
    p.add_argument(
        "--ready-timeout",
        type=float,
        default=120.0,
        help="wall seconds to wait for the vehicle: its link (refused / unreachable / no heartbeat are "
        "retried with back-off, one line each) and then EKF/GPS (default 120)",
    )
    p.add_argument(
        "--source-system",
        type=int,
        default=None,
        help="our MAVLink system id (default: the mission's vehicle.source_system, else 245; not 255, "
        "QGroundControl's: see the manual, docs/real-boat.md)",
    )
    p.add_argument(
        "--source-component",
        type=int,
        default=None,
        help="our MAVLink component id (default: the mission's vehicle.source_component, else 195 "
        "MAV_COMP_ID_PATHPLANNER)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a mission key (dotted, YAML value), e.g. --set planner.path_length=8; repeatable; "
        "the run directory keeps the mission as flown",
    )
    p.add_argument(
        "--approve",
        action="store_true",
        help="approve each leg before its upload (mission key approve.enabled): on the live page (--view), or "
        "type a (approve) or r (reject) + Enter on this console; approve.timeout_s / on_timeout decide unanswered",
    )
    p.add_argument("--no-report", action="store_true", help="do not write report/report.html at the end")
    p.add_argument("--quiet", action="store_true", help="no per-leg status lines")
    from passt_mav.commands.view import add_view_options  # live view: --view [PORT], --view-host

    add_view_options(p)


def link_config_for(
    connect: str, *, speedup: float = 1.0, tlog=None, signing_key=None, identity=(None, None), lockstep_s: float = 0.0
):
    """LinkConfig for a vehicle running ``speedup`` x real time (the vehicle's 1 Hz telemetry then comes
    ``speedup`` times a second; our timeouts stay wall-clock). ``identity``: our (system, component) ids,
    None = the link's defaults (``passt_mav.mavlink.link.DEFAULT_SOURCE_SYSTEM``/``_COMPONENT``).
    ``lockstep_s`` > 0: a simulator in lockstep, stepped that many vehicle seconds at a time while we
    wait for it, paced at ``speedup`` (:class:`passt_mav.mavlink.link.Lockstep`)."""
    from passt_mav.mavlink import LinkConfig

    kw = {k: v for k, v in zip(("source_system", "source_component"), identity) if v is not None}
    if speedup > 1.0:
        # a simulator at 300x sends its ~15 default 1 Hz streams 4500 times a wall second: more than a
        # Python reader parses on a loaded core, and the reply to a mission request then comes later than
        # the vehicle's 8 s (simulated) transfer timeout. Ask only for what the controller uses.
        kw["stream_rates_hz"] = LEAN_STREAMS
    return LinkConfig(
        connect,
        tlog=None if tlog is None else str(tlog),
        signing_key=signing_key,
        connect_timeout_s=30.0,
        link_lost_s=5.0 if speedup <= 1.0 else 2.0,
        lockstep_s=float(lockstep_s),
        lockstep_pace=max(float(speedup), 1.0),
        **kw,
    )


#: telemetry the controller needs (Hz of vehicle time; 0 = off), used for fast simulators
LEAN_STREAMS = (
    ("GLOBAL_POSITION_INT", 1.0),
    ("MISSION_CURRENT", 1.0),
    ("EKF_STATUS_REPORT", 0.5),
    ("SYSTEM_TIME", 0.2),
    ("SYS_STATUS", 0),
    ("GPS_RAW_INT", 0),
    ("ATTITUDE", 0),
    ("VFR_HUD", 0),
    ("BATTERY_STATUS", 0),
    ("NAV_CONTROLLER_OUTPUT", 0),
    ("LOCAL_POSITION_NED", 0),
    ("POWER_STATUS", 0),
    ("MEMINFO", 0),
)


def execute(
    config,
    *,
    connect: str,
    run_dir,
    mission_text: str | None,
    legs=None,
    resume=False,
    speedup=1.0,
    field_time_at_boot=None,
    signing_key=None,
    pause_timeout=300.0,
    ready_timeout=120.0,
    echo=print,
    extra_summary=None,
    report=True,
    link_factory=None,
    identity=(None, None),
    progress=True,
    lockstep_s=0.0,
    signals=None,
    field=None,
) -> dict:
    """Everything ``run`` does after parsing: field, predictor, link, controller, report. Returns the summary.

    The mission is checked before any link is opened (:func:`~passt_mav.vehicle.controller.preflight`): a
    mission that cannot fly never touches the vehicle. ``signals``: the command's
    :class:`~passt_mav.vehicle.signals.StopSignals` (None: signals keep their default action).

    ``progress``: show the wait for a vehicle that is not ready yet (EKF/GPS; :mod:`passt_mav.progress`).
    ``lockstep_s`` > 0: the vehicle is a simulator in lockstep (``vehicle-sim --lockstep``), stepped that many
    vehicle seconds at a time while the controller waits for it (:func:`link_config_for`).
    ``identity``: our (system, component) ids from the command line; None = the mission's
    ``vehicle.source_system/source_component``, else the link's defaults.
    ``field``: the mission's field when the caller loaded it already (``run`` does, before it makes the run
    directory: :func:`~passt_mav.fields.datasets.mission_field`); None loads it here.
    """
    import sys

    from passt_mav.fields.datasets import mission_field, speed_warning
    from passt_mav.vehicle.controller import build_predictor, preflight

    if speedup > 1.0:
        # hand the GIL over faster (default 5 ms): a mission request must be answered within the
        # vehicle's 1 s re-request time, which a simulator at 150x compresses to ~7 ms of wall time
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.001))
    if field is None:
        field = mission_field(config, series=True)  # the same rule as plan, replay and report
    fast = speed_warning(field, config.field.source)
    if fast:
        print(f"warning: {fast}", file=sys.stderr)
    predictor, pinfo = build_predictor(config.model, field, echo=echo)
    preflight(config, field, predictor)
    opts = _RunOptions(
        mission_text=mission_text,
        legs=legs,
        speedup=speedup,
        field_time_at_boot=field_time_at_boot,
        signing_key=signing_key,
        pause_timeout=pause_timeout,
        ready_timeout=ready_timeout,
        echo=echo,
        extra_summary=extra_summary,
        link_factory=link_factory,
        identity=identity,
        progress=progress,
        lockstep_s=lockstep_s,
        signals=signals,
    )
    if config.vehicles is not None:
        if resume:
            raise _user("--resume is not supported for a fleet (vehicles:) yet")
        summary = _execute_fleet(config, run_dir, field, predictor, pinfo, opts)
    else:
        summary = _execute_boat(config, connect, run_dir, field, predictor, pinfo, opts, resume=resume)
    return _report(summary, run_dir, report)


@dataclasses.dataclass(frozen=True)
class _RunOptions:
    """The options of :func:`execute` that every link and controller of a run shares (timeouts in
    seconds of wall time)."""

    mission_text: str | None
    legs: Any
    speedup: float
    field_time_at_boot: Any
    signing_key: Any
    pause_timeout: float
    ready_timeout: float
    echo: Callable
    extra_summary: Any
    link_factory: Any
    identity: tuple
    progress: bool
    lockstep_s: float = 0.0
    signals: Any = None


def _link(connect: str, tlog, vc, factory, opts: _RunOptions):
    """A (not yet connected) MAVLink link to ``connect``, logging to ``tlog``, with our ids for vehicle
    entry ``vc`` (:func:`_identity`)."""
    from passt_mav.mavlink import Link

    return Link(
        link_config_for(
            connect,
            speedup=opts.speedup,
            tlog=tlog,
            signing_key=opts.signing_key,
            identity=_identity(opts.identity, vc),
            lockstep_s=opts.lockstep_s,
        ),
        connection_factory=factory,
    )


def _execute_boat(config, connect: str, run_dir, field, predictor, pinfo, opts: _RunOptions, *, resume) -> dict:
    """One boat (``vehicle:``): its link, a :class:`MissionController` run over it; returns the summary."""
    from passt_mav.vehicle.controller import MissionController

    link = _link(connect, run_dir.tlog, config.vehicle, opts.link_factory, opts)
    echo = opts.echo
    echo(f"connecting to {connect} as system {link.config.source_system} component {link.config.source_component} ...")
    link.connect(wait_s=opts.ready_timeout, say=echo)
    try:
        veh = _vehicle_for(link, opts.speedup, opts.progress)
        ctl = MissionController(
            config,
            link,
            run_dir,
            field=field,
            predictor=predictor,
            predictor_info=pinfo,
            vehicle=veh,
            legs=opts.legs,
            field_time_at_boot=opts.field_time_at_boot,
            speedup_hint=opts.speedup,
            pause_timeout_s=opts.pause_timeout,
            ready_timeout_s=opts.ready_timeout,
            resume=resume,
            echo=echo,
            mission_text=opts.mission_text,
            extra_summary=opts.extra_summary,
            signals=opts.signals,
        )
        return ctl.run()
    finally:
        link.close()


def _report(summary: dict, run_dir, report: bool) -> dict:
    if report:
        from passt_mav.analysis.report import write_report

        html = write_report(run_dir.root)
        summary["report"] = str(html)
    return summary


def _vehicle_for(link, speedup: float, progress: bool = True):
    from passt_mav.mavlink import MissionClient, Vehicle

    mc = MissionClient(link, no_space_delay_s=max(0.05, 1.0 / max(speedup, 1.0) ** 0.5))
    return Vehicle(link, mc, retry_delay_s=max(0.02, 1.0 / max(speedup, 1.0)), show_progress=progress)


def _execute_fleet(config, run_dir, field, predictor, pinfo, opts: _RunOptions) -> dict:
    """``vehicles:``: one link per boat (its own tlog), one :class:`FleetController`."""
    from passt_mav.vehicle.fleet_controller import FleetController

    links = []
    try:
        for k, vc in enumerate(config.fleet):
            factory = None if opts.link_factory is None else (lambda f=opts.link_factory, c=vc.connect: f(c))
            link = _link(vc.connect, run_dir.boat_tlog(k), vc, factory, opts)
            opts.echo(f"boat {k}: connecting to {vc.connect} ...")
            links.append(link.connect(wait_s=opts.ready_timeout, say=opts.echo))
        fleet = FleetController(
            config,
            links,
            run_dir,
            field=field,
            predictor=predictor,
            predictor_info=pinfo,
            vehicles=[_vehicle_for(x, opts.speedup, opts.progress) for x in links],
            legs=opts.legs,
            echo=opts.echo,
            mission_text=opts.mission_text,
            extra_summary=opts.extra_summary,
            field_time_at_boot=opts.field_time_at_boot,
            speedup_hint=opts.speedup,
            pause_timeout_s=opts.pause_timeout,
            ready_timeout_s=opts.ready_timeout,
        )
        return fleet.run()
    finally:
        for link in links:
            link.close()


def _identity(cli: tuple, vc) -> tuple:
    """Our (system, component) ids for one boat: the command line's, else its mission entry's
    (``vehicle.source_system/source_component``); None left = the link's defaults."""
    return (cli[0] if cli[0] is not None else vc.source_system, cli[1] if cli[1] is not None else vc.source_component)


def _with_overrides(path, text: str, pairs: list[str]):
    """(config, text) of the mission file ``path`` with ``--set KEY=VALUE`` overrides (dotted keys,
    values parsed as YAML); the text is what the run directory keeps."""
    from pathlib import Path

    import yaml

    from passt_mav.mission.config import mission_overrides, validate_mission

    over = {}
    for kv in pairs:
        key, sep, val = kv.partition("=")
        if not sep or not key.strip():
            raise _user(f"--set needs KEY=VALUE (e.g. planner.path_length=8), got {kv!r}")
        try:
            over[key.strip()] = yaml.safe_load(val)
        except (yaml.YAMLError, RecursionError):
            raise _user(f"--set {key}: the value {val[:60]!r} is not valid YAML") from None
    data = mission_overrides(yaml.safe_load(text), over)
    try:
        config = validate_mission(data, source=f"{path} with --set", base_dir=Path(path).parent)
    except RecursionError:
        raise _user(f"--set: the mission {path} with --set is nested too deep") from None
    return config, yaml.safe_dump(data, sort_keys=False)


def _user(msg):
    from passt_mav.errors import UserError

    return UserError(msg)


def _check_view_port(args) -> None:
    """``--view PORT`` (not optional) on a port already taken: one line, before anything is written or connected."""
    if args.view is None or getattr(args, "view_optional", False):
        return
    from passt_mav.view import check_port

    try:
        check_port(args.view_host, args.view)
    except OSError as exc:
        raise _user(
            f"--view: {exc}; choose another port (or --view {args.view},optional to fly without the view)"
        ) from None


def _live_view(args, rd):
    """``--view [PORT][,optional]``: the live view in a subprocess (passt_mav.view), None without it (or, when
    optional, when it cannot start)."""
    if args.view is None:
        return None
    from passt_mav.commands.view import start_live_view

    return start_live_view(rd, args.view, args.view_host, required=not getattr(args, "view_optional", False))


def _checked_mission(args: argparse.Namespace):
    """(config, mission text) of ``run``'s mission file with the command line's overrides, every option checked:
    a bad one is one line before anything is written or connected. The text is what the run directory keeps,
    its relative paths made absolute (:func:`~passt_mav.mission.config.recorded_mission_text`)."""
    from passt_mav.mission.config import load_mission, recorded_mission_text

    recorded = _recorded_mission(args) if args.resume else None
    if recorded is None:
        config = load_mission(args.mission)
        mission_text = Path(args.mission).read_text()
    else:
        config, mission_text = recorded
    if args.set:
        config, mission_text = _with_overrides(args.mission, mission_text, args.set)
        if recorded is not None and not args.quiet:
            print(f"resume: changed by --set: {', '.join(args.set)}", flush=True)
    mission_text = recorded_mission_text(mission_text, config)
    if args.legs is not None and args.legs < 1:
        raise _user("--legs must be >= 1")
    if not 0 <= args.ready_timeout <= 86_400:  # (NaN or 1e20 would wait for the vehicle for ever)
        raise _user(f"--ready-timeout must be 0..86400 seconds (a day), got {args.ready_timeout:g}")
    if not args.lockstep >= 0:
        raise _user(f"--lockstep must be >= 0 vehicle seconds, got {args.lockstep}")
    if args.lockstep and config.vehicles is not None:
        raise _user("--lockstep flies one boat: a fleet's boats would step one shared simulator clock each")
    if args.connect and config.vehicles is not None:
        raise _user("--connect names one vehicle; a fleet's connections are in the mission's vehicles:")
    for name in ("source_system", "source_component"):
        v = getattr(args, name)
        if v is not None and not 1 <= v <= 255:
            raise _user(f"--{name.replace('_', '-')} must be 1..255, got {v}")
    if args.link_loss_window is not None:
        if not args.link_loss_window > 0:
            raise _user(f"--link-loss-window must be > 0 seconds, got {args.link_loss_window:g}")
        vehicle = config.vehicle.model_copy(update={"link_loss_window_s": float(args.link_loss_window)})
        config = config.model_copy(update={"vehicle": vehicle})
    if args.approve:
        config = config.model_copy(update={"approve": config.approve.model_copy(update={"enabled": True})})
    return config, mission_text


def _recorded_mission(args: argparse.Namespace):
    """``--resume``: (config, text) of the mission the run was flying, from its summary.json: ``config`` (the mission
    as validated, with ``--approve`` and ``--link-loss-window`` in it) and ``legs_planned`` (into ``args.legs``
    unless ``--legs`` is given), so that approve mode, the leg count and the budget go on as they were; the
    mission file named on the command line is not read again (said on the console). None when the run
    has no summary yet (its first session stopped before writing one): the mission file is read as for a new run."""
    import yaml

    from passt_mav.mission.config import validate_mission
    from passt_mav.runs.rundir import RunDir, RunDirError

    rd = RunDir(args.out or ".")
    summary = rd.summary_file
    try:
        rec = rd.read_summary()
    except (RunDirError, OSError):
        return None
    data = rec.get("config")
    if not isinstance(data, dict):
        return None
    config = validate_mission(data, source=str(summary), base_dir=summary.parent)
    if args.legs is None and isinstance(rec.get("legs_planned"), int) and rec["legs_planned"] >= 1:
        args.legs = rec["legs_planned"]
    if not args.quiet:
        ap = "on" if config.approve.enabled else "off"
        print(
            f"resume: the run's own mission from {summary} (approve {ap}, {args.legs or config.legs} legs, the "
            f"same budget); {args.mission} is not read again: --set KEY=VALUE or --legs N change it",
            flush=True,
        )
    return config, yaml.safe_dump(data, sort_keys=False)


def _open_run_dir(args: argparse.Namespace, config):
    """(run directory, the outermost folder this command made for it or None): ``--out`` continued with
    ``--resume``, ``--out`` made fresh, or ``runs/<UTC>_<mission name>``."""
    from passt_mav.runs.rundir import RunDir

    if args.resume:
        if not args.out:
            raise _user("--resume needs --out RUN_DIR (the run to continue)")
        rd = RunDir(args.out)
        if not rd.is_run_dir():
            raise _user(f"--resume: {args.out} is not a run directory")
        return rd, None
    if args.out:
        made = _new_folder(Path(args.out))
        return RunDir(args.out).create_fresh(), made
    made = _new_folder(Path("runs"))
    rd = RunDir.new("runs", config.name)
    return rd, made or rd.root.absolute()


def run(args: argparse.Namespace) -> int:
    import sys

    config, mission_text = _checked_mission(args)
    _check_view_port(args)
    from passt_mav.fields.datasets import mission_field

    field = mission_field(config, series=True)  # checked before the run directory is made or a link opened
    rd, made = _open_run_dir(args, config)
    echo = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    from passt_mav.errors import MavlinkError, UserError
    from passt_mav.vehicle.flow import Stopped
    from passt_mav.vehicle.signals import StopSignals, exit_code

    try:
        view = _live_view(args, rd)
    except UserError:
        if not args.resume:
            _discard_unflown(rd.root, made)
        raise
    if config.approve.enabled and sys.stdin is not None and sys.stdin.isatty():
        from passt_mav.runs.commands import start_console_keys

        start_console_keys(rd.root, sys.stdin)  # a / r + Enter: approve or reject the leg awaiting approval
    stop = StopSignals(echo=lambda s: print(s, flush=True))
    try:
        with stop:
            summary = execute(
                config,
                connect=args.connect or config.vehicle.connect,
                run_dir=rd,
                mission_text=mission_text,
                legs=args.legs,
                resume=args.resume,
                speedup=args.speedup_hint,
                field_time_at_boot=args.field_time_at_boot,
                signing_key=args.signing_key,
                pause_timeout=args.pause_timeout,
                ready_timeout=args.ready_timeout,
                echo=echo,
                report=not args.no_report,
                identity=(args.source_system, args.source_component),
                progress=not args.quiet,
                lockstep_s=args.lockstep,
                signals=stop,
                field=field,
            )
    except (Stopped, UserError, MavlinkError) as exc:
        # before the mission began (no vehicle, the field or model refused, a signal) nothing stays behind;
        # a mission that began keeps its records (_discard_unflown)
        _stop_view(view)
        view = None
        if not args.resume:
            _discard_unflown(rd.root, made)
        if not isinstance(exc, Stopped):
            raise
        print(f"passt-mav: stopped by {exc.name} before the mission began; nothing flown", flush=True)
        return exit_code(exc.signum)
    finally:
        _stop_view(view)
    return _outcome(summary, rd, stop)


def _stop_view(view) -> None:
    """Stop the live view subprocess (None: none runs)."""
    if view is not None:
        view.stop(grace_s=1.5)


def _outcome(summary: dict, rd, stop) -> int:
    """Say how the run ended (one line, the readings used, the report) and return the exit code."""
    from passt_mav.vehicle.signals import exit_code

    print(f"run {summary['status']}: {len(summary['legs'])} legs, {summary['n_samples']} samples -> {rd.root}")
    used = [f"{100 * x:.0f} %" for x in summary.get("readings_used") or [] if x is not None]
    bps = [f"{x:.0f}" for x in summary.get("link_vehicle_bytes_per_s") or [] if x is not None]
    if used or bps:  # the sensor readings placed on the track, and the link budget the vehicle used
        print(f"readings used per leg: {', '.join(used) or '-'}; the vehicle sent {', '.join(bps) or '-'} B/s per leg")
    if summary.get("report"):
        print(f"report: {summary['report']}")
    if summary["status"] == "stopped" and stop.received is not None:
        return exit_code(stop.received)
    return 0 if summary["status"] == "complete" else 1


def _new_folder(path) -> Path | None:
    """The outermost folder of ``path`` (``path`` itself included) that does not exist yet: the one making
    ``path`` creates; None when ``path`` exists."""
    made = None
    for p in (Path(path).absolute(), *Path(path).absolute().parents):
        if p.exists():
            break
        made = p
    return made


#: what ``run`` writes into a run directory before the mission begins: the telemetry logs of its
#: connection attempts and the live view's log (a folder holding only these holds no run)
_BEFORE_THE_MISSION = ("flight.tlog", "flight_boat*.tlog", "view.log")


def _discard_unflown(root, made) -> None:
    """Undo what ``run`` wrote into the run directory ``root`` when its mission never began (no vehicle, a
    refused field or model, a signal while connecting): the files of :data:`_BEFORE_THE_MISSION` and
    ``legs/``, then ``root`` itself and the empty folders above it up to ``made``, the outermost folder this
    command made (None: ``root`` was there before and stays). A directory that holds a run record (the
    mission, a summary, samples, a leg) is left as it is."""
    from passt_mav.runs.rundir import RunDir

    rd = RunDir(Path(root).absolute())
    if not rd.root.is_dir() or rd.leg_indices():
        return
    if any(p.exists() for p in (rd.mission_file, rd.summary_file, rd.samples_db)):
        return
    for pattern in _BEFORE_THE_MISSION:
        for p in rd.root.glob(pattern):
            p.unlink(missing_ok=True)
    _remove_empty(rd.legs_dir)
    if made is None:
        return
    p = rd.root
    while _remove_empty(p) and p != Path(made) and p.parent != p:
        p = p.parent


def _remove_empty(folder) -> bool:
    """Remove ``folder`` if it is an empty directory; True when it is gone."""
    try:
        folder.rmdir()
    except OSError:
        return not folder.exists()
    return True
