"""Several boats in one simulator (``vehicle-sim --boats N``, :class:`vehicle_sim.fleet.Fleet`).

Every test runs in lockstep (simulated-time timeouts only; wall timeouts are generous
and only guard against a hang), so the results do not depend on the machine's load.
"""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as M
from simclient import SimClient

from vehicle_sim import MODES, SimConfig
from vehicle_sim.cli import main as cli_main
from vehicle_sim.fleet import Fleet, boat_listen, line_starts, spread_starts
from vehicle_sim.sim import STEP_COMMAND

# a small geographic field whose current is LINEAR in lat/lon and constant in time: bilinear
# interpolation reproduces it exactly, so every reading has a known answer at the boat's position
S, W, N, E = 40.0, -63.0, 40.02, -62.97
ROWS = COLS = 21


def u_true(lat, lon):
    """East current, m/s."""
    return 0.1 + 0.2 * (lon - W) / (E - W)


def v_true(lat, lon):
    """North current, m/s."""
    return -0.05 - 0.1 * (lat - S) / (N - S)


def linear_field():
    import geo
    from passt_mav.fields import FlowField

    grid = geo.RegionGrid(S, W, N, E, ROWS, COLS)
    lats, lons = grid.centres_latlon()
    snap = np.stack([u_true(lats, lons), v_true(lats, lons)]).astype(np.float32)
    data = np.stack([snap, snap])
    return FlowField(data, grid, np.array([0.0, 36000.0]), time_origin="2020-01-01T00:00:00Z")


_GEOD = None


def _geod():
    global _GEOD
    if _GEOD is None:
        from pyproj import Geod

        _GEOD = Geod(ellps="WGS84")
    return _GEOD


def _offset(lat, lon, north_m, east_m):
    """The point ``north_m`` north then ``east_m`` east of (lat, lon), degrees (WGS84 geodesics)."""
    lon1, lat1, _ = _geod().fwd(lon, lat, 0.0, north_m)
    lon2, lat2, _ = _geod().fwd(lon1, lat1, 90.0, east_m)
    return lat2, lon2


def _dist_m(a, b):
    """WGS84 geodesic distance between (lat, lon) points, metres."""
    return _geod().inv(a[1], a[0], b[1], b[0])[2]


# -- start positions ------------------------------------------------------------------------------
def test_spread_starts_are_distinct_inside_the_region_and_avoid_land():
    f = linear_field()
    assert spread_starts(f, 1)[0] == pytest.approx(((S + N) / 2, (W + E) / 2), abs=1e-9)  # single boat: centre
    for n in (2, 3, 4, 5):
        st = spread_starts(f, n)
        assert len(st) == n
        for lat, lon in st:
            assert S <= lat <= N and W <= lon <= E
        # at least a quarter of the region's smaller side (2.2 km) apart
        assert min(_dist_m(a, b) for i, a in enumerate(st) for b in st[i + 1 :]) > 500
    # three boats: the SW, SE and NW block centres (cell 4.75 / 15.25 of 0..20)
    st = spread_starts(f, 3)
    assert st[0] == pytest.approx((S + 0.001 * 4.75, W + 0.0015 * 4.75), abs=1e-9)
    assert st[1] == pytest.approx((S + 0.001 * 4.75, W + 0.0015 * 15.25), abs=1e-9)
    assert st[2] == pytest.approx((S + 0.001 * 15.25, W + 0.0015 * 4.75), abs=1e-9)
    # a block centre on land moves to the nearest cell with data
    f.data[:, :, :10, :10] = np.nan
    lat, lon = spread_starts(f, 3)[0]
    r, c = f.grid.latlon_to_fcell(lat, lon)
    assert np.isfinite(f.data[0, 0, int(r), int(c)]) and (r >= 10 or c >= 10)
    # without a field: 20 m apart along the east axis
    ln = line_starts((40.0, -63.0), 3)
    assert [_dist_m(ln[0], p) for p in ln] == pytest.approx([0.0, 20.0, 40.0], abs=0.01)
    assert boat_listen(["tcp:127.0.0.1:5760", "udpout:127.0.0.1:14550", "tcp:127.0.0.1:0"], 2) == [
        "tcp:127.0.0.1:5780",
        "udpout:127.0.0.1:14570",
        "tcp:127.0.0.1:0",
    ]


# -- in-process: one clock, one field -------------------------------------------------------------
def test_inprocess_boats_share_one_clock_and_field_and_have_their_own_ids():
    f = linear_field()
    fleet = Fleet(f, starts=spread_starts(f, 3), config=SimConfig.fast(seed=4))
    assert all(b.current is fleet.current for b in fleet.boats)
    clients = [SimClient(b) for b in fleet.boats]
    hb = clients[1].wait("HEARTBEAT", timeout=2.0)  # stepping boat 1 steps the fleet
    assert hb is not None and hb.get_srcSystem() == 2
    assert [b.t for b in fleet.boats] == [fleet.t] * 3 and fleet.t > 0
    for i, c in enumerate(clients):
        c.mav.param_request_read_send(i + 1, 1, b"MAV_SYSID", -1)
        pv = c.wait("PARAM_VALUE", lambda m: m.param_id == "MAV_SYSID", timeout=1.0)
        assert pv is not None and pv.param_value == i + 1 and pv.get_srcSystem() == i + 1
        assert fleet.boats[i].config.seed == 4 + i  # noise/link-loss streams differ per boat
    # a message addressed to boat 2 is ignored by boat 1 (same GCS, other vehicle)
    clients[0].mav.command_long_send(2, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["HOLD"], 0, 0, 0, 0, 0)
    assert clients[0].wait("COMMAND_ACK", timeout=1.0) is None
    fleet.run_until(3.0)
    assert clients[0].set_mode(MODES["HOLD"]).result == 0
    assert [b.autopilot.mode for b in fleet.boats] == [MODES["HOLD"], MODES["MANUAL"], MODES["MANUAL"]]
    # a reboot of boat 2 restarts its boot timeline only; the clock runs on for everyone
    fleet.boats[2].reboot(downtime_s=1.0)
    fleet.step(2.0)
    # boat 2: silent for 1 s, then 1 s since boot; its world clock is everyone's
    assert fleet.boats[2].autopilot.t == pytest.approx(1.0, abs=0.06) and fleet.boats[2].autopilot.clock == fleet.t
    assert fleet.boats[0].autopilot.t == pytest.approx(fleet.t)
    with pytest.raises(ValueError, match="system id"):
        Fleet(f, starts=spread_starts(f, 2), config=SimConfig.fast(params=(("MAV_SYSID", 3.0),)))


def test_inprocess_fault_injection_and_tlogs_are_per_boat(tmp_path):
    """A link outage scheduled for boat 1 silences boat 1 only; each boat writes its own tlog."""
    from vehicle_sim import LinkConfig

    f = linear_field()
    fleet = Fleet(
        f,
        starts=spread_starts(f, 3),
        config=SimConfig.fast(tlog=str(tmp_path / "sim.tlog")),
        link_configs=[LinkConfig(), LinkConfig(drops=((5.0, 10.0),)), LinkConfig()],
    )
    clients = [SimClient(b) for b in fleet.boats]
    heard: dict[int, list[float]] = {i: [] for i in range(3)}
    while fleet.t < 20.0:
        fleet.step(0.5)
        for i, c in enumerate(clients):
            c.pump()
            heard[i] += [fleet.t for m in c.queue if m.get_type() == "HEARTBEAT"]
            c.queue.clear()
    silent = lambda ts: not any(5.5 < t < 15.0 for t in ts)
    assert silent(heard[1]) and not silent(heard[0]) and not silent(heard[2])
    assert any(t > 15.0 for t in heard[1])  # back after the outage
    fleet.stop()
    for sysid in (1, 2, 3):
        log = mavutil.mavlink_connection(str(tmp_path / f"sim-{sysid}.tlog"))
        srcs = set()
        while (m := log.recv_match(type="HEARTBEAT")) is not None:
            srcs.add(m.get_srcSystem())
        log.close()
        assert srcs == {sysid}


# -- over TCP, lockstep: three boats fly their own missions; one client link is killed -------------
class FleetGCS:
    """One pymavlink TCP connection per boat; the clock is stepped through one of them (31010)."""

    def __init__(self, ports):
        self.conns = [
            mavutil.mavlink_connection(f"tcp:127.0.0.1:{p}", source_system=255, source_component=190) for p in ports
        ]
        self.alive = [True] * len(ports)
        self.msgs: list[list] = [[] for _ in ports]  # every message received, per boat
        self.t = 0.0

    def pump(self, i) -> list:
        out = []
        if not self.alive[i]:
            return out
        while True:
            m = self.conns[i].recv_msg()
            if m is None:
                break
            if m.get_type() != "BAD_DATA":
                out.append(m)
        self.msgs[i].extend(out)
        return out

    def step(self, dt: float, on_msg=None) -> None:
        """Advance the fleet's clock by ``dt`` sim seconds; hand every message to ``on_msg(i, m)``."""
        k = self.alive.index(True)
        self.conns[k].mav.command_long_send(k + 1, 1, STEP_COMMAND, 0, dt, 0, 0, 0, 0, 0, 0)
        deadline = time.monotonic() + 60.0  # a hang guard only: nothing moves without this command
        acked = False
        while not acked:
            assert time.monotonic() < deadline, "no acknowledgement of the lockstep step"
            got_any = False
            for i in range(len(self.conns)):
                for m in self.pump(i):
                    got_any = True
                    if i == k and m.get_type() == "COMMAND_ACK" and m.command == STEP_COMMAND:
                        acked = True
                    elif on_msg is not None:
                        on_msg(i, m)
            if not got_any:
                time.sleep(0.001)
        self.t += dt
        # what arrived with the step's acknowledgement (sent last, so everything else is in)
        for i in range(len(self.conns)):
            for m in self.pump(i):
                if on_msg is not None:
                    on_msg(i, m)

    def kill(self, i) -> None:
        self.conns[i].close()
        self.alive[i] = False

    def close(self) -> None:
        for i, c in enumerate(self.conns):
            if self.alive[i]:
                c.close()


def test_three_boats_over_tcp_fly_their_missions_and_one_lost_link_stops_no_other():
    f = linear_field()
    n = 3
    starts = spread_starts(f, n)
    fleet = Fleet(f, starts=starts, config=SimConfig.fast())
    fleet.serve(["tcp:127.0.0.1:0"], lockstep=True)  # OS-chosen ports: tests may run side by side
    ports = fleet.tcp_ports()
    gcs = FleetGCS(ports)
    try:
        # each boat's mission: home, 150 m north, then 150 m east (its own, from its own start)
        missions = []
        for lat, lon in starts:
            a = _offset(lat, lon, 150.0, 0.0)
            b = _offset(lat, lon, 150.0, 150.0)
            missions.append([(lat, lon), a, b])
        gcs.step(3.0)  # boot (fast timeline: EKF and storage ready by 1.5 s)
        for i in range(n):
            hbs = [m for m in gcs.msgs[i] if m.get_type() == "HEARTBEAT"]
            assert hbs and {m.get_srcSystem() for m in hbs} == {i + 1}
            first = next(m for m in gcs.msgs[i] if m.get_type() == "GLOBAL_POSITION_INT" and m.lat != 0)
            assert _dist_m((first.lat / 1e7, first.lon / 1e7), starts[i]) < 1.0
            assert S <= first.lat / 1e7 <= N and W <= first.lon / 1e7 <= E
        # MAV_SYSID of each boat, read over its own link
        for i in range(n):
            gcs.conns[i].mav.param_request_read_send(i + 1, 1, b"MAV_SYSID", -1)

        def sysid_values(i):
            return [m for m in gcs.msgs[i] if m.get_type() == "PARAM_VALUE" and m.param_id == "MAV_SYSID"]

        t_end = gcs.t + 5.0  # each request may be read after the step command (see acked below)
        while not all(sysid_values(i) for i in range(n)) and gcs.t < t_end:
            gcs.step(0.2)
        for i in range(n):
            pv = sysid_values(i)
            assert pv and pv[-1].param_value == i + 1 and pv[-1].get_srcSystem() == i + 1

        # upload all three missions at once, each boat pacing its own transfer
        acks: dict[int, object] = {}

        def upload_handler(i, m):
            typ = m.get_type()
            if typ in ("MISSION_REQUEST_INT", "MISSION_REQUEST") and m.mission_type == 0:
                lat, lon = missions[i][m.seq]
                gcs.conns[i].mav.send(
                    M.MAVLink_mission_item_int_message(
                        i + 1,
                        1,
                        m.seq,
                        6 if m.seq else 0,
                        M.MAV_CMD_NAV_WAYPOINT,
                        0,
                        1,
                        0,
                        0,
                        0,
                        0,
                        int(round(lat * 1e7)),
                        int(round(lon * 1e7)),
                        0.0,
                        0,
                    )
                )
            elif typ == "MISSION_ACK":
                acks[i] = m

        for i in range(n):
            gcs.conns[i].mav.mission_count_send(i + 1, 1, len(missions[i]), 0)
        t_end = gcs.t + 10.0
        while len(acks) < n and gcs.t < t_end:
            gcs.step(0.1, upload_handler)
        assert sorted(acks) == [0, 1, 2] and all(a.type == M.MAV_MISSION_ACCEPTED for a in acks.values())
        assert [len(b.autopilot.store.items[0]) for b in fleet.boats] == [3, 3, 3]

        # arm and AUTO, each boat by its own system id
        results: dict[tuple, int] = {}

        def ack_handler(i, m):
            if m.get_type() == "COMMAND_ACK":
                results[(i, m.command)] = m.result

        def acked(cmd):
            # a command sent on boat i's socket may reach the fleet after the step command sent on
            # another socket (the serving loop reads sockets in turn): step until every boat answered,
            # bounded in simulated time, not in wall-clock time (failed 1 in a few runs under load)
            t_end = gcs.t + 5.0
            while not all((i, cmd) in results for i in range(n)) and gcs.t < t_end:
                gcs.step(0.2, ack_handler)

        for i in range(n):
            gcs.conns[i].mav.command_long_send(i + 1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        acked(M.MAV_CMD_COMPONENT_ARM_DISARM)
        for i in range(n):
            gcs.conns[i].mav.command_long_send(i + 1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["AUTO"], 0, 0, 0, 0, 0)
        acked(M.MAV_CMD_DO_SET_MODE)
        for i in range(n):
            assert results[(i, M.MAV_CMD_COMPONENT_ARM_DISARM)] == 0 and results[(i, M.MAV_CMD_DO_SET_MODE)] == 0

        # fly; CUR_U/CUR_V are checked against the field at the position sent with them
        reached: dict[int, dict[int, float]] = {i: {} for i in range(n)}
        last_gpi: dict[int, object] = {}
        pending_u: dict[int, float] = {}
        readings: dict[int, list] = {i: [] for i in range(n)}
        killed_at = None

        def fly_handler(i, m):
            typ = m.get_type()
            if typ == "GLOBAL_POSITION_INT":
                last_gpi[i] = m
            elif typ == "MISSION_ITEM_REACHED":
                reached[i].setdefault(m.seq, gcs.t)
            elif typ == "NAMED_VALUE_FLOAT" and m.name == "CUR_U":
                pending_u[i] = m.value
            elif typ == "NAMED_VALUE_FLOAT" and m.name == "CUR_V" and i in pending_u:
                g = last_gpi[i]
                assert g.time_boot_ms == m.time_boot_ms  # the fix and the reading are one instant
                readings[i].append((gcs.t, g.lat / 1e7, g.lon / 1e7, pending_u.pop(i), m.value))

        t_end = gcs.t + 400.0
        while gcs.t < t_end and not (2 in reached[0] and 2 in reached[2]):
            gcs.step(2.0, fly_handler)
            if killed_at is None and 1 in reached[1]:
                gcs.kill(1)  # boat 1's only client goes away mid-mission (the TCP connection closes)
                killed_at = gcs.t
        assert killed_at is not None, "boat 1 never reached its first waypoint"
        assert 2 in reached[0] and 2 in reached[2], reached
        assert 2 not in reached[1]  # nothing was heard from boat 1 after its link died
        assert not fleet.boats[1].links  # the vehicle side dropped the dead link ...
        assert fleet.boats[0].links and fleet.boats[2].links  # ... and only that one
        gcs.step(10.0, fly_handler)
        for i in (0, 2):
            assert reached[i][1] < reached[i][2] and reached[i][2] > killed_at
            g = last_gpi[i]
            # loitering at its own last waypoint (WP_RADIUS 2 m, LOIT_RADIUS 2 m, current <= 0.35 m/s)
            assert _dist_m((g.lat / 1e7, g.lon / 1e7), missions[i][2]) < 5.0
            assert sum(1 for r in readings[i] if r[0] > killed_at) >= 20  # still streaming after the kill
        for i in range(n):
            r = np.array(readings[i])
            assert len(r) >= 30
            np.testing.assert_allclose(r[:, 3], u_true(r[:, 1], r[:, 2]), atol=1e-5)
            np.testing.assert_allclose(r[:, 4], v_true(r[:, 1], r[:, 2]), atol=1e-5)
        # the boats sit in different water: their mean readings differ (boats 0/1 east-west, 0/2 north-south)
        means = [np.array(readings[i])[:, 3:].mean(axis=0) for i in range(n)]
        assert means[1][0] - means[0][0] > 0.05 and means[0][1] - means[2][1] > 0.03

        # boat 1 flew on without a GCS (FS_GCS_ENABLE 0); a new client finds it at its last waypoint
        gcs.conns[1] = mavutil.mavlink_connection(f"tcp:127.0.0.1:{ports[1]}", source_system=255, source_component=190)
        gcs.alive[1] = True
        gcs.msgs[1].clear()
        gcs.step(2.0)
        g = [m for m in gcs.msgs[1] if m.get_type() == "GLOBAL_POSITION_INT"]
        assert g and g[-1].get_srcSystem() == 2
        assert _dist_m((g[-1].lat / 1e7, g[-1].lon / 1e7), missions[1][2]) < 5.0
        # the vehicle side can drop one boat's clients too (the serving thread closes them)
        fleet.drop_clients(1)
        gcs.step(0.5)
        assert not fleet.boats[1].links and fleet.boats[0].links and fleet.boats[2].links
    finally:
        gcs.close()
        fleet.stop()


# -- the command line -----------------------------------------------------------------------------
def _free_base_port(n: int) -> int:
    """A port P with P, P+10, ... P+10(n-1) free on loopback right now (the SITL layout)."""
    for _ in range(200):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        p = s.getsockname()[1]
        s.close()
        if p + 10 * (n - 1) > 65535:
            continue
        socks = []
        try:
            for i in range(n):
                t = socket.socket()
                t.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                socks.append(t)
                t.bind(("127.0.0.1", p + 10 * i))
            return p
        except OSError:
            continue
        finally:
            for t in socks:
                t.close()
    raise AssertionError("no free port layout found")


def test_cli_boats_listen_like_sitl_instances_with_their_own_system_ids():
    n = 3
    for _attempt in range(3):  # another process may take a port between the check and the bind
        base = _free_base_port(n)
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "vehicle_sim.cli",
                "--boats",
                str(n),
                "--base-port",
                str(base),
                "--home",
                "40,-63",
                "--lockstep",
                "--fast-boot",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        lines = [proc.stderr.readline() for _ in range(n)]
        if proc.poll() is None or all("listening" in ln for ln in lines):
            break
        proc.communicate(timeout=10)
    try:
        # one status line per boat, naming its system id, start and port
        for i, ln in enumerate(lines):
            m = re.match(
                rf"vehicle-sim: boat {i} \(sysid {i + 1}\) at ([-\d.]+),([-\d.]+); listening on tcp:127.0.0.1:(\d+)", ln
            )
            assert m, ln
            assert int(m.group(3)) == base + 10 * i
            assert _dist_m((40.0, -63.0), (float(m.group(1)), float(m.group(2)))) == pytest.approx(
                20.0 * i, abs=0.2
            )  # 6 printed decimals
        gcs = FleetGCS([base + 10 * i for i in range(n)])
        try:
            for i in range(n):
                gcs.conns[i].mav.param_request_read_send(i + 1, 1, b"MAV_SYSID", -1)

            def answered(i):
                return any(m.get_type() == "PARAM_VALUE" and m.param_id == "MAV_SYSID" for m in gcs.msgs[i])

            # the requests travel on each boat's own socket, the step on boat 0's: the simulator may read a request
            # after the step it was sent before, and answer it in a later step; up to 10 s of simulated time
            gcs.step(1.0)
            while not all(answered(i) for i in range(n)) and gcs.t < 10.0:
                gcs.step(1.0)
            for i in range(n):
                hb = [m for m in gcs.msgs[i] if m.get_type() == "HEARTBEAT"]
                assert hb and {m.get_srcSystem() for m in hb} == {i + 1}
                pv = [m for m in gcs.msgs[i] if m.get_type() == "PARAM_VALUE" and m.param_id == "MAV_SYSID"]
                assert pv and pv[-1].param_value == i + 1
        finally:
            gcs.close()
    finally:
        import signal

        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err


def test_cli_boats_help_and_bad_input(capsys):
    with pytest.raises(SystemExit):
        cli_main(["--help"])
    assert "--boats" in capsys.readouterr().out
    bad = [
        ["--boats", "0", "--home", "40,-63"],
        ["--boats", "2", "--start", "40,-63"],  # one --start for two boats
        ["--boats", "2", "--start", "40,-63", "--start-cell", "1,1"],
        ["--boats", "2", "--home", "40,-63", "--boat-param", "2:WP_SPEED=3"],  # boats are 0 and 1
        ["--boats", "2", "--home", "40,-63", "--boat-param", "WP_SPEED=3"],
        ["--boats", "2", "--home", "40,-63", "--param", "MAV_SYSID=4"],
        ["--boats", "2", "--home", "40,-63", "--boat-param", "0:MAV_SYSID=2"],  # 2 is boat 1's id
        ["--boats", "2", "--home", "40,-63", "--boat-drop", "1:5"],
        ["--boats", "2", "--home", "40,-63", "--base-port", "65530"],
        ["--boats", "2", "--start-cell", "1,1", "--start-cell", "2,2"],  # no field to take cells of
    ]
    for argv in bad:
        assert cli_main(argv + ["--duration", "1", "--no-wait"]) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("vehicle-sim: error:") and err.count("\n") == 1, (argv, err)


# -- the served clock -----------------------------------------------------------------------------
@pytest.mark.parametrize("boats", [1, 3])
def test_served_clock_slips_after_a_stall_and_never_outruns_its_speedup(boats):
    """A served simulator that fell behind (a stall: here the test holds its lock for 0.4 s of
    wall time) drops the backlog beyond 5 s and then runs at ``speedup`` again, not faster.

    Only an upper bound is checked, so a loaded machine (a slower simulator) cannot fail it.
    """
    from vehicle_sim import Simulator

    speedup = 50.0
    if boats == 1:
        server = Simulator(None, home=(40.0, -63.0), config=SimConfig.fast())
        lock = server._lock
    else:
        server = Fleet(None, starts=line_starts((40.0, -63.0), boats), config=SimConfig.fast())
        lock = server._lock
    server.serve([], speedup=speedup)
    try:
        time.sleep(0.2)
        with lock:  # the stall: 20 sim s of backlog, beyond the 5 s the clock may catch up
            time.sleep(0.4)
        w0, t0 = time.monotonic(), server.t
        time.sleep(1.0)
        w1, t1 = time.monotonic(), server.t
        # at most the requested rate plus the 5 s (+ one 2.5 s slip margin) of backlog it may catch up
        assert t1 - t0 <= speedup * (w1 - w0) + 7.5 + 1.0, (t1 - t0, w1 - w0)
        assert t1 > t0  # and it does run
    finally:
        server.stop()
