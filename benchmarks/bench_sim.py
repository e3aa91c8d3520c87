"""Benchmarks of the vehicle simulator.

1. Real-time factor (simulated seconds per wall second) of one boat with the
   default 1 Hz streams and the current sensor, sampling a geographic field, on
   a lockstep in-process link whose GCS side parses everything; and the clock
   a served simulator (TCP, pymavlink client) actually achieves at a large
   ``--speedup``.
   Beside it, the same with several boats in one process (``vehicle-sim --boats N``,
   :class:`vehicle_sim.fleet.Fleet`: one field, one clock): the fleet's real-time
   factor with 1 and with 3 boats flying missions side by side (simulated seconds
   of the whole fleet per wall second; per-boat cost = 1/rtf), and the clock 3
   boats served over TCP achieve at a large ``--speedup``.
2. Mission-upload throughput (items per simulated second) with a client that
   answers each request at once: at loopback, and over an emulated 57600-baud
   radio (with and without the default telemetry competing for the bytes),
   both with ArduPilot's own request pace (~48/s) and without it, against the
   stop-and-wait bound 5760 B/s / (MISSION_ITEM_INT + MISSION_REQUEST bytes) ~ 88/s.

Usage: ``python benchmarks/bench_sim.py [--json] [--quick]``
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _field():
    import geo
    from passt_mav.fields import FlowField

    n = 30
    grid = geo.RegionGrid(39.9, -63.1, 40.1, -62.9, n, n)
    lats, lons = grid.centres_latlon()
    times = np.arange(0, 48) * 3600.0
    data = np.zeros((len(times), 2, n, n), np.float32)
    for i, t in enumerate(times):
        data[i, 0] = 0.3 * np.sin(lats * 20 + t / 20000)
        data[i, 1] = 0.2 * np.cos(lons * 20 - t / 30000)
    return FlowField(data, grid, times, time_origin="2020-01-01T00:00:00Z")


def _mission(home, n, dlat=2e-4):
    from pymavlink.dialects.v20 import ardupilotmega as M

    return [
        M.MAVLink_mission_item_int_message(
            1,
            1,
            i,
            6 if i else 0,
            16,
            0,
            1,
            0,
            0,
            0,
            0,
            int(round((home[0] + dlat * (i % 10)) * 1e7)),
            int(round((home[1] + dlat * (i // 10)) * 1e7)),
            0.0,
            0,
        )
        for i in range(n)
    ]


def bench_rtf(sim_seconds: float) -> dict:
    from pymavlink.dialects.v20 import ardupilotmega as M

    from vehicle_sim import MODES, SimConfig, Simulator
    from vehicle_sim.mission_server import Item

    home = (40.0, -63.0)
    sim = Simulator(_field(), home=home, config=SimConfig.fast())
    ep = sim.connect_inprocess()
    gcs = M.MAVLink(ep, srcSystem=255, srcComponent=190)
    sim.run_until(2.0)
    ap = sim.autopilot
    for it in _mission(home, 31):
        ap.store.put(Item.from_msg(it))
    ap.arm()
    ap.set_mode(MODES["AUTO"])
    n_msgs = 0
    t0, s0 = time.perf_counter(), sim.t
    while sim.t - s0 < sim_seconds:
        sim.step(0.25)
        n_msgs += len(gcs.parse_buffer(ep.read()) or [])
    wall = time.perf_counter() - t0
    return {
        "sim_s": sim.t - s0,
        "wall_s": wall,
        "rtf": (sim.t - s0) / wall,
        "msgs_per_sim_s": n_msgs / (sim.t - s0),
        "physics_dt": sim.config.physics_dt,
    }


def bench_rtf_fleet(n_boats: int, sim_seconds: float) -> dict:
    """Real-time factor of ``n_boats`` in one :class:`Fleet` (lockstep, in-process links).

    Each boat flies its own 31-waypoint mission (a 200 m x 100 m lawnmower from its own
    spread start) with the default 1 Hz streams and the current sensor on; one GCS per
    boat parses everything it sends, as :func:`bench_rtf` does for one boat.
    """
    from pymavlink.dialects.v20 import ardupilotmega as M

    from vehicle_sim import MODES, SimConfig
    from vehicle_sim.fleet import Fleet, spread_starts
    from vehicle_sim.mission_server import Item

    field = _field()
    starts = spread_starts(field, n_boats)
    fleet = Fleet(field, starts=starts, config=SimConfig.fast())
    eps = [b.connect_inprocess() for b in fleet.boats]
    gcs = [M.MAVLink(ep, srcSystem=255, srcComponent=190) for ep in eps]
    fleet.run_until(2.0)
    for b, home in zip(fleet.boats, starts):
        ap = b.autopilot
        for it in _mission(home, 31):
            ap.store.put(Item.from_msg(it))
        ap.arm()
        ap.set_mode(MODES["AUTO"])
    n_msgs = 0
    t0, s0 = time.perf_counter(), fleet.t
    while fleet.t - s0 < sim_seconds:
        fleet.step(0.25)
        for g, ep in zip(gcs, eps):
            n_msgs += len(g.parse_buffer(ep.read()) or [])
    wall = time.perf_counter() - t0
    sim_s = fleet.t - s0
    running = sum(b.autopilot.mission_state == "running" for b in fleet.boats)
    return {
        "boats": n_boats,
        "sim_s": sim_s,
        "wall_s": wall,
        "rtf": sim_s / wall,
        "boat_sim_s_per_wall_s": n_boats * sim_s / wall,
        "msgs_per_sim_s": n_msgs / sim_s,
        "boats_still_on_mission": running,
    }


def bench_served_fleet(n_boats: int, speedup: float, wall_s: float) -> dict:
    """Clock a TCP-served fleet achieves while one client per boat drains its socket (bytes only)."""
    from vehicle_sim import SimConfig
    from vehicle_sim.fleet import Fleet, spread_starts

    field = _field()
    fleet = Fleet(field, starts=spread_starts(field, n_boats), config=SimConfig.fast())
    fleet.serve(["tcp:127.0.0.1:0"], speedup=speedup)  # OS-chosen ports (the +10 layout may be taken)
    conns = [socket.create_connection(("127.0.0.1", p)) for p in fleet.tcp_ports()]
    for c in conns:
        c.setblocking(False)

    def drain(seconds):
        import select

        n, t_end = 0, time.perf_counter() + seconds
        while time.perf_counter() < t_end:
            ready, _, _ = select.select(conns, [], [], 0.2)
            for c in ready:
                try:
                    n += len(c.recv(1 << 16))
                except BlockingIOError:
                    pass
        return n

    drain(1.0)
    t0, s0 = time.perf_counter(), fleet.t
    nbytes = drain(wall_s)
    wall = time.perf_counter() - t0
    achieved = (fleet.t - s0) / wall
    for c in conns:
        c.close()
    fleet.stop()
    return {
        "boats": n_boats,
        "speedup_requested": speedup,
        "speedup_achieved": achieved,
        "bytes_per_wall_s": nbytes / wall,
    }


def bench_served(speedup: float, wall_s: float) -> dict:
    """Clock a TCP-served simulator achieves while a client drains its socket.

    The client only counts bytes (a Python MAVLink parser in the same process
    would compete for the GIL and measure itself, not the simulator).
    """
    from vehicle_sim import SimConfig, Simulator

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    sim = Simulator(_field(), home=(40.0, -63.0), config=SimConfig.fast())
    sim.serve([f"tcp:127.0.0.1:{port}"], speedup=speedup)
    conn = socket.create_connection(("127.0.0.1", port))
    conn.settimeout(0.2)

    def drain(seconds):
        n, t_end = 0, time.perf_counter() + seconds
        while time.perf_counter() < t_end:
            try:
                n += len(conn.recv(1 << 16))
            except TimeoutError:
                pass
        return n

    drain(1.0)  # let the clock settle (field/pyproj set-up at start)
    t0, s0 = time.perf_counter(), sim.t
    nbytes = drain(wall_s)
    wall = time.perf_counter() - t0
    achieved = (sim.t - s0) / wall
    conn.close()
    sim.stop()
    return {"speedup_requested": speedup, "speedup_achieved": achieved, "bytes_per_wall_s": nbytes / wall}


def bench_upload(n_items: int, baud: int, paced: bool, streams: bool) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from simclient import SimClient

    from vehicle_sim import LinkConfig, SimConfig, Simulator

    home = (40.0, -63.0)
    kw = {} if paced else {"mission_request_interval_s": 0.0}
    if not streams:
        kw["params"] = tuple((f"MAV1_{g}", 0) for g in ("EXT_STAT", "POSITION", "EXTRA1", "EXTRA2", "EXTRA3"))
        kw["current_rate_hz"] = 0.0
    sim = Simulator(None, home=home, config=SimConfig.fast(**kw))
    sim.run_until(2.0)
    c = SimClient(sim, link_config=LinkConfig(baud=baud))
    c.dt = 0.0005
    items = _mission(home, n_items)
    t0, s0 = time.perf_counter(), sim.t
    ack = c.upload(items, timeout=600)
    sim_s, wall = sim.t - s0, time.perf_counter() - t0
    assert ack is not None and ack.type == 0, ack
    frame_item = len(items[1].pack(c.mav))
    return {
        "items": n_items,
        "baud": baud,
        "vehicle_paced": paced,
        "telemetry": streams,
        "items_per_sim_s": (n_items - 1) / sim_s,
        "items_per_wall_s_lockstep": (n_items - 1) / wall,
        "mission_item_int_bytes": frame_item,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--quick", action="store_true", help="shorter runs")
    args = ap.parse_args(argv)
    q = args.quick
    out = {
        "rtf_lockstep": bench_rtf(300.0 if q else 1800.0),
        "rtf_fleet": [bench_rtf_fleet(1, 300.0 if q else 1800.0), bench_rtf_fleet(3, 300.0 if q else 1800.0)],
        "served": [bench_served(200.0, 2.0 if q else 5.0), bench_served(1000.0, 2.0 if q else 5.0)],
        "served_fleet": [
            bench_served_fleet(3, 200.0, 2.0 if q else 5.0),
            bench_served_fleet(3, 1000.0, 2.0 if q else 5.0),
        ],
        "upload": [
            bench_upload(101, 0, True, True),
            bench_upload(101, 0, False, True),
            bench_upload(101, 57600, True, True),
            bench_upload(101, 57600, False, False),
            bench_upload(101, 57600, False, True),
        ],
        "stop_and_wait_bound_57600": 5760.0 / (49 + 16),
    }
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        r = out["rtf_lockstep"]
        print(
            f"real-time factor (lockstep, default streams, field sampling): {r['rtf']:.0f}x "
            f"({r['sim_s']:.0f} sim s in {r['wall_s']:.2f} s; {r['msgs_per_sim_s']:.1f} msgs/sim s)"
        )
        f1, f3 = out["rtf_fleet"]
        print(
            f"real-time factor of a fleet (lockstep, each boat on its own mission): 1 boat {f1['rtf']:.0f}x, "
            f"3 boats {f3['rtf']:.0f}x ({f3['boat_sim_s_per_wall_s']:.0f} boat-s per wall s vs "
            f"{f1['boat_sim_s_per_wall_s']:.0f}; {f3['sim_s']:.0f} sim s in {f3['wall_s']:.2f} s)"
        )
        for s in out["served_fleet"]:
            print(
                f"3 boats served over TCP at --speedup {s['speedup_requested']:.0f}: achieved {s['speedup_achieved']:.0f}x "
                f"({s['bytes_per_wall_s'] / 1e3:.0f} kB/s to the clients)"
            )
        for s in out["served"]:
            print(
                f"served over TCP at --speedup {s['speedup_requested']:.0f}: achieved {s['speedup_achieved']:.0f}x "
                f"({s['bytes_per_wall_s'] / 1e3:.0f} kB/s to the client)"
            )
        for u in out["upload"]:
            print(
                f"upload {u['items'] - 1} items, baud {u['baud'] or 'loopback'}, paced={u['vehicle_paced']}, "
                f"telemetry={u['telemetry']}: {u['items_per_sim_s']:.1f} items/sim s "
                f"({u['items_per_wall_s_lockstep']:.0f} items/wall s in lockstep)"
            )
        print(f"stop-and-wait bound at 57600 baud: {out['stop_and_wait_bound_57600']:.0f} items/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
