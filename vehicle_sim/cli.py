"""``vehicle-sim``: serve a simulated ArduPilot Rover boat over MAVLink.

Examples::

    vehicle-sim --field builtin:ocean --listen tcp:127.0.0.1:5760 --speedup 10
    vehicle-sim --field currents.nc --home 40.1,-63.0 --listen tcp:127.0.0.1:5760 \\
        --listen udpout:127.0.0.1:14550 --loss 0.1 --baud 57600 --tlog sim.tlog
    vehicle-sim --field builtin:cylinder --anchor 40,-63 --scale 200 --velocity-scale 0.5 \\
        --time-scale 20 --listen tcp:127.0.0.1:5760
    vehicle-sim --field currents.nc --start-time 2024-05-01T06:00:00Z --utc-at-boot field \\
        --gps-noise 2 --current-noise 0.02 --seed 1
    vehicle-sim --field builtin:ocean --boats 3 --speedup 10     # boats on 5760, 5770, 5780; sysids 1, 2, 3
    vehicle-sim --field builtin:ocean --boats 2 --base-port 6000 --start 40.1,-63.0 --start 40.2,-62.8 \\
        --boat-param 1:FS_GCS_ENABLE=1 --boat-drop 1:300:60

Several boats (--boats N): one process, one current field, one clock; boat I (0..N-1, like
SITL's -I I) listens on every --listen port + 10*I (default tcp:127.0.0.1:5760 + 10*I),
has system id I+1 (parameter MAV_SYSID), its own autopilot, mission, modes and arming, and
starts at its --start/--start-cell, else 20 m apart east of --home, else spread over the
field's region. In --lockstep, a 31010 command to any boat advances all.
--tlog NAME.tlog writes NAME-<sysid>.tlog per boat.

Bad input exits with code 2 and a one-line message; Ctrl-C exits cleanly (0).
"""

from __future__ import annotations

import argparse
import signal
import sys
import time

EXAMPLES = __doc__.split("Examples::", 1)[1].split("Bad input", 1)[0]


class _Bad(Exception):
    pass


def _latlon(s: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in s.split(","))
    except ValueError:
        raise _Bad(f"{what} must be LAT,LON in degrees, got {s!r}") from None
    if not (-90 <= a <= 90 and -180 <= b <= 180):
        raise _Bad(f"{what} out of range: {s!r}")
    return a, b


def _drop(s: str) -> tuple[bool, float, float]:
    """``START:DURATION`` (seconds on the simulator's clock) or ``arm+START:DURATION`` (seconds after the
    vehicle first arms) -> (after_arm, start, duration)."""
    after_arm = s.startswith("arm+")
    try:
        a, b = (float(x) for x in s.removeprefix("arm+").split(":"))
    except ValueError:
        raise _Bad(f"--drop must be START:DURATION or arm+START:DURATION in seconds, got {s!r}") from None
    if a < 0 or b <= 0:
        raise _Bad(f"--drop needs START >= 0 and DURATION > 0, got {s!r}")
    return after_arm, a, b


def _split_drops(drops) -> dict:
    """LinkConfig keywords of parsed drops: ``drops`` (clock) and ``arm_drops`` (after the first arming)."""
    return {
        "drops": tuple((a, b) for arm, a, b in drops if not arm),
        "arm_drops": tuple((a, b) for arm, a, b in drops if arm),
    }


def _boat_prefixed(s: str, what: str, n: int) -> tuple[int, str]:
    """``I:REST`` of a per-boat option -> (boat index 0..n-1, REST)."""
    i, sep, rest = s.partition(":")
    try:
        idx = int(i)
    except ValueError:
        idx = -1
    if not sep or not rest or idx < 0:
        raise _Bad(f"{what} must start with a boat index I: (0..{n - 1}), got {s!r}")
    if idx >= n:
        raise _Bad(f"{what} {s!r}: no boat {idx} among --boats {n} (boats are numbered 0..{n - 1})")
    return idx, rest


def _param_kv(kv: str, what: str) -> tuple[str, float]:
    if "=" not in kv:
        raise _Bad(f"{what} must be NAME=VALUE, got {kv!r}")
    k, v = kv.split("=", 1)
    try:
        return k.strip().upper(), float(v)
    except ValueError:
        raise _Bad(f"{what} {k} value must be a number, got {v!r}") from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vehicle-sim",
        description="An ArduPilot-Rover-compatible MAVLink boat simulator drifting in a replayed current field.",
        epilog="examples:" + EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--field",
        default=None,
        help="FILE.nc | builtin:ocean | builtin:cylinder | builtin:oscillating | none (still water)",
    )
    p.add_argument("--home", default=None, help="start/home LAT,LON (default: centre of the field's region)")
    p.add_argument(
        "--listen",
        action="append",
        default=None,
        help="tcp:HOST:PORT, udpin:HOST:PORT or udpout:HOST:PORT; repeatable (default tcp:127.0.0.1:5760); "
        "with --boats, boat I gets PORT + 10*I",
    )
    p.add_argument(
        "--boats",
        type=int,
        default=1,
        help="number of boats N (default 1): boat I on port + 10*I with system id I+1, all in one field and clock",
    )
    p.add_argument(
        "--base-port",
        type=int,
        default=None,
        help="boat 0's TCP port (boat I: BASE + 10*I), i.e. --listen tcp:127.0.0.1:BASE; 0 = OS-chosen ports (printed)",
    )
    p.add_argument(
        "--start",
        action="append",
        default=[],
        help="a boat's start/home LAT,LON; repeatable, once per boat (default: spread over the field's region)",
    )
    p.add_argument(
        "--start-cell",
        action="append",
        default=[],
        help="a boat's start as ROW,COL of the field's grid (cell centre; row 0 = south); repeatable, once per boat",
    )
    p.add_argument(
        "--boat-param",
        action="append",
        default=[],
        help="I:NAME=VALUE parameter of boat I only (after --param); repeatable; I:MAV_SYSID=S sets its system id",
    )
    p.add_argument(
        "--boat-drop",
        action="append",
        default=[],
        help="I:START:DURATION link outage of boat I only (sim seconds; I:arm+START:DURATION counts START from "
        "the boat's first arming); repeatable",
    )
    p.add_argument(
        "--region", default=None, help="crop the field to SOUTH,WEST,NORTH,EAST degrees (default: whole grid)"
    )
    p.add_argument(
        "--velocity-scale", type=float, default=None, help="m/s per field velocity unit (metric fields; default 1)"
    )
    p.add_argument(
        "--time-scale", type=float, default=None, help="seconds per field time unit (metric fields; default 1)"
    )
    p.add_argument("--anchor", default=None, help="LAT,LON of a metric field's centre (re-anchors it)")
    p.add_argument("--scale", type=float, default=None, help="Earth metres per data metre of a metric field")
    p.add_argument("--rotation", type=float, default=None, help="counter-clockwise rotation of a metric field, degrees")
    p.add_argument(
        "--start-time",
        default=None,
        help="field time at boot: a number in the field's time units, or an ISO UTC time for geographic fields (default: first snapshot)",
    )
    p.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="time stands still until a GCS sends COMMAND_LONG 31010 (MAV_CMD_USER_1) with param1 = seconds to run",
    )
    p.add_argument(
        "--no-wait",
        action="store_true",
        help="start the clock at once (default with a tcp listener: hold it until the first TCP client connects, like SITL)",
    )
    p.add_argument("--loss", type=float, default=0.0, help="frame loss probability each way (0..1)")
    p.add_argument("--latency", type=float, default=0.0, help="one-way latency, simulated seconds")
    p.add_argument("--baud", type=int, default=0, help="emulate a serial radio of this many bit/s (0 = unlimited)")
    p.add_argument(
        "--radio-buffer",
        type=int,
        default=0,
        help="the radio's transmit buffer, bytes: a frame that does not fit is dropped (0 = no limit; "
        "a SiK radio: 2048). A SiK-like radio: --baud 57600 --latency 0.1 --loss 0.03 --radio-buffer 2048",
    )
    p.add_argument(
        "--drop",
        action="append",
        default=[],
        help="scheduled link outage START:DURATION (sim seconds since the clock started) or arm+START:DURATION "
        "(since the vehicle first armed: the same moment of the mission however long a client took to connect); "
        "repeatable",
    )
    p.add_argument(
        "--drops-break-link",
        action="store_true",
        help="a drop also ends the connections it interrupts: they stay silent after it until the ground station "
        "reconnects (a modem that lost its session), so a drop is always noticed",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of link loss and sensor noise")
    p.add_argument("--current-noise", type=float, default=0.0, help="std of Gaussian noise on CUR_U/CUR_V, m/s")
    p.add_argument("--current-rate", type=float, default=1.0, help="CUR_U/CUR_V rate, Hz of simulated time (0 = off)")
    p.add_argument(
        "--gps-noise",
        type=float,
        default=0.0,
        help="std of the reported position's error, m per axis (Gauss-Markov, 60 s correlation; seeded by --seed)",
    )
    p.add_argument(
        "--utc-at-boot",
        default=None,
        help="UTC of the vehicle clock at boot (SYSTEM_TIME): an ISO time, 'field' (the field's time at "
        "--start-time, so a controller mapping UTC samples the same hour), or 'none' (no clock: "
        "time_unix_usec stays 0); default: now",
    )
    p.add_argument(
        "--nav",
        choices=("pursuit", "crosstrack"),
        default="pursuit",
        help="pursuit: crab not compensated (default); crosstrack: hold the line like L1",
    )
    p.add_argument("--param", action="append", default=[], help="NAME=VALUE initial parameter; repeatable")
    p.add_argument("--signing-key", default=None, help="MAVLink 2 signing: 64 hex digits or a passphrase (sha256)")
    p.add_argument("--tlog", default=None, help="write a .tlog of everything sent and received")
    p.add_argument("--fast-boot", action="store_true", help="compress the boot timeline (ready in ~2 s)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many simulated seconds")
    p.add_argument("--quiet", action="store_true", help="no status lines on stderr")
    return p


def _load_field(args):
    if args.field in (None, "none"):
        return None
    from passt_mav.fields.datasets import resolve_field, speed_warning

    try:
        field = resolve_field(args.field, seed=args.seed, series=True)  # checked before anything listens
    except ImportError as exc:
        raise _Bad(f"field {args.field!r} is not available in this installation ({exc})") from None
    fast = speed_warning(field, args.field)
    if fast:
        print(f"vehicle-sim: warning: {fast}", file=sys.stderr)
    g = field.grid
    if any(v is not None for v in (args.anchor, args.scale, args.rotation)):
        if field.is_geographic:
            raise _Bad("--anchor/--scale/--rotation apply to metric (cylinder) fields only")
        import geo

        lat, lon = _latlon(args.anchor, "--anchor") if args.anchor else (g.anchor_lat, g.anchor_lon)
        grid = geo.MetricRegionGrid(
            g.x0,
            g.x1,
            g.y0,
            g.y1,
            g.rows,
            g.cols,
            anchor_lat=lat,
            anchor_lon=lon,
            rotation_deg=g.rotation_deg if args.rotation is None else args.rotation,
            scale=g.scale if args.scale is None else args.scale,
        )
        from passt_mav.fields.field import FlowField

        field = FlowField(field.data, grid, field.times, field.time_origin, field.units, field.attrs)
    if args.region:
        try:
            s, w, n, e = (float(x) for x in args.region.split(","))
        except ValueError:
            raise _Bad(f"--region must be SOUTH,WEST,NORTH,EAST, got {args.region!r}") from None
        import numpy as np

        lats, lons = field.grid.centres_latlon()
        inside = (lats >= s) & (lats <= n) & (lons >= w) & (lons <= e)
        rows = np.where(inside.any(axis=1))[0]
        cols = np.where(inside.any(axis=0))[0]
        if rows.size < 2 or cols.size < 2:
            raise _Bad(f"--region {args.region} keeps fewer than 2x2 cells of the field")
        field = field.isel(rows=slice(int(rows[0]), int(rows[-1]) + 1), cols=slice(int(cols[0]), int(cols[-1]) + 1))
    return field


def _start_time(value, field) -> float | None:
    if value is None:
        return None
    try:
        return float(value)
    except ValueError:
        pass
    if field is None or field.time_origin is None:
        raise _Bad(f"--start-time {value!r}: an ISO time needs a geographic field with a time origin")
    import datetime as dt

    try:
        t = dt.datetime.fromisoformat(value)
        t0 = dt.datetime.fromisoformat(field.time_origin)
    except ValueError:
        raise _Bad(f"--start-time must be a number or an ISO time, got {value!r}") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    if t0.tzinfo is None:
        t0 = t0.replace(tzinfo=dt.UTC)
    sec = (t - t0).total_seconds()
    if not field.times[0] <= sec <= field.times[-1]:
        raise _Bad(f"--start-time {value} lies outside the field's time range")
    return sec


def _utc_at_boot(value, field, start: float | None, time_scale: float) -> float | None:
    """Simulator ``epoch0`` (UTC epoch seconds at boot) from ``--utc-at-boot``; None = now (or no clock)."""
    if value is None or value.strip().lower() == "none":
        return None
    import datetime as dt

    if value.strip().lower() == "field":
        if field is None or field.time_origin is None:
            raise _Bad("--utc-at-boot field needs a geographic field with a time origin")
        if time_scale != 1.0:
            raise _Bad("--utc-at-boot field needs a field in seconds (--time-scale 1)")
        t0 = dt.datetime.fromisoformat(field.time_origin)
        t0 = t0 if t0.tzinfo else t0.replace(tzinfo=dt.UTC)
        return t0.timestamp() + (float(field.times[0]) if start is None else start)
    try:
        t = dt.datetime.fromisoformat(value)
    except ValueError:
        raise _Bad(f"--utc-at-boot must be an ISO UTC time, 'field' or 'none', got {value!r}") from None
    return (t if t.tzinfo else t.replace(tzinfo=dt.UTC)).timestamp()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except _Bad as exc:
        print(f"vehicle-sim: error: {exc}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        # UserError/GeoError are ValueErrors; OSError: a port in use, an unreadable file
        print(f"vehicle-sim: error: {exc}", file=sys.stderr)
        return 2


def _starts(args, field, n: int) -> list[tuple[float, float]]:
    """Each boat's start/home (lat, lon) from --home / --start / --start-cell / the field."""
    if args.start and args.start_cell:
        raise _Bad("give --start or --start-cell, not both")
    if args.home and (args.start or args.start_cell):
        raise _Bad("give --home or --start/--start-cell, not both")
    given = args.start or args.start_cell
    if given and len(given) != n:
        opt = "--start" if args.start else "--start-cell"
        raise _Bad(f"{opt} given {len(given)} times for --boats {n}: give it once per boat")
    if args.start:
        return [_latlon(s, "--start") for s in args.start]
    if args.start_cell:
        if field is None:
            raise _Bad("--start-cell needs a field")
        R, C = field.grid.shape
        out = []
        for s in args.start_cell:
            try:
                r, c = (float(x) for x in s.split(","))
            except ValueError:
                raise _Bad(f"--start-cell must be ROW,COL, got {s!r}") from None
            if not (0 <= r <= R - 1 and 0 <= c <= C - 1):
                raise _Bad(f"--start-cell {s} lies outside the field's {R}x{C} grid")
            lat, lon = field.grid.fcell_to_latlon(r, c)
            out.append((float(lat), float(lon)))
        return out
    from vehicle_sim.fleet import line_starts, spread_starts

    if args.home:
        home = _latlon(args.home, "--home")
        return [home] if n == 1 else line_starts(home, n)
    if field is None:
        raise _Bad("--home LAT,LON is required without a field")
    if n == 1:
        g = field.grid
        lat, lon = g.fcell_to_latlon((g.rows - 1) / 2.0, (g.cols - 1) / 2.0)
        return [(float(lat), float(lon))]
    return spread_starts(field, n)


def _run(args) -> int:
    from vehicle_sim.boat import BoatParams
    from vehicle_sim.config import LinkConfig, SimConfig
    from vehicle_sim.link import parse_link_spec, secret_from_key
    from vehicle_sim.sim import Simulator

    if args.radio_buffer < 0:
        raise _Bad(f"--radio-buffer must be >= 0, got {args.radio_buffer}")
    if not 0 <= args.loss < 1:
        raise _Bad(f"--loss must be in [0, 1), got {args.loss}")
    if args.speedup <= 0:
        raise _Bad(f"--speedup must be positive, got {args.speedup}")
    n = args.boats
    if not 1 <= n <= 100:
        raise _Bad(f"--boats must be 1..100, got {n}")
    if args.base_port is not None:
        if args.listen:
            raise _Bad("give --base-port or --listen, not both")
        if not 0 <= args.base_port < 65536:
            raise _Bad(f"--base-port out of range: {args.base_port}")
        listen = [f"tcp:127.0.0.1:{args.base_port}"]
    else:
        listen = args.listen or ["tcp:127.0.0.1:5760"]
    for spec in listen:
        try:
            _, _, port = parse_link_spec(spec)
        except ValueError as exc:
            raise _Bad(str(exc)) from None
        if port and port + 10 * (n - 1) > 65535:
            raise _Bad(f"{spec}: boat {n - 1}'s port {port + 10 * (n - 1)} would be out of range")
    params = [_param_kv(kv, "--param") for kv in args.param]
    boat_params: list[list[tuple[str, float]]] = [[] for _ in range(n)]
    for s in args.boat_param:
        i, kv = _boat_prefixed(s, "--boat-param", n)
        boat_params[i].append(_param_kv(kv, "--boat-param"))
    boat_drops: list[list[tuple[bool, float, float]]] = [[] for _ in range(n)]
    for s in args.boat_drop:
        i, d = _boat_prefixed(s, "--boat-drop", n)
        boat_drops[i].append(_drop(d))
    if n > 1 and any(k == "MAV_SYSID" for k, _ in params):
        raise _Bad("--param MAV_SYSID would give every boat the same system id; use --boat-param I:MAV_SYSID=S")
    field = _load_field(args)
    starts = _starts(args, field, n)
    home = starts[0]
    vs = args.velocity_scale if args.velocity_scale is not None else 1.0
    ts = args.time_scale if args.time_scale is not None else 1.0
    if vs <= 0 or ts <= 0:
        raise _Bad("--velocity-scale and --time-scale must be positive")
    from vehicle_sim.autopilot import DEFAULT_PARAMS

    for k, _ in params + [kv for bp in boat_params for kv in bp]:
        if k not in DEFAULT_PARAMS:
            raise _Bad(f"unknown parameter {k!r} in --param")
    base = SimConfig.fast() if args.fast_boot else SimConfig()
    cfg = base.replace(
        seed=args.seed,
        current_noise_std=args.current_noise,
        current_rate_hz=args.current_rate,
        gps_noise_m=args.gps_noise,
        utc_clock=(args.utc_at_boot or "").strip().lower() != "none",
        boat=BoatParams(nav=args.nav),
        params=tuple(params),
        tlog=args.tlog,
        signing_key=secret_from_key(args.signing_key) if args.signing_key else None,
    )
    drops = [_drop(d) for d in args.drop]
    start = _start_time(args.start_time, field)
    epoch0 = _utc_at_boot(args.utc_at_boot, field, start, ts)
    if n == 1:
        p0 = dict(params + boat_params[0])
        # MAV_SYSID is the system id, as in a SITL params file (ArduPilot reads it at boot)
        cfg = cfg.replace(params=tuple(params + boat_params[0]), sysid=int(p0.get("MAV_SYSID", cfg.sysid)))
        link_cfg = LinkConfig(
            loss=args.loss,
            latency_s=args.latency,
            baud=args.baud,
            buffer_bytes=args.radio_buffer,
            **_split_drops(drops + boat_drops[0]),
            drops_break_link=args.drops_break_link,
            seed=args.seed,
        )
        server = Simulator(
            field,
            home=home,
            config=cfg,
            velocity_scale=vs,
            time_scale=ts,
            start_time=start,
            link_config=link_cfg,
            epoch0=epoch0,
        )
        boats = [server]
    else:
        from vehicle_sim.fleet import Fleet, boat_config

        try:
            configs = [boat_config(cfg.replace(params=tuple(params + boat_params[i])), i) for i in range(n)]
        except ValueError as exc:
            raise _Bad(str(exc)) from None
        link_cfgs = [
            LinkConfig(
                loss=args.loss,
                latency_s=args.latency,
                baud=args.baud,
                buffer_bytes=args.radio_buffer,
                **_split_drops(drops + boat_drops[i]),
                drops_break_link=args.drops_break_link,
                seed=args.seed + i,
            )
            for i in range(n)
        ]
        server = Fleet(
            field,
            starts=starts,
            configs=configs,
            velocity_scale=vs,
            time_scale=ts,
            start_time=start,
            link_configs=link_cfgs,
            epoch0=epoch0,
        )
        boats = server.boats
    stop = {"flag": False}

    def _stop(*_):
        stop["flag"] = True

    # SIGINT and SIGTERM only set a flag, installed before the serving thread starts: a
    # KeyboardInterrupt raised between serve() and the loop below (seen on a loaded machine,
    # where the main thread can be starved for seconds) would skip sim.stop() and leave the
    # serving thread holding the process open
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    try:
        server.serve(listen, speedup=args.speedup, wait_for_client=not args.no_wait, lockstep=args.lockstep)
    except BaseException:
        server.stop()
        raise
    if not args.quiet:
        from vehicle_sim.fleet import boat_listen

        for i, b in enumerate(boats):
            specs = boat_listen(listen, i) if n > 1 else listen
            bound = dict(b.ports())
            where = ", ".join(f"{s} (port {bound[s]})" if s.endswith(":0") and s in bound else s for s in specs)
            lat, lon = starts[i]
            who = "boat" if n == 1 else f"boat {i} (sysid {b.config.sysid})"
            print(
                f"vehicle-sim: {who} at {lat:.6f},{lon:.6f}; listening on {where}; "
                f"speedup {args.speedup:g}" + (" (signed)" if cfg.signing_key else ""),
                file=sys.stderr,
                flush=True,
            )
    try:
        last = 0.0
        while not stop["flag"] and server.running:
            time.sleep(0.1)
            if args.duration is not None and server.t >= args.duration:
                break
            if not args.quiet and time.monotonic() - last > 10:
                last = time.monotonic()
                from vehicle_sim.autopilot import MODE_NAMES

                for i, b in enumerate(boats):
                    ap = b.autopilot
                    lat, lon = ap.position()
                    who = "" if n == 1 else f"boat {i} "
                    print(
                        f"{who}t={ap.t:8.1f}s mode={MODE_NAMES.get(ap.mode, ap.mode)} armed={ap.armed} "
                        f"pos={lat:.6f},{lon:.6f} links={len(b.links)}",
                        file=sys.stderr,
                    )
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    if not args.quiet:
        tl = args.tlog if n == 1 else ", ".join(b.config.tlog for b in boats) if args.tlog else None
        print("vehicle-sim: stopped" + (f"; tlog written to {tl}" if args.tlog else ""), file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
