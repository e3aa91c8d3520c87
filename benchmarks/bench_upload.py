"""Mission upload time of the controller's MissionClient (and of MAVSDK's mission_raw) against vehicle_sim.

The simulator is served at real time (speedup 1) over TCP on loopback, so its own pace
(ArduPilot asks for ~48 items per second) and, with ``baud``, an emulated 57600-baud
radio (5760 B/s, frames serialised one after another) apply as on a real link.
Reference: the stop-and-wait bound of a 57600-baud radio, 5760 B/s / (49 B MISSION_ITEM_INT
+ 16 B MISSION_REQUEST) ~ 88 items/s (shared/ARDUPILOT_ROVER.md). Rows: n items (home + n-1
waypoints), seconds, items/s, and for MAVSDK the ratio MAVSDK time / our time.

Usage: ``python benchmarks/bench_upload.py [--quick] [--json] [--no-mavsdk]``
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

HOME = (40.0, -63.0)
BOUND_57600 = 5760.0 / (49 + 16)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _items(n: int):
    from passt_mav.mission.items import MissionItem

    dlat = 10.0 / 111_035.0
    return [
        MissionItem(i, 0 if i == 0 else 3, 16, 0, 1, 0, 0, 0, 0, HOME[0] + dlat * i, HOME[1], 0.0, 0) for i in range(n)
    ]


def _sim(baud: int):
    from vehicle_sim import LinkConfig, SimConfig, Simulator

    port = _free_port()
    sim = Simulator(None, home=HOME, config=SimConfig.fast(), link_config=LinkConfig(baud=baud))
    sim.serve([f"tcp:127.0.0.1:{port}"], speedup=1.0, wait_for_client=False)
    return sim, port


def ours(n: int, baud: int) -> float:
    from passt_mav.mavlink import Link, LinkConfig, MissionClient

    sim, port = _sim(baud)
    try:
        link = Link(LinkConfig(f"tcp:127.0.0.1:{port}", connect_timeout_s=10)).connect()
        try:
            mc = MissionClient(link)
            time.sleep(0.5)  # storage ready (fast boot: 0.3 s)
            t0 = time.monotonic()
            mc.upload(_items(n))
            return time.monotonic() - t0
        finally:
            link.close()
    finally:
        sim.stop()


def mavsdk_upload(n: int, baud: int) -> float | None:
    try:
        from mavsdk import ComponentType, Configuration, Mavsdk
        from mavsdk.plugins.mission_raw import MissionItem, MissionRaw
    except Exception:  # noqa: BLE001 - MAVSDK is optional
        return None
    sim, port = _sim(baud)
    drone = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        if drone.add_any_connection(f"tcpout://127.0.0.1:{port}") != 0:
            return None
        system = drone.first_autopilot(10.0)
        if system is None:
            return None
        mr = MissionRaw(system)
        time.sleep(0.5)
        # MAVSDK's mission_raw wants exactly one item marked current (else CURRENT_INVALID)
        items = [
            MissionItem(
                it.seq, it.frame, it.command, 1 if it.seq == 0 else 0, 1, 0, 0, 0, 0, it.x_int, it.y_int, 0.0, 0
            )
            for it in _items(n)
        ]
        t0 = time.monotonic()
        mr.upload_mission(items)
        return time.monotonic() - t0
    except Exception as exc:  # noqa: BLE001 - report, do not fail the benchmark
        print(f"MAVSDK upload of {n} items failed: {str(exc.args[0] if exc.args else exc)[:200]}", file=sys.stderr)
        return None
    finally:
        sim.stop()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 and 100 items only")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-mavsdk", action="store_true")
    a = ap.parse_args(argv)
    sizes = (10, 100) if a.quick else (10, 100, 500)
    rows = []
    for baud in (0, 57600):
        for n in sizes:
            t = ours(n, baud)
            m = None if a.no_mavsdk else mavsdk_upload(n, baud)
            rows.append(
                {
                    "link": "loopback" if baud == 0 else f"{baud} baud",
                    "items": n,
                    "seconds": t,
                    "items_per_s": n / t,
                    "bound_items_per_s": BOUND_57600 if baud else None,
                    "mavsdk_seconds": m,
                    "mavsdk_over_ours": (m / t) if m else None,
                }
            )
    if a.json:
        print(json.dumps(rows, indent=1))
    else:
        print(f"{'link':>11} {'items':>5} {'s':>7} {'items/s':>8} {'bound':>6} {'MAVSDK s':>9} {'ratio':>6}")
        for r in rows:
            b = f"{r['bound_items_per_s']:.0f}" if r["bound_items_per_s"] else "-"
            ms = f"{r['mavsdk_seconds']:.2f}" if r["mavsdk_seconds"] else "-"
            ra = f"{r['mavsdk_over_ours']:.2f}" if r["mavsdk_over_ours"] else "-"
            print(
                f"{r['link']:>11} {r['items']:>5} {r['seconds']:>7.2f} {r['items_per_s']:>8.1f} {b:>6} {ms:>9} {ra:>6}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
