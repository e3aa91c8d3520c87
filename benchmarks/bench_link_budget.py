"""Benchmark: bytes per second ArduPilot Rover SITL sends the controller through an emulated radio.

    .venv/bin/python benchmarks/bench_link_budget.py                       # 57600 and 19200 baud, ~3 min
    .venv/bin/python benchmarks/bench_link_budget.py --bauds 57600 --seconds 20 --json
    .venv/bin/python benchmarks/bench_link_budget.py --bauds 57600 --keep-streams   # as before: every stream on

For each baud rate: a fresh SITL (real time, speedup 1, so the radio's wall-clock baud rate is the
vehicle's) with the Lua current sensor (vehicle_sim/lua, 4 Hz) at the north_atlantic home, behind
``vehicle_sim.radio.RadioProxy`` (100 ms one way, 3 % loss, 2 kB buffer); the controller's Link
connects through it (which stops every stream and asks for its own four), waits for the EKF, then
counts the vehicle's bytes over ``--seconds`` of vehicle time. No mission is flown: this is the
steady telemetry of a leg (a mission transfer adds ~50 bytes per item each way while it runs).
Needs ../shared/sitl (tests/sitl.py finds it).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HOME = "40.2759179,-63.0400207"  # inside missions/north_atlantic.yaml, where vehicle_sim/lua/current_grid.bin has data


def measure(baud: int, seconds: float, instance: int, quiet: bool = True) -> dict:
    from passt_mav.mavlink import Link, LinkConfig, Vehicle
    from vehicle_sim.radio import RadioConfig, RadioProxy

    sitl_dir = REPO.parent / "shared" / "sitl"
    wd = Path(tempfile.mkdtemp(prefix="bench_link_"))
    out = subprocess.run(
        [
            str(sitl_dir / "start-sitl"),
            str(wd),
            "-I",
            str(instance),
            "--speedup",
            "1",
            "--home",
            HOME,
            "--scripts",
            str(REPO / "vehicle_sim" / "lua"),
            "--wipe",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    pid, port = (int(x) for x in out.stdout.split()[:2])
    shutil.copy(REPO / "vehicle_sim" / "lua" / "current_grid.bin", wd / "scripts" / "current_grid.bin")
    radio = RadioProxy(("127.0.0.1", port), RadioConfig(baud=baud, latency_s=0.1, loss=0.03, buffer_bytes=2048))
    radio.start()
    link = None
    try:
        link = Link(
            LinkConfig(radio.connect, connect_timeout_s=60.0, timeout_s=1.5, retries=8, quiet_other_streams=quiet)
        ).connect()
        Vehicle(link).wait_ready(timeout=120.0)
        time.sleep(2.0)  # streams settled
        b0, t0 = link.stats.vehicle_bytes, link.vehicle_uptime_s()
        types0 = dict(link.stats.by_type)
        time.sleep(seconds)
        b1, t1 = link.stats.vehicle_bytes, link.vehicle_uptime_s()
        types = {k: n - types0.get(k, 0) for k, n in link.stats.by_type.items() if n - types0.get(k, 0)}
    finally:
        if link is not None:
            link.close()
        radio.stop()
        subprocess.run(["kill", str(pid)], check=False)
    st = radio.stats()["down"]
    return {
        "baud": baud,
        "capacity_bytes_per_s": baud / 10,
        "vehicle_bytes_per_s": round((b1 - b0) / (t1 - t0), 1),
        "vehicle_seconds": round(t1 - t0, 1),
        "messages": types,
        "radio_down": dict(st),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bauds", default="57600,19200", help="comma-separated baud rates (default %(default)s)")
    p.add_argument("--seconds", type=float, default=30.0, help="vehicle seconds to count (default %(default)s)")
    p.add_argument("--instance", type=int, default=47, help="SITL instance number (port 5760 + 10 N)")
    p.add_argument(
        "--keep-streams",
        action="store_true",
        help="do not stop the vehicle's other streams (the controller before the link budget)",
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    args = p.parse_args(argv)
    res = [measure(int(b), args.seconds, args.instance, quiet=not args.keep_streams) for b in args.bauds.split(",")]
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        for r in res:
            print(
                f"{r['baud']} baud: the vehicle sends {r['vehicle_bytes_per_s']} B/s "
                f"({100 * r['vehicle_bytes_per_s'] / r['capacity_bytes_per_s']:.0f} % of {r['capacity_bytes_per_s']:g}"
                f" B/s) over {r['vehicle_seconds']} s; messages {r['messages']}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
