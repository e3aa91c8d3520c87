"""``vehicle-sim``: serve a simulated ArduPilot Rover boat over MAVLink.

Examples::

    vehicle-sim --field builtin:ocean --listen tcp:127.0.0.1:5760 --speedup 10
    vehicle-sim --field currents.nc --home 40.1,-63.0 --listen tcp:127.0.0.1:5760 \\
        --listen udpout:127.0.0.1:14550 --loss 0.1 --baud 57600 --tlog sim.tlog
    vehicle-sim --field builtin:cylinder --anchor 40,-63 --scale 200 --velocity-scale 0.5 \\
        --time-scale 20 --listen tcp:127.0.0.1:5760
    vehicle-sim --field currents.nc --start-time 2024-05-01T06:00:00Z --utc-at-boot field \\
        --gps-noise 2 --current-noise 0.02 --seed 1

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


def _drop(s: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in s.split(":"))
    except ValueError:
        raise _Bad(f"--drop must be START:DURATION in seconds, got {s!r}") from None
    if a < 0 or b <= 0:
        raise _Bad(f"--drop needs START >= 0 and DURATION > 0, got {s!r}")
    return a, b


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vehicle-sim",
        description="An ArduPilot-Rover-compatible MAVLink boat simulator drifting in a replayed current field.",
        epilog="examples:" + EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--field", default=None, help="FILE.nc | builtin:ocean | builtin:cylinder | builtin:oscillating | none (still water)")
    p.add_argument("--home", default=None, help="start/home LAT,LON (default: centre of the field's region)")
    p.add_argument("--listen", action="append", default=None,
                   help="tcp:HOST:PORT, udpin:HOST:PORT or udpout:HOST:PORT; repeatable (default tcp:127.0.0.1:5760)")
    p.add_argument("--region", default=None, help="crop the field to SOUTH,WEST,NORTH,EAST degrees (default: whole grid)")
    p.add_argument("--velocity-scale", type=float, default=None, help="m/s per field velocity unit (metric fields; default 1)")
    p.add_argument("--time-scale", type=float, default=None, help="seconds per field time unit (metric fields; default 1)")
    p.add_argument("--anchor", default=None, help="LAT,LON of a metric field's centre (re-anchors it)")
    p.add_argument("--scale", type=float, default=None, help="Earth metres per data metre of a metric field")
    p.add_argument("--rotation", type=float, default=None, help="counter-clockwise rotation of a metric field, degrees")
    p.add_argument("--start-time", default=None,
                   help="field time at boot: a number in the field's time units, or an ISO UTC time for geographic fields (default: first snapshot)")
    p.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument("--lockstep", action="store_true",
                   help="time stands still until a GCS sends COMMAND_LONG 31010 (MAV_CMD_USER_1) with param1 = seconds to run")
    p.add_argument("--no-wait", action="store_true",
                   help="start the clock at once (default with a tcp listener: hold it until the first TCP client connects, like SITL)")
    p.add_argument("--loss", type=float, default=0.0, help="frame loss probability each way (0..1)")
    p.add_argument("--latency", type=float, default=0.0, help="one-way latency, simulated seconds")
    p.add_argument("--baud", type=int, default=0, help="emulate a serial radio of this many bit/s (0 = unlimited)")
    p.add_argument("--drop", action="append", default=[], help="scheduled link outage START:DURATION (sim seconds); repeatable")
    p.add_argument("--seed", type=int, default=0, help="seed of link loss and sensor noise")
    p.add_argument("--current-noise", type=float, default=0.0, help="std of Gaussian noise on CUR_U/CUR_V, m/s")
    p.add_argument("--current-rate", type=float, default=1.0, help="CUR_U/CUR_V rate, Hz of simulated time (0 = off)")
    p.add_argument("--gps-noise", type=float, default=0.0,
                   help="std of the reported position's error, m per axis (Gauss-Markov, 60 s correlation; seeded by --seed)")
    p.add_argument("--utc-at-boot", default=None,
                   help="UTC of the vehicle clock at boot (SYSTEM_TIME): an ISO time, 'field' (the field's time at "
                        "--start-time, so a controller mapping UTC samples the same hour), or 'none' (no clock: "
                        "time_unix_usec stays 0); default: now")
    p.add_argument("--nav", choices=("pursuit", "crosstrack"), default="pursuit",
                   help="pursuit: crab not compensated (default); crosstrack: hold the line like L1")
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
    from passt_mav.fields.datasets import resolve_field

    try:
        field = resolve_field(args.field, seed=args.seed)
    except ImportError as exc:
        raise _Bad(f"field {args.field!r} is not available in this installation ({exc})") from None
    g = field.grid
    if any(v is not None for v in (args.anchor, args.scale, args.rotation)):
        if field.is_geographic:
            raise _Bad("--anchor/--scale/--rotation apply to metric (cylinder) fields only")
        import geo

        lat, lon = _latlon(args.anchor, "--anchor") if args.anchor else (g.anchor_lat, g.anchor_lon)
        grid = geo.MetricRegionGrid(g.x0, g.x1, g.y0, g.y1, g.rows, g.cols, anchor_lat=lat, anchor_lon=lon,
                                    rotation_deg=g.rotation_deg if args.rotation is None else args.rotation,
                                    scale=g.scale if args.scale is None else args.scale)
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
        t = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
        t0 = dt.datetime.fromisoformat(field.time_origin.replace("Z", "+00:00"))
    except ValueError:
        raise _Bad(f"--start-time must be a number or an ISO time, got {value!r}") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.timezone.utc)
    if t0.tzinfo is None:
        t0 = t0.replace(tzinfo=dt.timezone.utc)
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
        t0 = dt.datetime.fromisoformat(field.time_origin.replace("Z", "+00:00"))
        t0 = t0 if t0.tzinfo else t0.replace(tzinfo=dt.timezone.utc)
        return t0.timestamp() + (float(field.times[0]) if start is None else start)
    try:
        t = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise _Bad(f"--utc-at-boot must be an ISO UTC time, 'field' or 'none', got {value!r}") from None
    return (t if t.tzinfo else t.replace(tzinfo=dt.timezone.utc)).timestamp()


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


def _run(args) -> int:
    from vehicle_sim.boat import BoatParams
    from vehicle_sim.config import LinkConfig, SimConfig
    from vehicle_sim.link import parse_link_spec, secret_from_key
    from vehicle_sim.sim import Simulator

    if not 0 <= args.loss < 1:
        raise _Bad(f"--loss must be in [0, 1), got {args.loss}")
    if args.speedup <= 0:
        raise _Bad(f"--speedup must be positive, got {args.speedup}")
    listen = args.listen or ["tcp:127.0.0.1:5760"]
    for spec in listen:
        try:
            parse_link_spec(spec)
        except ValueError as exc:
            raise _Bad(str(exc)) from None
    params = []
    for kv in args.param:
        if "=" not in kv:
            raise _Bad(f"--param must be NAME=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        try:
            params.append((k.strip().upper(), float(v)))
        except ValueError:
            raise _Bad(f"--param {k} value must be a number, got {v!r}") from None
    field = _load_field(args)
    if args.home:
        home = _latlon(args.home, "--home")
    elif field is not None:
        g = field.grid
        lat, lon = g.fcell_to_latlon((g.rows - 1) / 2.0, (g.cols - 1) / 2.0)
        home = (float(lat), float(lon))
    else:
        raise _Bad("--home LAT,LON is required without a field")
    vs = args.velocity_scale if args.velocity_scale is not None else 1.0
    ts = args.time_scale if args.time_scale is not None else 1.0
    if vs <= 0 or ts <= 0:
        raise _Bad("--velocity-scale and --time-scale must be positive")
    from vehicle_sim.autopilot import DEFAULT_PARAMS

    for k, _ in params:
        if k not in DEFAULT_PARAMS:
            raise _Bad(f"unknown parameter {k!r} in --param")
    base = SimConfig.fast() if args.fast_boot else SimConfig()
    cfg = base.replace(
        seed=args.seed, current_noise_std=args.current_noise, current_rate_hz=args.current_rate,
        gps_noise_m=args.gps_noise, utc_clock=(args.utc_at_boot or "").strip().lower() != "none",
        boat=BoatParams(nav=args.nav), params=tuple(params), tlog=args.tlog,
        signing_key=secret_from_key(args.signing_key) if args.signing_key else None,
    )
    link_cfg = LinkConfig(loss=args.loss, latency_s=args.latency, baud=args.baud,
                          drops=tuple(_drop(d) for d in args.drop), seed=args.seed)
    start = _start_time(args.start_time, field)
    sim = Simulator(field, home=home, config=cfg, velocity_scale=vs, time_scale=ts,
                    start_time=start, link_config=link_cfg, epoch0=_utc_at_boot(args.utc_at_boot, field, start, ts))
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
        sim.serve(listen, speedup=args.speedup, wait_for_client=not args.no_wait, lockstep=args.lockstep)
    except BaseException:
        sim.stop()
        raise
    if not args.quiet:
        bound = {spec: port for spec, port in sim.ports()}
        where = ", ".join(f"{s} (port {bound[s]})" if s.endswith(":0") and s in bound else s for s in listen)
        print(f"vehicle-sim: boat at {home[0]:.6f},{home[1]:.6f}; listening on {where}; "
              f"speedup {args.speedup:g}" + (" (signed)" if cfg.signing_key else ""), file=sys.stderr)
    try:
        last = 0.0
        while not stop["flag"] and sim.running:
            time.sleep(0.1)
            if args.duration is not None and sim.t >= args.duration:
                break
            if not args.quiet and time.monotonic() - last > 10:
                last = time.monotonic()
                ap = sim.autopilot
                from vehicle_sim.autopilot import MODE_NAMES

                lat, lon = ap.position()
                print(f"t={ap.t:8.1f}s mode={MODE_NAMES.get(ap.mode, ap.mode)} armed={ap.armed} "
                      f"pos={lat:.6f},{lon:.6f} links={len(sim.links)}", file=sys.stderr)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
    if not args.quiet:
        print("vehicle-sim: stopped" + (f"; tlog written to {args.tlog}" if args.tlog else ""), file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
