"""Link impairment, fuzzing, sockets and the command line."""

from __future__ import annotations

import random
import socket
import subprocess
import sys
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as M
from simclient import SimClient, free_port

from vehicle_sim import MODES, LinkConfig, SimConfig, Simulator
from vehicle_sim.cli import main as cli_main

HOME = (40.0, -63.0)


def wps(n):
    return [SimClient.waypoint(i, HOME[0] + 1e-5 * i, HOME[1] - 1e-5 * i) for i in range(n)]


@pytest.mark.parametrize("seed", [3, 11])
def test_lossy_link_100_item_upload_completes_and_state_is_exact(seed):
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.run_until(1.0)
    c = SimClient(sim, link_config=LinkConfig(loss=0.2, seed=seed))
    items = wps(101)
    ack = c.upload(items, timeout=600.0)
    assert ack is not None and ack.type == M.MAV_MISSION_ACCEPTED
    link = sim.links[0]
    # loss really happened, at the configured rate, both ways
    assert link.stats["tx_lost"] / link.stats["tx_frames"] == pytest.approx(0.2, abs=0.04)
    assert link.stats["rx_lost"] / (link.stats["rx_lost"] + link.stats["rx_frames"]) == pytest.approx(0.2, abs=0.05)
    # the vehicle's own state: exactly the uploaded mission (home at 0)
    stored = sim.autopilot.store.items[0]
    assert len(stored) == 101
    assert [(s.x, s.y) for s in stored[1:]] == [(i.x, i.y) for i in items[1:]]
    # and a lossy read-back agrees
    got = c.download(timeout=600.0)
    assert [(g.x, g.y) for g in got[1:]] == [(i.x, i.y) for i in items[1:]]


def test_baud_limits_throughput_and_latency_delays():
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.run_until(1.0)
    c = SimClient(sim, link_config=LinkConfig(baud=57600, latency_s=0.1))
    c.dt = 0.002
    c.drain()
    t0 = sim.t
    c.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["HOLD"], 0, 0, 0, 0, 0)
    ack = c.wait("COMMAND_ACK")
    assert ack is not None and sim.t - t0 >= 0.2  # two one-way latencies
    # byte budget: at most baud/10 bytes per simulated second leave the vehicle
    sim.links[0].stats.clear()
    c.mav.param_request_list_send(1, 1)
    t1 = sim.t
    c.collect(2.0, dt=0.01)
    delivered = sum(len(m.get_msgbuf()) for t, m in c.log if t > t1)
    assert delivered <= 5760 * 2.0 + 300


def test_scheduled_drop_silences_the_link():
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    c = SimClient(sim, link_config=LinkConfig(drops=((5.0, 3.0),)))
    c.collect(10.0)
    times = [t for t, m in c.log if m.get_type() == "HEARTBEAT"]
    assert not any(5.05 < t < 8.0 for t in times)
    assert any(t < 5.0 for t in times) and any(t >= 8.0 for t in times)


def test_arm_relative_drop_counts_from_the_first_arming():
    # LinkConfig.arm_drops (vehicle-sim --drop arm+START:DURATION): the outage falls the same number of
    # simulated seconds into the mission however long the vehicle waited for a client before arming
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    c = SimClient(sim, link_config=LinkConfig(arm_drops=((2.0, 3.0),)))
    c.collect(6.0)  # 6 s unarmed: no outage yet (an outage at 2..5 s on the clock would show here)
    hb = [t for t, m in c.log if m.get_type() == "HEARTBEAT"]
    assert any(2.5 < t < 5.0 for t in hb)
    c.arm(force=True)
    t_arm = sim.autopilot.first_armed_clock
    assert t_arm is not None and 5.9 <= t_arm < 7.0
    c.collect(8.0)
    hb = [t for t, m in c.log if m.get_type() == "HEARTBEAT"]
    assert not any(t_arm + 2.05 < t < t_arm + 5.0 for t in hb)
    assert any(t_arm < t < t_arm + 2.0 for t in hb) and any(t >= t_arm + 5.0 for t in hb)
    # a link opened after the arming (a GCS reconnecting) counts from the same arming
    SimClient(sim, link_config=LinkConfig(arm_drops=((2.0, 3.0),)))
    assert sim.links[-1].armed_at == t_arm and sim.links[-1].is_down(t_arm + 3.0)


def test_drop_that_breaks_the_link_holds_until_the_client_reconnects():
    # LinkConfig.drops_break_link (vehicle-sim --drops-break-link, passt-mav demo --inject-link-drop): the link
    # open when the drop began stays silent after its 3 s; a link opened during the drop hears the vehicle
    # once the drop is over, one opened after it at once
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    cfg = LinkConfig(drops=((5.0, 3.0),), drops_break_link=True)
    old = SimClient(sim, link_config=cfg)
    old.collect(6.0)
    during = SimClient(sim, link_config=cfg)  # opened at 6 s, inside the drop
    assert during.sim.links[-1].opened_at == pytest.approx(6.0)
    while sim.t < 12.0:
        sim.step(0.05)
        old.pump(), during.pump()
    hb_old = [t for t, m in old.log if m.get_type() == "HEARTBEAT"]
    hb_during = [t for t, m in during.log if m.get_type() == "HEARTBEAT"]
    assert any(t < 5.0 for t in hb_old) and not any(t > 5.05 for t in hb_old)
    assert not any(t < 8.0 for t in hb_during) and any(t >= 8.0 for t in hb_during)
    after = SimClient(sim, link_config=cfg)
    after.collect(2.0)
    assert [m for t, m in after.log if m.get_type() == "HEARTBEAT"]
    assert not sim.links[0].is_down(4.9) and sim.links[0].is_down(1e6)  # the interrupted link: for good


def test_cli_parses_arm_relative_drops():
    from vehicle_sim.cli import _drop, _split_drops

    d = [_drop("10:5"), _drop("arm+300:900")]
    assert _split_drops(d) == {"drops": ((10.0, 5.0),), "arm_drops": ((300.0, 900.0),)}


def _frames(rng: random.Random, n: int) -> list[bytes]:
    """Valid frames of many message types (packed by pymavlink), for mutation."""
    mav = M.MAVLink(None, srcSystem=255, srcComponent=190)
    mk = [
        lambda: M.MAVLink_mission_count_message(1, 1, rng.randint(0, 2000), rng.choice([0, 1, 2, 7, 255])),
        lambda: M.MAVLink_mission_item_int_message(
            1,
            1,
            rng.randint(0, 50),
            rng.randint(0, 12),
            rng.randint(0, 6000),
            rng.randint(0, 3),
            1,
            rng.uniform(-1e9, 1e9),
            0,
            0,
            float("nan"),
            rng.randint(-(2**31), 2**31 - 1),
            rng.randint(-(2**31), 2**31 - 1),
            0,
            rng.choice([0, 1, 2, 9]),
        ),
        lambda: M.MAVLink_mission_request_int_message(1, 1, rng.randint(0, 65535), rng.randint(0, 3)),
        lambda: M.MAVLink_mission_request_list_message(1, 1, rng.randint(0, 3)),
        lambda: M.MAVLink_command_long_message(
            rng.choice([0, 1]),
            rng.choice([0, 1]),
            rng.randint(0, 65535),
            0,
            *(rng.choice([0.0, 1.0, -1.0, 1e38, float("nan"), float("inf"), rng.uniform(-1e6, 1e6)]) for _ in range(7)),
        ),
        lambda: M.MAVLink_command_int_message(
            1,
            1,
            rng.randint(0, 20),
            rng.randint(0, 65535),
            0,
            0,
            *(rng.uniform(-1e9, 1e9) for _ in range(4)),
            rng.randint(-(2**31), 2**31 - 1),
            rng.randint(-(2**31), 2**31 - 1),
            0.0,
        ),
        lambda: M.MAVLink_param_set_message(
            1,
            1,
            rng.choice([b"WP_SPEED", b"FS_GCS_ENABLE", b"MAV1_POSITION", b"\xff\xfe", b"X" * 16]),
            rng.choice([float("nan"), 1e30, -5.0, 0.5]),
            9,
        ),
        lambda: M.MAVLink_param_request_read_message(1, 1, b"WP_RADIUS", rng.randint(-1, 400)),
        lambda: M.MAVLink_set_mode_message(1, rng.randint(0, 255), rng.randint(0, 2**32 - 1)),
        lambda: M.MAVLink_mission_set_current_message(1, 1, rng.randint(0, 65535)),
        lambda: M.MAVLink_mission_clear_all_message(1, 1, rng.choice([0, 1, 2, 255, 9])),
        lambda: M.MAVLink_request_data_stream_message(
            1, 1, rng.randint(0, 255), rng.randint(0, 65535), rng.randint(0, 1)
        ),
        lambda: M.MAVLink_timesync_message(0, rng.randint(-(2**63), 2**63 - 1)),
        lambda: M.MAVLink_set_position_target_global_int_message(
            0, 1, 1, 6, 0, rng.randint(-(2**31), 2**31 - 1), rng.randint(-(2**31), 2**31 - 1), 0, 0, 0, 0, 0, 0, 0, 0, 0
        ),
        lambda: M.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3),
    ]
    out = []
    for _ in range(n):
        msg = rng.choice(mk)()
        try:
            out.append(bytes(msg.pack(mav)))
        except Exception:  # noqa: BLE001, S112 - a value pymavlink refuses to pack: skip it
            continue
    return out


def _mutate(rng: random.Random, f: bytes) -> bytes:
    b = bytearray(f)
    r = rng.random()
    if r < 0.25:
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(len(b))] = rng.randrange(256)
    elif r < 0.4:
        b = b[: rng.randrange(1, len(b))]
    elif r < 0.5:
        b = bytearray(rng.randbytes(rng.randint(1, 300)))
    elif r < 0.6:
        b[1] = rng.randrange(256)  # wrong length
    elif r < 0.7:
        b = bytearray(b"\xfd" + rng.randbytes(rng.randint(0, 40)))
    # else: valid frame (exercises the state machine with random values)
    return bytes(b)


def _fuzz(n: int, seed: int) -> Simulator:
    rng = random.Random(seed)
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.run_until(2.0)
    ep = sim.connect_inprocess()
    good = _frames(rng, 2000)
    t0 = time.monotonic()
    sent = 0
    while sent < n:
        if (sent // 50) % 2:
            # every other burst: well-formed frames with random values (drives the state machines)
            burst = b"".join(rng.choice(good) for _ in range(50))
        else:
            burst = b"".join(_mutate(rng, rng.choice(good)) for _ in range(50))
        ep.write(burst)
        sent += 50
        sim.step(0.02)
        ep.read()
        assert time.monotonic() - t0 < 60 + n / 500, "fuzzing hangs"
    return sim


def _still_works(sim):
    c = SimClient(sim, sysid=250)
    sim.autopilot.disarm()
    sim.autopilot.missions.uploads.clear()  # a fuzzed upload from another GCS would (correctly) deny ours
    assert c.set_mode(MODES["HOLD"]).result == 0
    assert c.upload(wps(3)).type == 0


def test_fuzz_inprocess_1e4_frames():
    sim = _fuzz(10_000, seed=1)
    assert sim.links[0].stats["rx_bad"] > 1000 and sim.links[0].stats["rx_frames"] > 5000
    _still_works(sim)


@pytest.mark.slow(reason="10^5 fuzzed frames through the simulator's parser (the default run fuzzes fewer): ~1 min")
def test_fuzz_inprocess_1e5_frames():
    sim = _fuzz(100_000, seed=2)
    _still_works(sim)


def test_tcp_two_clients_and_socket_fuzz_smoke():
    port = free_port()
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.serve([f"tcp:127.0.0.1:{port}"], speedup=20)
    try:
        a = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255)
        b = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=254)
        assert a.wait_heartbeat(timeout=5) and b.wait_heartbeat(timeout=5)
        # past INITIALISING (mode changes are refused while the autopilot boots)
        assert a.recv_match(type="HEARTBEAT", condition="HEARTBEAT.custom_mode==0", blocking=True, timeout=5)
        # garbage on a third socket
        rng = random.Random(5)
        s = socket.create_connection(("127.0.0.1", port))
        for f in _frames(rng, 300):
            s.sendall(_mutate(rng, f))
        s.sendall(rng.randbytes(5000))
        s.close()
        a.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["HOLD"], 0, 0, 0, 0, 0)
        ack = a.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)
        assert ack is not None and ack.result == 0
        hb = b.recv_match(type="HEARTBEAT", condition="HEARTBEAT.custom_mode==4", blocking=True, timeout=5)
        assert hb is not None
        a.close()
        b.close()
    finally:
        sim.stop()


def test_udpout_like_sitl_gcs_output():
    port = free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.serve([f"udpout:127.0.0.1:{port}"], speedup=20)
    try:
        assert gcs.wait_heartbeat(timeout=5)
        # past INITIALISING (mode changes are refused while the autopilot boots)
        assert gcs.recv_match(type="HEARTBEAT", condition="HEARTBEAT.custom_mode==0", blocking=True, timeout=5)
        gcs.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["LOITER"], 0, 0, 0, 0, 0)
        ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)
        assert ack is not None and ack.result == 0
    finally:
        sim.stop()
        gcs.close()


def test_cli_help_and_bad_input(capsys):
    with pytest.raises(SystemExit) as e:
        cli_main(["--help"])
    assert e.value.code == 0
    assert "vehicle-sim" in capsys.readouterr().out
    assert cli_main(["--home", "95,0", "--duration", "1"]) == 2
    assert "--home" in capsys.readouterr().err
    assert cli_main(["--home", "40,-63", "--listen", "bogus:1"]) == 2
    assert cli_main(["--field", "/nonexistent.nc"]) == 2
    assert cli_main(["--home", "40,-63", "--param", "ARMING_CHECK=0"]) == 2


def test_cli_serves_and_stops(tmp_path):
    port = free_port()
    tlog = tmp_path / "cli.tlog"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "vehicle_sim.cli",
            "--home",
            "40,-63",
            "--listen",
            f"tcp:127.0.0.1:{port}",
            "--speedup",
            "10",
            "--fast-boot",
            "--tlog",
            str(tlog),
            "--quiet",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        conn = None
        for _ in range(100):
            try:
                conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255)
                break
            except OSError:
                time.sleep(0.1)
        assert conn is not None and conn.wait_heartbeat(timeout=10)
        conn.close()
    finally:
        import signal

        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert tlog.stat().st_size > 100


def test_cli_field_options_metric_anchor_region_and_start_time(tmp_path):
    import numpy as np

    import geo
    from passt_mav.fields import FlowField
    from vehicle_sim.cli import _load_field, _start_time, build_parser

    g = geo.MetricRegionGrid(0.0, 9.0, 0.0, 9.0, 10, 10, anchor_lat=10.0, anchor_lon=10.0)
    data = np.ones((2, 2, 10, 10), np.float32)
    FlowField(data, g, np.array([0.0, 1.0]), None, "1").to_netcdf(tmp_path / "m.nc")
    args = build_parser().parse_args(
        ["--field", str(tmp_path / "m.nc"), "--anchor", "40,-63", "--scale", "100", "--rotation", "30"]
    )
    f = _load_field(args)
    assert (f.grid.anchor_lat, f.grid.anchor_lon, f.grid.scale, f.grid.rotation_deg) == (40.0, -63.0, 100.0, 30.0)
    lat, lon = f.grid.fcell_to_latlon(4.5, 4.5)
    assert (float(lat), float(lon)) == pytest.approx((40.0, -63.0), abs=1e-9)
    geo_grid = geo.RegionGrid(39.0, -64.0, 40.0, -63.0, 11, 11)
    FlowField(
        np.zeros((3, 2, 11, 11), np.float32), geo_grid, np.array([0.0, 3600.0, 7200.0]), "2020-01-01T00:00:00Z"
    ).to_netcdf(tmp_path / "g.nc")
    args = build_parser().parse_args(["--field", str(tmp_path / "g.nc"), "--region", "39.2,-63.8,39.5,-63.5"])
    f = _load_field(args)
    assert f.grid.shape == (4, 4) and f.grid.south == pytest.approx(39.2)
    assert _start_time("2020-01-01T01:30:00Z", f) == 5400.0
    assert _start_time("120", f) == 120.0
    assert cli_main(["--field", str(tmp_path / "g.nc"), "--anchor", "40,-63"]) == 2  # metric-only option


def test_lockstep_over_tcp_advances_only_when_asked():
    from vehicle_sim.sim import STEP_COMMAND

    port = free_port()
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.serve([f"tcp:127.0.0.1:{port}"], lockstep=True)
    try:
        conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255)
        time.sleep(0.3)
        assert sim.t == 0.0
        conn.mav.command_long_send(1, 1, STEP_COMMAND, 0, 5.0, 0, 0, 0, 0, 0, 0)
        ack = conn.recv_match(
            type="COMMAND_ACK", condition=f"COMMAND_ACK.command=={STEP_COMMAND}", blocking=True, timeout=10
        )
        assert ack is not None and ack.result == 0
        assert sim.t == pytest.approx(5.0, abs=1e-6)
        time.sleep(0.2)
        assert sim.t == pytest.approx(5.0, abs=1e-6)
        # messages are answered at the frozen time
        conn.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["HOLD"], 0, 0, 0, 0, 0)
        ack = conn.recv_match(type="COMMAND_ACK", condition="COMMAND_ACK.command==176", blocking=True, timeout=5)
        assert ack is not None and ack.result == 0 and sim.t == pytest.approx(5.0, abs=1e-6)
        conn.close()
    finally:
        sim.stop()


def test_inprocess_mavutil_with_served_clock():
    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    conn = sim.connect_inprocess().mavlink_connection()  # the serving thread drives time
    sim.serve([], speedup=20)
    try:
        assert conn.recv_match(type="HEARTBEAT", condition="HEARTBEAT.custom_mode==0", blocking=True, timeout=5)
        conn.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["HOLD"], 0, 0, 0, 0, 0)
        ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)
        assert ack is not None and ack.result == 0
    finally:
        sim.stop()
