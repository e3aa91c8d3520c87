"""Mission protocol client against the simulator (served at high speed-up, in-process link).

Tests whose outcome depends on the vehicle's own timers (re-request after 1 s, cancel after 8 s)
run the simulator *paced* (:func:`paced`) instead of served at a wall-clock speed-up: it advances
one small step at a time and only once the client has read everything the vehicle sent, so the
simulated clock can never run ahead of a client that the machine's load has slowed down.
"""

from __future__ import annotations

import contextlib
import threading
import time

import pytest
from mavlink_helpers import HOME, inprocess_factory, link_config, served, vehicle, waypoints
from pymavlink.dialects.v20 import ardupilotmega as M

from passt_mav.errors import LinkTimeout, MissionRejected
from passt_mav.mavlink import Link, MissionClient, with_home
from passt_mav.mavlink.mission_client import rover_stored, to_msg
from passt_mav.mission.items import MissionItem
from vehicle_sim import LinkConfig as SimLinkConfig
from vehicle_sim import SimConfig, Simulator

OFFSETS = [(1e-4 * i, -1.3e-4 * i + 3e-7) for i in range(1, 9)]


@contextlib.contextmanager
def paced(
    config: SimConfig | None = None,
    *,
    sim_link: SimLinkConfig | None = None,
    dt: float = 0.01,
    wall_per_step_s: float = 0.001,
    link_kw: dict | None = None,
):
    """(sim, link): the simulator advanced by a thread in steps of ``dt`` simulated seconds, each
    after the client has read all the vehicle sent and at least ``wall_per_step_s`` of wall time
    (so at most ``dt / wall_per_step_s`` = 10x). A loaded machine makes the vehicle slower, never
    faster, relative to the client's wall-clock timeouts: its 8 s transfer timeout needs the client
    silent for >= 0.8 s of wall time."""
    sim = Simulator(None, home=HOME, config=config or SimConfig.fast())
    eps = []

    def factory():
        conn = inprocess_factory(sim, sim_link)()
        eps.append(conn.endpoint)
        return conn

    stop = threading.Event()

    def stepper():
        while not stop.is_set():
            t_wait = time.monotonic() + 1.0
            while any(e.pending() for e in eps if not e.closed) and time.monotonic() < t_wait and not stop.is_set():
                time.sleep(0.0005)
            sim.step(dt)
            time.sleep(wall_per_step_s)

    th = threading.Thread(target=stepper, daemon=True)
    th.start()
    link = Link(link_config(**({"stream_rates_hz": ()} | (link_kw or {}))), connection_factory=factory)
    try:
        link.connect()
        yield sim, link
    finally:
        link.close()
        stop.set()
        th.join(5)


def test_with_home_numbers_from_one_and_puts_a_placeholder_at_zero():
    items = with_home(waypoints(OFFSETS[:3]), home=HOME)
    assert [i.seq for i in items] == [0, 1, 2, 3]
    assert (items[0].lat, items[0].lon, items[0].frame) == (HOME[0], HOME[1], 0)
    fence = with_home(waypoints(OFFSETS[:2], mission_type=1), mission_type=1)
    assert [i.seq for i in fence] == [0, 1]  # no home in fence/rally lists


def test_upload_then_read_back_equals_and_seq0_is_the_vehicles_home():
    with served() as (sim, link):
        mc = MissionClient(link)
        items = with_home(waypoints(OFFSETS), home=(0.0, 0.0))  # placeholder 0,0: the vehicle writes home
        got = mc.upload_verified(items)
        assert len(got) == len(items)
        # the vehicle keeps its own form of each item (Rover drops NAV_WAYPOINT's param2 radius)
        assert all(rover_stored(a) == b for a, b in zip(items[1:], got[1:]))
        assert {g.param2 for g in got[1:]} == {0.0} and {i.param2 for i in items[1:]} == {2.0}
        # exact int32 degE7 round trip
        assert [(g.x_int, g.y_int) for g in got[1:]] == [(i.x_int, i.y_int) for i in items[1:]]
        assert got[0].lat == pytest.approx(HOME[0], abs=1e-7) and got[0].lon == pytest.approx(HOME[1], abs=1e-7)
        # the vehicle's own state agrees (seq 0 home, the rest ours)
        stored = sim.autopilot.store.items[0]
        assert [(s.x, s.y) for s in stored[1:]] == [(i.x_int, i.y_int) for i in items[1:]]


def test_fence_type_round_trips_and_clear_and_set_current():
    with served() as (sim, link):
        mc = MissionClient(link)
        fence = [
            MissionItem(i, command=5001, frame=0, param1=3, lat=HOME[0] + d[0], lon=HOME[1] + d[1], mission_type=1)
            for i, d in enumerate([(0.01, 0.01), (0.01, -0.01), (-0.01, 0.0)])
        ]
        got = mc.upload_verified(fence, mission_type=1)
        assert [g.command for g in got] == [5001] * 3
        mc.upload_verified(with_home(waypoints(OFFSETS[:4])))
        mc.set_current(3)
        assert sim.autopilot.mission_index == 3
        mc.clear(0)
        assert len(mc.download(0)) == 1  # only home is left
        assert len(mc.download(1)) == 3  # the fence is separate


def test_no_space_over_capacity_is_rejected_and_named():
    with served(SimConfig.fast(mission_capacity=(5, 84, 20))) as (_sim, link):
        mc = MissionClient(link, boot_grace_s=0.0)  # past boot: NO_SPACE is a real limit, raised at once
        # past boot indeed: the vehicle has left INITIALISING and sent its time (until then a NO_SPACE counts as
        # a vehicle still booting and is asked again, as test_no_space_right_after_boot_is_retried checks)
        end = time.monotonic() + 30.0
        while time.monotonic() < end and (
            link.vehicle_uptime_s() is None or getattr(link.latest("HEARTBEAT"), "custom_mode", 16) == 16
        ):
            time.sleep(0.01)
        with pytest.raises(MissionRejected) as ei:
            mc.upload(with_home(waypoints(OFFSETS[:6])))
        assert ei.value.result == M.MAV_MISSION_NO_SPACE and ei.value.name == "MAV_MISSION_NO_SPACE"
        assert "capacity" in str(ei.value)
        mc.upload(with_home(waypoints(OFFSETS[:4])))  # 5 items fit


def test_no_space_right_after_boot_is_retried():
    # storage ready at 4 s of simulated time = 0.2 s of wall time at 20x: connect takes less
    cfg = SimConfig.fast(storage_ready_s=4.0)
    with served(cfg, speedup=20, link_kw=dict(stream_rates_hz=())) as (sim, link):
        mc = MissionClient(link, no_space_delay_s=0.1, no_space_retries=10)
        assert sim.t < 4.0
        res = mc.upload(with_home(waypoints(OFFSETS[:3])))
        assert res.no_space_retries >= 1 and sim.t >= 4.0
        assert len(mc.download()) == 4


def test_second_gcs_mid_transfer_gets_denied():
    with served() as (sim, link):
        other = sim.connect_inprocess()
        mav = M.MAVLink(other, srcSystem=250, srcComponent=190, use_native=False)
        mav.mission_count_send(1, 1, 10, 0)  # starts a transfer it never finishes
        time.sleep(0.05)
        with pytest.raises(MissionRejected) as ei:
            MissionClient(link).upload(with_home(waypoints(OFFSETS[:3])))
        assert ei.value.result == M.MAV_MISSION_DENIED and "DENIED" in str(ei.value)


@pytest.mark.parametrize("seed", [1, 7])
def test_upload_completes_under_20_percent_loss_each_way(seed):
    # paced: the vehicle's 8 s transfer timeout is simulated time and cannot race the client's
    # wall-clock item timeout (served at 50x it ran out under load: OPERATION_CANCELLED)
    with paced(sim_link=SimLinkConfig(loss=0.2, seed=seed), link_kw=dict(timeout_s=0.1)) as (sim, link):
        mc = MissionClient(link)
        items = with_home(waypoints(OFFSETS))  # 9 items
        got = mc.upload_verified(items)
        assert [(g.x_int, g.y_int) for g in got[1:]] == [(i.x_int, i.y_int) for i in items[1:]]
        s = sim.links[0].stats
        assert s["tx_lost"] > 0 and s["rx_lost"] > 0  # loss really happened both ways
        # the link's sequence-gap count sees the vehicle->GCS loss
        assert link.stats.loss == pytest.approx(s["tx_lost"] / s["tx_frames"], abs=0.05)


def test_upload_never_hangs_when_the_vehicle_goes_silent():
    with served() as (sim, link):
        mc = MissionClient(link)
        sim.stop()  # the vehicle stops answering (and heartbeating)
        t0 = time.monotonic()
        with pytest.raises(LinkTimeout):
            mc.upload(with_home(waypoints(OFFSETS)), timeout=1.0)
        assert time.monotonic() - t0 < 1.0 + 2 * link.reply_timeout
        # without an explicit timeout the bound is retries x item timeout
        mc = MissionClient(link, retries=3)
        t0 = time.monotonic()
        with pytest.raises(LinkTimeout, match="silent|deadline"):
            mc.upload(with_home(waypoints(OFFSETS)))
        assert time.monotonic() - t0 <= (mc.retries + 2) * link.reply_timeout


def test_upload_times_out_when_vehicle_goes_silent_mid_transfer():
    # the vehicle keeps its clock but the link drops everything from 1 s of sim time after the first request
    with served(SimConfig.fast(mission_request_interval_s=0.5)) as (sim, link):
        mc = MissionClient(link, retries=3)
        done = threading.Event()
        errors = []

        def run():
            try:
                mc.upload(with_home(waypoints(OFFSETS)), timeout=3.0)
            except Exception as exc:  # noqa: BLE001 - inspected below
                errors.append(exc)
            done.set()

        th = threading.Thread(target=run)
        th.start()
        time.sleep(0.05)
        sim.links[0].config = SimLinkConfig(drops=((0.0, 1e9),))  # cut the radio mid-transfer
        assert done.wait(5.0)
        assert errors and isinstance(errors[0], LinkTimeout)


def test_a_transfer_the_vehicle_cancels_is_restarted():
    """The vehicle cancels an upload after 8 s without the next item (OPERATION_CANCELLED): the
    client starts the transfer again from MISSION_COUNT instead of failing."""
    with paced(link_kw=dict(timeout_s=0.1)) as (sim, link):
        mc = MissionClient(link)
        items = with_home(waypoints(OFFSETS[:5]))
        send = link.send
        swallowed = []

        def lossy_send(msg):
            # every copy of item 3 is lost for 8.5 s of simulated time: the vehicle gives up (at 8 s)
            if msg.get_type() == "MISSION_ITEM_INT" and msg.seq == 3 and (not swallowed or sim.t < swallowed[0] + 8.5):
                swallowed.append(sim.t)
                return
            send(msg)

        link.send = lossy_send
        res = mc.upload(items)
        assert res.cancel_restarts == 1 and len(swallowed) >= 5  # the vehicle re-requested item 3 each second
        assert sim.t >= swallowed[0] + 8.0  # the cancellation came from the vehicle's own timeout
        assert "Mission upload timeout" in [t for _, _, t in link.texts]
        got = mc.download()
        assert [(g.x_int, g.y_int) for g in got[1:]] == [(i.x_int, i.y_int) for i in items[1:]]


def test_cancel_restarts_are_bounded():
    """A vehicle that cancels every transfer is not retried forever: the cancel is raised, named."""
    with paced(link_kw=dict(timeout_s=0.1)) as (_sim, link):
        mc = MissionClient(link, cancel_restarts=1)
        send = link.send
        link.send = lambda msg: None if msg.get_type() == "MISSION_ITEM_INT" and msg.seq == 2 else send(msg)
        with pytest.raises(MissionRejected) as ei:
            mc.upload(with_home(waypoints(OFFSETS[:4])), timeout=60.0)
        assert ei.value.result == M.MAV_MISSION_OPERATION_CANCELLED
        assert "Mission upload timeout" in str(ei.value)


def test_wp_radius_goes_through_the_parameter_and_is_restored():
    """Rover's acceptance radius is WP_RADIUS: set by PARAM_SET, confirmed by the PARAM_VALUE echo,
    and put back afterwards; the simulator's boat uses it (not the waypoint's param2)."""
    with served() as (sim, link):
        v = vehicle(link)
        assert v.get_param("WP_RADIUS") == pytest.approx(2.0)  # Rover's default
        assert v.set_wp_radius(7.5) == pytest.approx(7.5)
        assert sim.autopilot.params["WP_RADIUS"] == pytest.approx(7.5)
        assert v.changed_params == {"WP_RADIUS": pytest.approx(2.0)}
        assert v.restore_params() == {"WP_RADIUS": pytest.approx(2.0)}
        assert sim.autopilot.params["WP_RADIUS"] == pytest.approx(2.0) and v.changed_params == {}
        with pytest.raises(LinkTimeout, match="ARMING_CHECK"):
            v.get_param("ARMING_CHECK", timeout=0.5)  # 4.7 has no such parameter: no answer at all


def test_a_stale_error_ack_does_not_fail_the_read_back():
    """ArduPilot answers an item that arrives while no upload runs with MISSION_ACK ERROR: the echo of an
    upload's last item resent as its ACCEPTED crossed it. Landing in the read-back that follows (here the
    stray item goes out just before MISSION_REQUEST_LIST, so the vehicle's ERROR precedes its COUNT), the
    download asks again and reads the mission; a vehicle that keeps answering ERROR is still reported. Before
    an upload's first request the echo is ignored too."""
    with paced() as (_sim, link):
        mc = MissionClient(link)
        items = with_home(waypoints(OFFSETS[:3]))
        mc.upload(items)
        send = link.send
        strays = []

        def with_stray(m):
            if m.get_type() == "MISSION_REQUEST_LIST" and not strays:
                stray = to_msg(items[-1], link.target_system, link.target_component)
                strays.append(stray)
                send(stray)
            send(m)

        link.send = with_stray
        got = mc.download()
        assert strays and [(g.x_int, g.y_int) for g in got[1:]] == [(i.x_int, i.y_int) for i in items[1:]]

        def always_stray(m):
            if m.get_type() == "MISSION_REQUEST_LIST":
                send(to_msg(items[-1], link.target_system, link.target_component))
            else:
                send(m)

        link.send = always_stray
        with pytest.raises(MissionRejected, match="MAV_MISSION_ERROR"):
            mc.download()

        # the same echo ahead of the next upload's first request: ignored there too
        strays.clear()

        def stray_before_count(m):
            if m.get_type() == "MISSION_COUNT" and not strays:
                strays.append(m)
                send(to_msg(items[-1], link.target_system, link.target_component))
            send(m)

        link.send = stray_before_count
        res = mc.upload(items)
        assert strays and res.count == len(items)
