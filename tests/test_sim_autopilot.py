"""Autopilot state machine, commands, parameters and telemetry (in-process, lockstep)."""

from __future__ import annotations

import hashlib

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as M
from simclient import SimClient

from vehicle_sim import MODES, SimConfig, Simulator
from vehicle_sim.link import secret_from_key

HOME = (40.0, -63.0)


def make(config=None, **kw):
    sim = Simulator(None, home=HOME, config=config or SimConfig.fast(**kw))
    return sim, SimClient(sim)


def test_boot_timeline_like_sitl_defaults():
    """Default timeline: INITIALISING -> MANUAL, GPS at ~9 s, arming refused < 25 s, EKF uses GPS at ~42 s."""
    sim, c = make(SimConfig())
    hb = c.wait("HEARTBEAT", timeout=0.2)
    assert (hb.type, hb.autopilot, hb.custom_mode) == (M.MAV_TYPE_SURFACE_BOAT, M.MAV_AUTOPILOT_ARDUPILOTMEGA, 16)
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert c.wait("HEARTBEAT", lambda m: m.custom_mode == 0, timeout=3) is not None
    gpi = c.wait("GLOBAL_POSITION_INT", timeout=2)
    assert (gpi.lat, gpi.lon) == (0, 0)
    # arming before ~25 s: refused, with ArduPilot's text
    sim.run_until(20)
    c.drain()
    ack = c.arm()
    assert ack.result == M.MAV_RESULT_FAILED
    assert "Arm: System not initialised" in c.texts()
    gpi = c.wait("GLOBAL_POSITION_INT", timeout=2)
    assert gpi.lat == int(round(HOME[0] * 1e7)) and gpi.lon == int(round(HOME[1] * 1e7))
    ekf = c.wait("EKF_STATUS_REPORT", timeout=2)
    assert ekf.flags == 167 and not ekf.flags & 16 and ekf.flags & 128
    sim.run_until(26)
    assert c.arm().result == M.MAV_RESULT_ACCEPTED
    assert c.arm().result == M.MAV_RESULT_ACCEPTED  # arming while armed: ACCEPTED
    # armed, EKF without absolute position: AUTO and GUIDED refused; HOLD accepted
    c.drain()
    assert c.set_mode(MODES["AUTO"]).result == M.MAV_RESULT_FAILED
    assert c.set_mode(MODES["GUIDED"]).result == M.MAV_RESULT_FAILED
    assert "Flight mode change failed" in c.texts()
    assert c.set_mode(MODES["HOLD"]).result == M.MAV_RESULT_ACCEPTED
    sim.run_until(43)
    c.drain()
    ekf = c.wait("EKF_STATUS_REPORT", timeout=2)
    assert ekf.flags == 831 and ekf.flags & 16 and not ekf.flags & 128
    assert c.set_mode(MODES["AUTO"]).result == M.MAV_RESULT_ACCEPTED


def test_gps_detected_near_9s():
    _sim, c = make(SimConfig())
    first = c.wait("GLOBAL_POSITION_INT", lambda m: m.lat != 0, timeout=15)
    assert 9.0 <= first.time_boot_ms / 1000 <= 10.1
    c.collect(5.0)
    # HOME_POSITION is sent once, when home is set (no stream)
    hps = [m for _, m in c.log if m.get_type() == "HOME_POSITION"]
    assert len(hps) == 1 and hps[0].latitude == int(round(HOME[0] * 1e7))


def test_any_mode_accepted_while_disarmed_even_without_position():
    sim, c = make(SimConfig())
    sim.run_until(5)
    for name in ("AUTO", "GUIDED", "LOITER", "RTL", "HOLD", "ACRO", "MANUAL"):
        assert c.set_mode(MODES[name]).result == 0, name
        assert sim.autopilot.mode == MODES[name]
    assert c.set_mode(2).result == M.MAV_RESULT_FAILED  # LEARNING no longer exists
    assert c.set_mode(16).result == M.MAV_RESULT_FAILED


def test_set_mode_message_acked_and_component_zero_accepted():
    sim, c = make()
    sim.run_until(2)
    c.mav.set_mode_send(1, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MODES["HOLD"])
    ack = c.wait("COMMAND_ACK")
    assert ack.command == M.MAVLINK_MSG_ID_SET_MODE and ack.result == 0 and sim.autopilot.mode == MODES["HOLD"]
    assert c.command(M.MAV_CMD_DO_SET_MODE, 1, MODES["LOITER"], target_component=0).result == 0
    assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, target_component=0).result == 0
    assert sim.autopilot.armed
    hb = c.wait("HEARTBEAT")
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED and hb.system_status == M.MAV_STATE_ACTIVE
    assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == 0
    hb = c.wait("HEARTBEAT")
    assert not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED and hb.system_status == M.MAV_STATE_STANDBY


def test_unknown_command_unsupported_and_other_targets_ignored():
    sim, c = make()
    sim.run_until(2)
    assert c.command(31999, 1).result == M.MAV_RESULT_UNSUPPORTED
    c.mav.command_long_send(7, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)  # another vehicle
    assert c.wait("COMMAND_ACK", timeout=1) is None and not sim.autopilot.armed


def test_parameters_defaults_set_and_unknown_names_silent():
    sim, c = make()
    sim.run_until(1)
    want = {
        "WP_SPEED": 2.0,
        "WP_RADIUS": 2.0,
        "FS_GCS_ENABLE": 0,
        "FS_ACTION": 2,
        "FS_TIMEOUT": 1.5,
        "MIS_DONE_BEHAVE": 1,
        "MIS_RESTART": 0,
        "MAV_SYSID": 1,
        "MAV_GCS_SYSID": 255,
        "MAV1_POSITION": 1,
        "ARMING_SKIPCHK": 0,
    }
    for name, val in want.items():
        c.mav.param_request_read_send(1, 1, name.encode(), -1)
        pv = c.wait("PARAM_VALUE", timeout=1)
        assert pv.param_id == name and pv.param_value == pytest.approx(val), name
    for old in ("ARMING_CHECK", "SYSID_THISMAV", "SR0_POSITION"):
        c.mav.param_request_read_send(1, 1, old.encode(), -1)
        assert c.wait("PARAM_VALUE", timeout=1) is None
        c.mav.param_set_send(1, 1, old.encode(), 0, M.MAV_PARAM_TYPE_INT32)
        assert c.wait("PARAM_VALUE", timeout=1) is None
    c.mav.param_set_send(1, 1, b"WP_SPEED", 3.5, M.MAV_PARAM_TYPE_REAL32)
    pv = c.wait("PARAM_VALUE", timeout=1)
    assert pv.param_id == "WP_SPEED" and pv.param_value == 3.5 and sim.autopilot.wp_speed() == 3.5
    c.mav.param_request_list_send(1, 1)
    pvs = [m for m in c.collect(0.5) if m.get_type() == "PARAM_VALUE"]
    assert len(pvs) == pvs[0].param_count and len({p.param_index for p in pvs}) == len(pvs)


def test_default_streams_at_1hz_sim_time_and_message_interval():
    sim, c = make()
    sim.run_until(3)
    c.drain()
    msgs = c.collect(10.0)
    counts = {}
    for m in msgs:
        counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
    for name in (
        "HEARTBEAT",
        "SYS_STATUS",
        "GPS_RAW_INT",
        "ATTITUDE",
        "VFR_HUD",
        "MISSION_CURRENT",
        "EKF_STATUS_REPORT",
        "BATTERY_STATUS",
        "SYSTEM_TIME",
        "TIMESYNC",
        "NAV_CONTROLLER_OUTPUT",
        "LOCAL_POSITION_NED",
        "POWER_STATUS",
        "MEMINFO",
    ):
        assert 9 <= counts.get(name, 0) <= 11, (name, counts.get(name))
    # GLOBAL_POSITION_INT: the 1 Hz stream plus one with each current-sensor sample (1 Hz)
    assert 18 <= counts["GLOBAL_POSITION_INT"] <= 22
    assert c.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 100000).result == 0
    assert c.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_VFR_HUD, -1).result == 0
    msgs = c.collect(5.0)
    att = sum(m.get_type() == "ATTITUDE" for m in msgs)
    assert 48 <= att <= 52 and not any(m.get_type() == "VFR_HUD" for m in msgs)
    c.mav.request_data_stream_send(1, 1, M.MAV_DATA_STREAM_EXTRA3, 4, 1)
    msgs = c.collect(5.0)
    assert 19 <= sum(m.get_type() == "SYSTEM_TIME" for m in msgs) <= 21


def test_request_message_home_and_autopilot_version():
    sim, c = make()
    sim.run_until(2)
    c.drain()
    assert c.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION).result == 0
    hp = c.wait("HOME_POSITION", timeout=1)
    assert hp.latitude == int(round(HOME[0] * 1e7))
    assert c.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION).result == 0
    av = c.wait("AUTOPILOT_VERSION", timeout=1)
    assert (
        av.capabilities & M.MAV_PROTOCOL_CAPABILITY_MISSION_INT and av.capabilities & M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    )
    assert c.command(M.MAV_CMD_GET_HOME_POSITION).result == 0


def test_timesync_request_answered():
    sim, c = make()
    sim.run_until(1)
    c.drain()
    c.mav.timesync_send(0, 123456789)
    m = c.wait("TIMESYNC", lambda m: m.ts1 == 123456789, timeout=1)
    assert m is not None and m.tc1 == pytest.approx(sim.t * 1e9, abs=0.1e9)


def _arm_auto(sim, c, n=3, dlat=1e-3):
    items = [SimClient.waypoint(i, HOME[0] + dlat * i, HOME[1]) for i in range(n)]
    assert c.upload(items).type == 0
    assert c.arm().result == 0
    assert c.set_mode(MODES["AUTO"]).result == 0


def test_gcs_failsafe_hold_after_timeout():
    sim, c = make(params=(("FS_GCS_ENABLE", 1),))
    sim.run_until(2)
    c.heartbeat()
    _arm_auto(sim, c)
    for _ in range(5):
        c.heartbeat()
        t_last = sim.t
        c.collect(1.0)
    assert sim.autopilot.mode == MODES["AUTO"]
    c.wait("HEARTBEAT", lambda m: m.custom_mode == MODES["HOLD"], timeout=5)
    assert sim.autopilot.mode == MODES["HOLD"]
    assert 1.5 <= sim.t - t_last <= 3.0
    assert "GCS Failsafe" in c.texts()


def test_gcs_failsafe_continue_in_auto_and_only_from_gcs_sysid():
    sim, c = make(params=(("FS_GCS_ENABLE", 2),))
    sim.run_until(2)
    c.heartbeat()
    _arm_auto(sim, c)
    other = SimClient(sim, sysid=200)
    for _ in range(5):
        other.heartbeat()  # not MAV_GCS_SYSID: does not count
        c.collect(1.0)
    assert sim.autopilot.mode == MODES["AUTO"] and sim.autopilot.failsafe
    assert "Failsafe - Continuing Auto Mode" in c.texts()


def test_signing_unsigned_commands_ignored_signed_accepted():
    secret = secret_from_key("correct horse")
    assert secret == hashlib.sha256(b"correct horse").digest()
    sim = Simulator(None, home=HOME, config=SimConfig.fast(signing_key=secret))
    sim.run_until(2)
    plain = SimClient(sim)
    plain.command(M.MAV_CMD_DO_SET_MODE, 1, MODES["HOLD"], timeout=1)
    assert sim.autopilot.mode != MODES["HOLD"]
    wrong = SimClient(sim, sysid=250, signing_secret=secret_from_key("wrong"))
    wrong.command(M.MAV_CMD_DO_SET_MODE, 1, MODES["HOLD"], timeout=1)
    assert sim.autopilot.mode != MODES["HOLD"]
    good = SimClient(sim, sysid=251, signing_secret=secret)
    ack = good.command(M.MAV_CMD_DO_SET_MODE, 1, MODES["HOLD"], timeout=1)
    assert ack is not None and ack.result == 0 and sim.autopilot.mode == MODES["HOLD"]
    # what the vehicle sends is signed
    raw = next(m for _, m in good.log if m.get_type() == "HEARTBEAT").get_msgbuf()
    assert raw[2] & 0x01 and len(raw) == 12 + raw[1] + 13


def test_tlog_readable_by_mavutil(tmp_path):
    path = tmp_path / "sim.tlog"
    sim = Simulator(None, home=HOME, config=SimConfig.fast(tlog=str(path)), epoch0=1.7e9)
    c = SimClient(sim)
    sim.run_until(3)
    c.command(M.MAV_CMD_DO_SET_MODE, 1, MODES["HOLD"])
    sim.stop()
    log = mavutil.mavlink_connection(str(path))
    types, stamps = [], []
    while True:
        m = log.recv_match()
        if m is None:
            break
        types.append(m.get_type())
        stamps.append(m._timestamp)
    assert types.count("HEARTBEAT") >= 3
    assert "COMMAND_LONG" in types and "COMMAND_ACK" in types  # received and sent
    assert stamps[0] == pytest.approx(1.7e9, abs=1.0) and stamps[-1] <= 1.7e9 + 3.5


def test_inprocess_mavutil_connection_in_the_controller_driven_lockstep():
    """Served in lockstep, the in-process connection's clock runs only for the steps it asks for (COMMAND_LONG
    31010): each step is acknowledged after everything the vehicle sent during it, at exactly the time asked
    for, and between steps the simulator answers at the held time."""
    from vehicle_sim.sim import STEP_COMMAND

    sim = Simulator(None, home=HOME, config=SimConfig.fast())
    sim.serve([], lockstep=True)
    conn = sim.connect_inprocess().mavlink_connection()
    seen: list = []

    def step(seconds: float) -> None:
        conn.mav.command_long_send(1, 1, STEP_COMMAND, 0, seconds, 0, 0, 0, 0, 0, 0)
        while True:
            m = conn.recv_match(blocking=True, timeout=5)
            assert m is not None, "no acknowledgement of the step"
            if m.get_type() == "COMMAND_ACK" and m.command == STEP_COMMAND:
                return
            seen.append(m)

    try:
        assert conn.recv_match(blocking=True, timeout=0.2) is None and sim.t == 0.0  # no step, no time
        step(3.0)
        assert sim.t == pytest.approx(3.0, abs=1e-9)
        hb = next(m for m in seen if m.get_type() == "HEARTBEAT")
        assert hb.type == M.MAV_TYPE_SURFACE_BOAT and conn.target_system == 1
        assert any(m.get_type() == "GLOBAL_POSITION_INT" and m.lat != 0 for m in seen)
        assert max(getattr(m, "time_boot_ms", 0) for m in seen) <= 3000  # all of it sent within the step
        conn.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, MODES["HOLD"], 0, 0, 0, 0, 0)
        ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)  # answered at the held time
        assert ack.command == M.MAV_CMD_DO_SET_MODE and ack.result == 0 and sim.t == pytest.approx(3.0, abs=1e-9)
        seen.clear()
        step(1.5)
        assert sim.t == pytest.approx(4.5, abs=1e-9)
        assert [m.custom_mode for m in seen if m.get_type() == "HEARTBEAT"][-1] == MODES["HOLD"]
    finally:
        conn.close()
        sim.stop()


def test_guided_goto_and_rtl_return_home():
    sim, c = make()
    sim.run_until(2)
    assert c.arm().result == 0
    assert c.set_mode(MODES["GUIDED"]).result == 0
    north = 100.0 / 111_035.0
    c.mav.set_position_target_global_int_send(
        0,
        1,
        1,
        M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        0b110111111000,
        int(round((HOME[0] + north) * 1e7)),
        int(round(HOME[1] * 1e7)),
        0,
        0,
        0,
        0,
        0,
        0,
        0,
        0,
        0,
    )
    c.collect(60.0, dt=0.1)
    lat, lon = sim.autopilot.position()
    assert (lat - HOME[0]) * 111_035.0 == pytest.approx(100.0, abs=2.5)
    assert c.set_mode(MODES["RTL"]).result == 0
    c.collect(60.0, dt=0.1)
    lat, lon = sim.autopilot.position()
    assert abs(lat - HOME[0]) * 111_035.0 < 2.5 and sim.autopilot.mode == MODES["RTL"]
    # DO_REPOSITION (COMMAND_INT) switches to GUIDED and goes
    c.mav.command_int_send(
        1,
        1,
        M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        M.MAV_CMD_DO_REPOSITION,
        0,
        0,
        -1,
        1,
        0,
        0,
        int(round(HOME[0] * 1e7)),
        int(round((HOME[1] + 0.0005) * 1e7)),
        0,
    )
    ack = c.wait("COMMAND_ACK", lambda m: m.command == M.MAV_CMD_DO_REPOSITION)
    assert ack.result == 0 and sim.autopilot.mode == MODES["GUIDED"]
    c.collect(40.0, dt=0.1)
    lat, lon = sim.autopilot.position()
    assert (lon - HOME[1]) * 111_320.0 * 0.766 == pytest.approx(0.0005 * 111_320.0 * 0.766, abs=2.5)


def test_mission_start_arguments_and_mis_total():
    sim, c = make()
    sim.run_until(2)
    items = [SimClient.waypoint(i, HOME[0] + 1e-4 * i, HOME[1]) for i in range(3)]
    assert c.upload(items).type == 0
    c.mav.param_request_read_send(1, 1, b"MIS_TOTAL", -1)
    assert c.wait("PARAM_VALUE").param_value == 3
    assert c.command(M.MAV_CMD_MISSION_START, 1, 2).result == M.MAV_RESULT_DENIED  # first/last item: unsupported
    assert sim.autopilot.mode == MODES["MANUAL"]
    assert c.command(M.MAV_CMD_MISSION_START, 0, 0).result == 0 and sim.autopilot.mode == MODES["AUTO"]


# -- reboot (brown-out / commanded) ---------------------------------------------------------------
def _ready_with_mission(c, sim):
    sim.run_until(3.0)
    c.drain()
    items = [c.waypoint(0, *HOME)] + [c.waypoint(k, HOME[0] + 1e-3 * k, HOME[1]) for k in (1, 2, 3)]
    assert c.upload(items).type == M.MAV_MISSION_ACCEPTED
    return items


def test_reboot_command_refused_armed_accepted_disarmed_and_keeps_mission_and_params():
    """Like Rover 4.7 SITL: 246 param1=1 while armed -> FAILED; disarmed -> ACCEPTED, then a reboot."""
    sim, c = make()
    _ready_with_mission(c, sim)
    assert c.command(M.MAV_CMD_DO_SET_PARAMETER, 0) is not None  # any command works before
    c.mav.param_set_send(1, 1, b"WP_SPEED", 3.5, M.MAV_PARAM_TYPE_REAL32)
    assert c.wait("PARAM_VALUE", lambda m: m.param_id == "WP_SPEED", timeout=1).param_value == 3.5
    assert c.arm().result == M.MAV_RESULT_ACCEPTED
    assert c.command(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1).result == M.MAV_RESULT_FAILED
    assert sim.autopilot.boot_count == 0 and sim.autopilot.armed
    c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0)
    c.mav.system_time_send(0, 0)  # (ignored: only to show the vehicle still listens)
    st0 = c.wait("SYSTEM_TIME", lambda m: m.time_unix_usec > 0, timeout=2)
    t_reboot = sim.t
    assert c.command(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1).result == M.MAV_RESULT_ACCEPTED
    ap = sim.autopilot
    assert ap.boot_count == 1 and ap.down and not ap.armed
    # silent while down (2 s), then boots again: INITIALISING, time_boot_ms from 0
    assert c.wait(("HEARTBEAT", "SYSTEM_TIME"), timeout=1.5) is None
    hb = c.wait("HEARTBEAT", timeout=1.0)
    assert hb is not None and hb.custom_mode == MODES["INITIALISING"]
    st = c.wait("SYSTEM_TIME", lambda m: m.time_unix_usec > 0, timeout=2)
    assert st.time_boot_ms < 2000 and sim.t - t_reboot > 2.0
    # UTC runs on through the reboot (the GPS clock); the boot time restarted
    utc_boot0 = st0.time_unix_usec / 1e6 - st0.time_boot_ms / 1e3
    utc_boot1 = st.time_unix_usec / 1e6 - st.time_boot_ms / 1e3
    assert utc_boot1 - utc_boot0 == pytest.approx(t_reboot + 2.0, abs=0.1)
    # parameters and the stored mission survived (eeprom)
    assert ap.p("WP_SPEED") == 3.5 and ap.store.count(0) == 4
    got = c.download()
    assert got is not None and len(got) == 4 and got[3].x == int(round((HOME[0] + 3e-3) * 1e7))
    cur = c.wait("MISSION_CURRENT", timeout=2)
    assert cur.total == 3 and cur.mission_state == M.MISSION_STATE_NOT_STARTED


def test_brownout_reboot_mid_mission_stops_the_boat_and_forgets_progress():
    sim, c = make()
    _ready_with_mission(c, sim)
    assert c.arm().result == 0 and c.set_mode(MODES["AUTO"]).result == 0
    assert c.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 1, timeout=120) is not None
    ap = sim.autopilot
    v0, t0 = ap.boat.speed, sim.t
    sim.reboot(downtime_s=1.0)  # a brown-out: no command, no ACK
    assert not ap.armed and ap.mode == MODES["INITIALISING"] and ap.mission_index == 0
    sim.run_until(sim.t + 3.0)
    # disarmed, motor off: the hull coasts down by its drag alone, v = v0 / (1 + k v0 t), k = 0.25 /m
    assert ap.mode == MODES["MANUAL"] and v0 > 1.5
    assert ap.boat.speed == pytest.approx(v0 / (1 + 0.25 * v0 * (sim.t - t0)), rel=0.05)
    c.drain()
    cur = c.wait("MISSION_CURRENT", timeout=2)
    assert cur.mission_state == M.MISSION_STATE_NOT_STARTED and cur.total == 3


def test_gps_noise_is_seeded_correlated_and_of_the_configured_size():
    import numpy as np

    def track(seed):
        sim = Simulator(None, home=HOME, config=SimConfig.fast(gps_noise_m=3.0, gps_noise_tau_s=20.0, seed=seed))
        ap, out = sim.autopilot, []
        for _ in range(4000):
            sim.step(0.5)
            lat, lon = ap.reported_position()
            tl, tn = ap.position()
            out.append(((lat - tl) * 111_000.0, (lon - tn) * 111_000.0 * np.cos(np.radians(HOME[0]))))
        return np.array(out)

    a, b, c = track(1), track(1), track(2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)  # seeded
    # 2000 s / 20 s correlation time = ~100 independent values per axis: std within ~20 %
    assert a.std(axis=0) == pytest.approx([3.0, 3.0], rel=0.25)
    lag1 = np.corrcoef(a[:-1, 0], a[1:, 0])[0, 1]
    assert lag1 == pytest.approx(np.exp(-0.5 / 20.0), abs=0.02)  # Gauss-Markov: exp(-dt/tau)
    # and the reported fix carries it
    sim = Simulator(None, home=HOME, config=SimConfig.fast(gps_noise_m=3.0, seed=1))
    cl = SimClient(sim)
    sim.run_until(2.0)
    cl.drain()
    g = cl.wait("GLOBAL_POSITION_INT", lambda m: m.lat != 0, timeout=2)
    lat, _lon = sim.autopilot.reported_position()
    assert abs(g.lat / 1e7 - lat) < 2e-6 and (g.lat, g.lon) != (int(round(HOME[0] * 1e7)), int(round(HOME[1] * 1e7)))


def test_system_time_utc_settable_and_off_for_a_vehicle_without_a_clock():
    sim = Simulator(None, home=HOME, config=SimConfig.fast(), epoch0=1714521600.0)  # 2024-05-01T00:00:00Z
    c = SimClient(sim)
    st = c.wait("SYSTEM_TIME", lambda m: m.time_unix_usec > 0, timeout=3)
    assert st.time_unix_usec / 1e6 - st.time_boot_ms / 1e3 == pytest.approx(1714521600.0, abs=0.002)
    sim = Simulator(None, home=HOME, config=SimConfig.fast(utc_clock=False))
    c = SimClient(sim)
    sts = [m for m in c.collect(3.0) if m.get_type() == "SYSTEM_TIME"]
    assert sts and all(m.time_unix_usec == 0 for m in sts) and sts[-1].time_boot_ms > 2000
