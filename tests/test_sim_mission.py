"""Mission protocol of the simulator against shared/ARDUPILOT_ROVER.md (pymavlink, in-process, lockstep)."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as M
from simclient import SimClient

from vehicle_sim import MODES, SimConfig, Simulator

HOME = (40.0, -63.0)


def make(**kw):
    cfg = SimConfig.fast(**kw)
    sim = Simulator(None, home=HOME, config=cfg)
    sim.run_until(2.0)  # past boot, GPS, EKF and storage init
    return sim, SimClient(sim)


def wps(n, dlat=1e-4, mission_type=0, start=0):
    """n items: seq 0 a placeholder (home), then a line north."""
    return [SimClient.waypoint(i, HOME[0] + dlat * (i + start), HOME[1], mission_type) for i in range(n)]


def test_upload_requests_are_mission_request_not_int_and_ack_only_at_end():
    _sim, c = make()
    items = wps(4)
    c.mav.mission_count_send(1, 1, 4, 0)
    seen = []
    for k in range(4):
        m = c.wait(("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"))
        assert m is not None
        seen.append(m.get_type())
        assert m.get_type() == "MISSION_REQUEST" and m.get_msgId() == 40 and m.seq == k and m.mission_type == 0
        c.mav.send(items[k])
    ack = c.wait("MISSION_ACK")
    assert ack.type == M.MAV_MISSION_ACCEPTED and ack.mission_type == 0
    assert "MISSION_REQUEST_INT" not in seen


def test_seq0_is_home_and_download_round_trips_degE7_exactly():
    _sim, c = make()
    items = [SimClient.waypoint(0, 41.5, -60.0)]  # a "first waypoint" at seq 0: lost, replaced by home
    odd = [(40.0001234, -63.0004321), (39.9999999, -62.9999999), (40.00005, -63.00005)]
    items += [SimClient.waypoint(i + 1, la, lo) for i, (la, lo) in enumerate(odd)]
    assert c.upload(items).type == M.MAV_MISSION_ACCEPTED
    got = c.download()
    assert len(got) == 4  # MISSION_COUNT counts home
    h = got[0]
    assert (h.x, h.y, h.frame, h.seq) == (int(round(HOME[0] * 1e7)), int(round(HOME[1] * 1e7)), 0, 0)
    for sent, back in zip(items[1:], got[1:]):
        assert (back.x, back.y, back.command, back.seq) == (sent.x, sent.y, sent.command, sent.seq)
        assert back.mission_type == 0


def test_float_mission_item_accepted_with_warning():
    _sim, c = make()
    c.mav.mission_count_send(1, 1, 2, 0)
    for k in range(2):
        c.wait("MISSION_REQUEST")
        c.mav.mission_item_send(1, 1, k, 3, 16, 0, 1, 0, 0, 0, 0, 40.0002, -63.0001, 0.0, 0)
    assert c.wait("MISSION_ACK").type == M.MAV_MISSION_ACCEPTED
    assert "got MISSION_ITEM; GCS should send MISSION_ITEM_INT" in c.texts()
    got = c.download()
    # float32 carries ~7 digits: the item is stored as the float rounded to degE7 (why ArduPilot warns)
    f32 = np.float32
    assert (got[1].x, got[1].y) == (round(float(f32(40.0002)) * 1e7), round(float(f32(-63.0001)) * 1e7))
    assert abs(got[1].x - 400002000) < 50


def test_count_truncates_at_once_and_failed_upload_leaves_a_mix():
    sim, c = make(mission_timeout_s=8.0)
    old = wps(6, dlat=1e-4)
    assert c.upload(old).type == M.MAV_MISSION_ACCEPTED
    # new upload of 5 items stops after 3 (seq 0..2): storage is 5 long, 1..2 new, 3..4 old
    new = wps(5, dlat=2e-4)
    c.mav.mission_count_send(1, 1, 5, 0)
    for k in range(3):
        c.wait("MISSION_REQUEST", lambda m, k=k: m.seq == k)
        c.mav.send(new[k])
    assert sim.autopilot.store.count(0) == 5  # truncated at once (old had 6)
    ack = c.wait("MISSION_ACK", timeout=10.0)
    assert ack.type == M.MAV_MISSION_OPERATION_CANCELLED
    got = c.download()
    assert [g.x for g in got[1:]] == [new[1].x, new[2].x, old[3].x, old[4].x]


def test_rerequest_after_one_second_and_cancel_after_eight():
    sim, c = make()
    c.mav.mission_count_send(1, 1, 3, 0)
    first = c.wait("MISSION_REQUEST")
    t0 = sim.t
    reqs = [m for m in c.collect(9.0, dt=0.02) if m.get_type() == "MISSION_REQUEST"]
    times = [t for t, m in c.log if m.get_type() == "MISSION_REQUEST" and t > t0]
    assert first.seq == 0 and all(r.seq == 0 for r in reqs)
    assert 1.0 <= times[0] - t0 <= 1.2
    assert 6 <= len(reqs) <= 8  # about one a second until the cancel
    acks = [m for _, m in c.log if m.get_type() == "MISSION_ACK"]
    assert acks and acks[-1].type == M.MAV_MISSION_OPERATION_CANCELLED
    cancel_t = [t for t, m in c.log if m.get_type() == "MISSION_ACK"][-1]
    assert 8.0 <= cancel_t - t0 <= 8.3
    assert "Mission upload timeout" in c.texts()


def test_out_of_sequence_item_gets_invalid_sequence_and_transfer_continues():
    _sim, c = make()
    items = wps(3)
    c.mav.mission_count_send(1, 1, 3, 0)
    c.wait("MISSION_REQUEST", lambda m: m.seq == 0)
    c.mav.send(items[2])
    ack = c.wait("MISSION_ACK")
    assert ack.type == M.MAV_MISSION_INVALID_SEQUENCE and ack.mission_type == 0
    c.mav.send(items[0])
    c.wait("MISSION_REQUEST", lambda m: m.seq == 1)
    c.mav.send(items[1])
    c.wait("MISSION_REQUEST", lambda m: m.seq == 2)
    c.mav.send(items[2])
    assert c.wait("MISSION_ACK").type == M.MAV_MISSION_ACCEPTED


def test_second_gcs_denied_mid_transfer_and_download_denied_during_upload():
    sim, c = make()
    other = SimClient(sim, sysid=254, compid=190)
    same_sys_other_comp = SimClient(sim, sysid=255, compid=1)
    c.mav.mission_count_send(1, 1, 3, 0)
    c.wait("MISSION_REQUEST")
    other.mav.mission_count_send(1, 1, 2, 0)
    assert other.wait("MISSION_ACK").type == M.MAV_MISSION_DENIED
    same_sys_other_comp.mav.mission_count_send(1, 1, 2, 0)
    assert same_sys_other_comp.wait("MISSION_ACK").type == M.MAV_MISSION_DENIED
    other.mav.mission_request_list_send(1, 1, 0)
    assert other.wait(("MISSION_ACK", "MISSION_COUNT")).get_type() == "MISSION_ACK"
    c.mav.mission_request_list_send(1, 1, 0)
    m = c.wait(("MISSION_ACK", "MISSION_COUNT"))
    assert m.get_type() == "MISSION_ACK" and m.type == M.MAV_MISSION_DENIED
    # a fence download is a different list: not denied
    other.mav.mission_request_list_send(1, 1, 1)
    m = other.wait(("MISSION_ACK", "MISSION_COUNT"))
    assert m.get_type() == "MISSION_COUNT" and m.mission_type == 1


def test_no_space_over_capacity():
    _sim, c = make(mission_capacity=(50, 10, 5))
    c.mav.mission_count_send(1, 1, 51, 0)
    assert c.wait("MISSION_ACK").type == M.MAV_MISSION_NO_SPACE
    c.mav.mission_count_send(1, 1, 11, 1)
    ack = c.wait("MISSION_ACK")
    assert ack.type == M.MAV_MISSION_NO_SPACE and ack.mission_type == 1
    assert c.upload(wps(50)).type == M.MAV_MISSION_ACCEPTED


def test_no_space_right_after_boot_then_retry_succeeds():
    cfg = SimConfig(storage_ready_s=3.0)
    sim = Simulator(None, home=HOME, config=cfg)
    c = SimClient(sim)
    sim.run_until(0.5)
    c.mav.mission_count_send(1, 1, 3, 0)
    assert c.wait("MISSION_ACK", timeout=0.5).type == M.MAV_MISSION_NO_SPACE
    sim.run_until(3.5)
    assert c.upload(wps(3)).type == M.MAV_MISSION_ACCEPTED


def test_legacy_mission_request_download_gets_float_items():
    _sim, c = make()
    assert c.upload(wps(3)).type == M.MAV_MISSION_ACCEPTED
    got = c.download(legacy=True)
    assert [g.get_type() for g in got] == ["MISSION_ITEM"] * 3
    assert got[2].x == pytest.approx(HOME[0] + 2e-4, abs=4e-6)  # float32 spacing at 40 deg
    assert "got MISSION_REQUEST; use MISSION_REQUEST_INT!" in c.texts()


def test_fence_and_rally_separate_and_clear_all_per_type():
    _sim, c = make()
    assert c.upload(wps(4)).type == M.MAV_MISSION_ACCEPTED
    fence = [
        SimClient.waypoint(i, HOME[0] + 0.01 * (i % 2), HOME[1] + 0.01 * (i // 2), 1, command=5001, frame=5)
        for i in range(4)
    ]
    rally = [SimClient.waypoint(0, HOME[0] + 0.001, HOME[1], 2, command=5100, frame=6)]
    assert c.upload(fence, mission_type=1).mission_type == 1
    assert c.upload(rally, mission_type=2).mission_type == 2
    assert len(c.download(0)) == 4 and len(c.download(1)) == 4 and len(c.download(2)) == 1
    f = c.download(1)
    assert f[0].x == fence[0].x and f[0].command == 5001  # no home in fence lists
    c.mav.mission_clear_all_send(1, 1, 1)
    ack = c.wait("MISSION_ACK")
    assert ack.type == M.MAV_MISSION_ACCEPTED and ack.mission_type == 1
    assert c.download(1) == [] and len(c.download(0)) == 4 and len(c.download(2)) == 1
    c.mav.mission_clear_all_send(1, 1, 0)
    assert c.wait("MISSION_ACK").mission_type == 0
    assert len(c.download(0)) == 1  # home only


def test_mission_current_total_excludes_home_and_states():
    _sim, c = make()
    mc = c.wait("MISSION_CURRENT", timeout=2)
    assert mc.mission_state == M.MISSION_STATE_NO_MISSION
    assert c.upload(wps(6)).type == M.MAV_MISSION_ACCEPTED
    mc = c.wait("MISSION_CURRENT", timeout=2)
    assert mc.total == 5 and mc.mission_state == M.MISSION_STATE_NOT_STARTED
    assert c.arm().result == 0
    assert c.set_mode(MODES["AUTO"]).result == 0
    mc = c.wait("MISSION_CURRENT", timeout=2)
    assert mc.mission_state == M.MISSION_STATE_ACTIVE and mc.seq == 1


def test_mission_runs_to_completion_with_reached_messages_and_stays_armed_in_auto():
    sim, c = make()
    n = 4  # home + 3 waypoints 11 m apart
    assert c.upload(wps(n)).type == M.MAV_MISSION_ACCEPTED
    assert c.arm().result == 0
    assert c.command(M.MAV_CMD_MISSION_START, 0, 0).result == 0
    done = c.wait("STATUSTEXT", lambda m: m.text == "Mission Complete", timeout=120)
    assert done is not None
    reached = [m.seq for _, m in c.log if m.get_type() == "MISSION_ITEM_REACHED"]
    assert reached == [1, 2, 3]
    texts = [t for t in c.texts() if t.startswith("Reached waypoint")]
    assert [t.split()[2] for t in texts] == ["#1", "#2", "#3"]
    mc = c.wait("MISSION_CURRENT", timeout=2)
    assert (mc.seq, mc.total, mc.mission_state) == (3, 3, M.MISSION_STATE_COMPLETE)
    hb = c.wait("HEARTBEAT", timeout=2)
    assert hb.custom_mode == MODES["AUTO"] and hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    # it loiters at the last waypoint
    c.collect(30)
    lat, _lon = sim.autopilot.position()
    assert abs(lat - (HOME[0] + 3e-4)) * 111e3 < 5


def test_upload_in_auto_continues_by_old_sequence_until_reset():
    sim, c = make()
    old = wps(4, dlat=2e-4)  # 22 m legs
    assert c.upload(old).type == M.MAV_MISSION_ACCEPTED
    c.arm()
    c.set_mode(MODES["AUTO"])
    c.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 1, timeout=60)
    # now heading for old #2; upload a mission going south
    new = [SimClient.waypoint(i, HOME[0] - 2e-4 * i, HOME[1]) for i in range(4)]
    assert c.upload(new).type == M.MAV_MISSION_ACCEPTED
    ap = sim.autopilot
    assert ap.active_item.x == old[2].x  # still the old item #2
    c.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 2, timeout=60)
    lat, _ = ap.position()
    assert abs(lat - (HOME[0] + 4e-4)) * 111e3 < 3  # reached the OLD #2 position
    assert ap.active_item.x == new[3].x  # then continues by sequence: new #3
    # resetting the current item makes the new mission take over at once
    assert c.command(M.MAV_CMD_DO_SET_MISSION_CURRENT, 1, 0).result == 0
    assert ap.mission_index == 1 and ap.active_item.x == new[1].x


def test_mission_set_current_message_and_bad_seq():
    sim, c = make()
    assert c.upload(wps(5)).type == M.MAV_MISSION_ACCEPTED
    c.mav.mission_set_current_send(1, 1, 3)
    mc = c.wait("MISSION_CURRENT", lambda m: m.seq == 3, timeout=1)
    assert mc is not None
    assert c.command(M.MAV_CMD_DO_SET_MISSION_CURRENT, 9, 0).result == M.MAV_RESULT_DENIED
    c.arm()
    c.set_mode(MODES["AUTO"])
    assert sim.autopilot.mission_index == 3


def test_mis_restart_0_resumes_where_stopped_and_1_restarts():
    sim, c = make()
    assert c.upload(wps(5, dlat=2e-4)).type == M.MAV_MISSION_ACCEPTED
    c.arm()
    c.set_mode(MODES["AUTO"])
    c.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 2, timeout=60)
    c.set_mode(MODES["HOLD"])
    assert c.wait("MISSION_CURRENT", timeout=2).mission_state == M.MISSION_STATE_PAUSED
    c.set_mode(MODES["AUTO"])
    assert sim.autopilot.mission_index == 3  # resumed
    c.set_mode(MODES["HOLD"])
    c.mav.param_set_send(1, 1, b"MIS_RESTART", 1, M.MAV_PARAM_TYPE_INT8)
    assert c.wait("PARAM_VALUE").param_value == 1
    c.set_mode(MODES["AUTO"])
    assert sim.autopilot.mission_index == 1  # restarted


def test_vehicle_paces_requests_near_48_per_second():
    sim, c = make()
    c.dt = 0.001  # answer each request within 1 ms of simulated time: the vehicle sets the pace
    items = wps(101)
    t0 = sim.t
    assert c.upload(items).type == M.MAV_MISSION_ACCEPTED
    rate = 100 / (sim.t - t0)
    assert 40 <= rate <= 50
    t0 = sim.t
    got = c.download()
    assert len(got) == 101
    assert 40 <= 100 / (sim.t - t0) <= 50  # downloads are paced by the vehicle as well


def test_item_without_upload_gets_error():
    _sim, c = make()
    c.mav.send(wps(1)[0])
    assert c.wait("MISSION_ACK").type == M.MAV_MISSION_ERROR


# Items sent -> what Rover 4.7 SITL (../shared/sitl) returned on download, recorded with pymavlink:
# (frame, command, autocontinue, p1, p2, p3, p4, x, y, z)
_LAT, _LON = 400001000, -630001000
FIRMWARE_READBACK = [
    ((2, 178, 1, 1, 2.5, -1, 9, 123, 456, 7.5), (0, 178, 1, 1.0, 2.5, -1.0, 0.0, 0, 0, 0.0)),
    ((3, 16, 1, 5.7, 25, 3, 7, _LAT, _LON, 12.345), (3, 16, 1, 5.0, 0.0, 0.0, 0.0, _LAT, _LON, 12.34)),
    ((6, 16, 1, 0, 25, 0, 0, _LAT + 100, _LON, 1), (3, 16, 1, 0.0, 0.0, 0.0, 0.0, _LAT + 100, _LON, 1.0)),
    ((3, 19, 1, 10, 4, 10, 0.5, _LAT, _LON + 100, 0), (3, 19, 1, 10.0, 0.0, 1.0, 1.0, _LAT, _LON + 100, 0.0)),
    ((3, 19, 1, 10.9, 0, -10, 0, _LAT, _LON + 100, 0), (3, 19, 1, 10.0, 0.0, -1.0, 0.0, _LAT, _LON + 100, 0.0)),
    ((3, 20, 1, 1, 2, 3, 4, _LAT, _LON, 5), (0, 20, 1, 0.0, 0.0, 0.0, 0.0, 0, 0, 0.0)),
    ((0, 183, 1, 5, 1500.7, 3, 4, 7, 8, 9), (0, 183, 1, 5.0, 1500.0, 0.0, 0.0, 0, 0, 0.0)),
    ((0, 177, 0, 2, 3.6, 5, 6, 7, 8, 9), (0, 177, 1, 2.0, 3.0, 0.0, 0.0, 0, 0, 0.0)),
    ((5, 16, 1, -1, 0, 0, 0, _LAT, _LON, -3.339), (0, 16, 1, 65535.0, 0.0, 0.0, 0.0, _LAT, _LON, -3.33)),
    ((2, 16, 1, 70000, 0, 0, 0, _LAT, _LON, 3), (0, 16, 1, 4464.0, 0.0, 0.0, 0.0, _LAT, _LON, 3.0)),
    ((0, 17, 1, 1, 2, -30, 4, _LAT, _LON, 3), (0, 17, 1, 0.0, 0.0, -30.0, 0.0, _LAT, _LON, 3.0)),
    ((0, 112, 1, 4.5, 2, 3, 4, _LAT, _LON, 3), (0, 112, 1, 4.5, 0.0, 0.0, 0.0, 0, 0, 0.0)),
]


def _item_msg(seq, sent):
    frame, cmd, auto, p1, p2, p3, p4, x, y, z = sent
    return M.MAVLink_mission_item_int_message(1, 1, seq, frame, cmd, 0, auto, p1, p2, p3, p4, x, y, z, 0)


def _readback(m):
    return (m.frame, m.command, m.autocontinue, m.param1, m.param2, m.param3, m.param4, m.x, m.y, m.z)


def test_items_are_stored_in_the_firmwares_form():
    """ARDUPILOT_ROVER.md's table and more: each item reads back as Rover 4.7 SITL returned it."""
    _sim, c = make()
    items = [SimClient.waypoint(0, *HOME)] + [_item_msg(i + 1, s) for i, (s, _) in enumerate(FIRMWARE_READBACK)]
    assert c.upload(items).type == M.MAV_MISSION_ACCEPTED
    got = c.download()
    for (sent, want), back in zip(FIRMWARE_READBACK, got[1:]):
        assert _readback(back) == pytest.approx(want, abs=1e-6), sent


def test_verbatim_storage_when_normalisation_is_off():
    sim, c = make()
    sim.autopilot.missions.normalise = False
    items = [SimClient.waypoint(0, *HOME)] + [_item_msg(i + 1, s) for i, (s, _) in enumerate(FIRMWARE_READBACK[:2])]
    assert c.upload(items).type == M.MAV_MISSION_ACCEPTED
    got = c.download()
    assert (got[1].frame, got[1].param4) == (2, 9.0) and (got[2].param2, got[2].param1) == (25.0, pytest.approx(5.7))


@pytest.mark.parametrize(
    "bad, result",
    [
        ((0, 31999, 1, 0, 0, 0, 0, 0, 0, 0), M.MAV_MISSION_UNSUPPORTED),
        ((1, 16, 1, 0, 0, 0, 0, _LAT, _LON, 0), M.MAV_MISSION_UNSUPPORTED_FRAME),
        ((0, 16, 1, 0, 0, 0, 0, 910000000, _LON, 0), M.MAV_MISSION_INVALID_PARAM5_X),
        ((0, 16, 1, 0, 0, 0, 0, _LAT, 1810000000, 0), M.MAV_MISSION_INVALID_PARAM6_Y),
        ((0, 16, 1, 0, 0, 0, 0, _LAT, _LON, float("nan")), M.MAV_MISSION_INVALID_PARAM7),
        ((0, 178, 1, 1, float("nan"), 0, 0, 0, 0, 0), M.MAV_MISSION_INVALID_PARAM2),
        ((0, 183, 1, 1, 2, 3, float("nan"), 0, 0, 0), M.MAV_MISSION_INVALID_PARAM4),
        ((0, 177, 1, 0, 1, 0, 0, 0, 0, 0), M.MAV_MISSION_ERROR),  # jump to home
        ((0, 177, 1, 3, 1, 0, 0, 0, 0, 0), M.MAV_MISSION_ERROR),  # jump past the 3-item list
    ],
)
def test_items_the_firmware_refuses_end_the_transfer_with_its_result(bad, result):
    """Results as Rover 4.7 SITL answered (no STATUSTEXT); the transfer is over: a next item gets ERROR."""
    _sim, c = make()
    c.drain()
    c.mav.mission_count_send(1, 1, 3, 0)
    assert c.wait("MISSION_REQUEST").seq == 0
    c.mav.send(SimClient.waypoint(0, *HOME))
    assert c.wait("MISSION_REQUEST").seq == 1
    c.mav.send(_item_msg(1, bad))
    assert c.wait("MISSION_ACK").type == result
    c.mav.send(_item_msg(2, FIRMWARE_READBACK[1][0]))
    assert c.wait("MISSION_ACK").type == M.MAV_MISSION_ERROR
    assert not [t for t in c.texts() if "ission" in t]


def test_nan_yaw_of_a_waypoint_is_accepted():
    _sim, c = make()
    items = [SimClient.waypoint(0, *HOME), _item_msg(1, (3, 16, 1, 0, 0, 0, float("nan"), _LAT, _LON, 0))]
    assert c.upload(items).type == M.MAV_MISSION_ACCEPTED


def test_no_space_comes_with_the_firmwares_warning():
    _sim, c = make(mission_capacity=(5, 84, 20))
    c.drain()
    c.mav.mission_count_send(1, 1, 6, 0)
    assert c.wait("MISSION_ACK").type == M.MAV_MISSION_NO_SPACE
    c.collect(0.2)
    assert "Only 5 items are supported" in c.texts()


def test_acceptance_radius_is_the_wp_radius_parameter_not_param2():
    """Like Rover, the boat reaches a waypoint within WP_RADIUS; a waypoint's param2 (dropped on
    upload) changes nothing."""
    for radius in (2.0, 9.0):
        sim, c = make()
        c.mav.param_set_send(1, 1, b"WP_RADIUS", radius, M.MAV_PARAM_TYPE_REAL32)
        echo = c.wait("PARAM_VALUE", lambda m: m.param_id == "WP_RADIUS")
        assert echo.param_value == pytest.approx(radius)
        items = wps(2, dlat=4e-4)  # one waypoint 44 m north
        items[1].param2 = 30.0  # asks for 30 m: ignored
        assert c.upload(items).type == M.MAV_MISSION_ACCEPTED
        assert c.arm().result == 0 and c.set_mode(MODES["AUTO"]).result == 0
        assert c.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 1, timeout=120) is not None
        lat, _lon = sim.autopilot.position()
        dist = abs(lat - (HOME[0] + 4e-4)) * 111.2e3
        assert radius - 1.0 <= dist <= radius + 1e-6, (radius, dist)  # reached on crossing WP_RADIUS


# -- speed and the end of a mission, as Rover's ModeAuto runs them on a boat ----------------------------------
M_PER_DEG_LAT = 111_035.0  # near 40 N


def _speed_item(seq: int, mps: float):
    """DO_CHANGE_SPEED (178), frame 2 (MISSION), param1 1 = ground speed, param2 m/s, param3 -1 (throttle)."""
    return M.MAVLink_mission_item_int_message(1, 1, seq, 2, 178, 0, 1, 1, mps, -1, 0, 0, 0, 0, 0)


def _north(seq: int, metres: float):
    return SimClient.waypoint(seq, HOME[0] + metres / M_PER_DEG_LAT, HOME[1])


def _leg_speed(sim, c, y_from: float, y_to: float) -> float:
    """Mean ground speed (m/s, north) while the boat goes from north y_from to y_to metres."""
    ap = sim.autopilot
    while ap.boat.y < y_from:
        c.advance(0.1)
    t0, y0 = sim.t, ap.boat.y
    while ap.boat.y < y_to:
        c.advance(0.1)
    return (ap.boat.y - y0) / (sim.t - t0)


def test_do_change_speed_before_the_first_waypoint_is_not_applied_on_a_boat():
    """Rover 4.7 SITL (tests/test_sitl_current.py): ModeAuto::_enter starts a boat in its loiter submode, so a
    DO_CHANGE_SPEED at seq 1 (before the first NAV_WAYPOINT) goes to loiter, which takes no speed: the legs fly
    at WP_SPEED (2 m/s here), and no "speed: ..." STATUSTEXT. Still verified: MISSION_ITEM_REACHED 1."""
    sim, c = make()
    items = [_north(0, 0), _speed_item(1, 1.0), _north(2, 100), _north(3, 200)]
    assert c.upload(items).type == 0
    assert c.arm().result == 0
    assert c.set_mode(MODES["AUTO"]).result == 0
    assert _leg_speed(sim, c, 20, 80) == pytest.approx(2.0, abs=0.05)
    assert _leg_speed(sim, c, 120, 180) == pytest.approx(2.0, abs=0.05)
    c.pump()
    assert not [t for t in c.texts() if t.startswith("speed:")]
    assert 1 in [m.seq for _, m in c.log if m.get_type() == "MISSION_ITEM_REACHED"]


def test_do_change_speed_after_the_first_waypoint_is_applied_from_there():
    """After the first NAV_WAYPOINT the submode is wp: DO_CHANGE_SPEED 1 m/s sets the waypoint speed from the
    second leg on ("speed: 1.0 m/s"), as SITL did with it at seq 2."""
    sim, c = make()
    items = [_north(0, 0), _north(1, 100), _speed_item(2, 1.0), _north(3, 200)]
    assert c.upload(items).type == 0
    assert c.arm().result == 0
    assert c.set_mode(MODES["AUTO"]).result == 0
    assert _leg_speed(sim, c, 20, 80) == pytest.approx(2.0, abs=0.05)
    assert _leg_speed(sim, c, 120, 180) == pytest.approx(1.0, abs=0.05)
    c.pump()
    assert "speed: 1.0 m/s" in c.texts()


def test_do_change_speed_command_in_auto_applies_and_auto_entry_resets_it():
    """DO_CHANGE_SPEED as a COMMAND_LONG right after AUTO is ACCEPTED and flown; HOLD refuses it (FAILED,
    Mode::set_desired_speed); entering AUTO again resets the speed to WP_SPEED (g2.wp_nav.init())."""
    sim, c = make()
    items = [_north(0, 0), _speed_item(1, 1.0), _north(2, 100), _north(3, 300)]
    assert c.upload(items).type == 0
    assert c.arm().result == 0
    assert c.set_mode(MODES["AUTO"]).result == 0
    assert c.command(M.MAV_CMD_DO_CHANGE_SPEED, 1, 1.0, -1).result == M.MAV_RESULT_ACCEPTED
    assert _leg_speed(sim, c, 20, 80) == pytest.approx(1.0, abs=0.05)
    assert c.set_mode(MODES["HOLD"]).result == 0
    assert c.command(M.MAV_CMD_DO_CHANGE_SPEED, 1, 1.0, -1).result == M.MAV_RESULT_FAILED
    assert c.set_mode(MODES["AUTO"]).result == 0  # resumes the current waypoint (MIS_RESTART 0)
    assert _leg_speed(sim, c, 120, 280) == pytest.approx(2.0, abs=0.05)


@pytest.mark.parametrize(("behave", "moves"), [(0, True), (1, False)])
def test_mission_end_follows_mis_done_behave(behave, moves):
    """ModeAuto::exit_mission on a boat: MIS_DONE_BEHAVE 1 loiters (keeps station in AUTO); 0 (HOLD) is
    start_stop(): motor off, still AUTO, the boat drifts with the current (0.5 m/s east here: ~60 m in 120 s)."""
    cfg = SimConfig.fast(params=(("MIS_DONE_BEHAVE", behave),))
    sim = Simulator(None, home=HOME, config=cfg, uniform_current=(0.5, 0.0))
    sim.run_until(2.0)
    c = SimClient(sim)
    assert c.upload([_north(0, 0), _north(1, 50)]).type == 0
    assert c.arm().result == 0
    assert c.set_mode(MODES["AUTO"]).result == 0
    c.wait("STATUSTEXT", lambda m: m.text.startswith("Mission Complete"), timeout=120, dt=0.1)
    b = sim.autopilot.boat
    x0 = b.x
    c.advance(120.0)
    assert sim.autopilot.mode == MODES["AUTO"]
    if moves:
        assert b.x - x0 == pytest.approx(60.0, abs=5.0)
    else:
        assert abs(b.x - x0) < 2 * 2.0  # 2 x LOIT_RADIUS
