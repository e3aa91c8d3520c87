"""SampleCollector: pairing, duplicates, expiry (hand-made messages) and a mission in a known field."""

from __future__ import annotations

import numpy as np
import pytest
from mavlink_helpers import HOME, inprocess_factory, link_config, served, vehicle, waypoints
from pymavlink.dialects.v20 import ardupilotmega as M

import geo
from passt_mav.fields import FlowField
from passt_mav.mavlink import Link, SampleCollector, with_home
from vehicle_sim import SimConfig


def gpi(tb, lat, lon):
    return M.MAVLink_global_position_int_message(tb, int(round(lat * 1e7)), int(round(lon * 1e7)), 0, 0, 0, 0, 0, 0)


def nvf(tb, name, value):
    return M.MAVLink_named_value_float_message(tb, name.encode(), value)


def boat_at(t_ms, lat0=40.1, lon0=-63.2, speed=3.0, heading_deg=30.0, t0_ms=10_000):
    """Exact position (deg) of a boat on a straight course at constant speed (pyproj geodesic)."""
    from pyproj import Geod

    lon, lat, _ = Geod(ellps="WGS84").fwd(lon0, lat0, heading_deg, speed * (t_ms - t0_ms) / 1000.0)
    return lat, lon


def metres(lat, lon, lat1, lon1):
    from pyproj import Geod

    return Geod(ellps="WGS84").inv(lon, lat, lon1, lat1)[2]


def test_readings_between_1hz_fixes_are_placed_on_the_track_when_the_next_fix_arrives():
    """4 Hz readings, 1 Hz fixes of a boat at 3 m/s: every reading is used, within 1 cm of the true track."""
    out = []
    c = SampleCollector(out.append, max_gap_ms=3000)
    c.handle(M.MAVLink_system_time_message(int(1.7e15 + 5000e3), 5000))  # unix = 1.7e9 s + 5 s at boot 5 s
    expect = []
    for k in range(10):
        tf = 10_000 + 1000 * k
        c.handle(gpi(tf, *boat_at(tf)))
        n_before = len(out)
        for j in range(4):  # readings at tf + 0, 250, 500, 750 ms arrive before the next fix
            tb = tf + 250 * j
            c.handle(nvf(tb, "CUR_V", -0.25 * k))
            c.handle(nvf(tb, "CUR_U", 0.5 + j))
            expect.append((tb, 0.5 + j, -0.25 * k))
        # the reading at the fix's own time is placed at once (gap 0); the others wait for the next fix
        assert len(out) == n_before + 1 and out[-1]["gap_ms"] == 0
    assert len(out) == 1 + 9 * 4  # the last second's three readings still wait
    c.handle(gpi(20_000, *boat_at(20_000)))
    assert len(out) == 40 and c.counts["readings"] == 40 and c.counts["gap"] == 0
    for r, (tb, u, v) in zip(out, expect):
        assert (r["time_boot_ms"], r["u"], r["source"]) == (tb, u, "mavlink") and r["v"] == pytest.approx(v)
        assert r["gap_ms"] == (0 if tb % 1000 == 0 else 1000)
        assert metres(r["lat"], r["lon"], *boat_at(tb)) < 0.01  # degE7 rounding is 1 cm
        assert r["utc"] == pytest.approx(1.7e9 + tb / 1000.0)


def test_a_gap_beyond_the_bound_drops_the_readings_in_it_and_counts_them():
    out = []
    c = SampleCollector(out.append, max_gap_ms=2500)
    c.handle(gpi(1000, *boat_at(1000)))
    c.handle(gpi(2000, *boat_at(2000)))
    # fix 3000 lost: the readings between 2000 and 4000 are bracketed 2000 ms apart (used)
    for tb in (2500, 3500):
        c.handle(nvf(tb, "CUR_U", 1.0)), c.handle(nvf(tb, "CUR_V", 2.0))
    c.handle(gpi(4000, *boat_at(4000)))
    assert [(r["time_boot_ms"], r["gap_ms"]) for r in out] == [(2500, 2000), (3500, 2000)]
    assert metres(out[0]["lat"], out[0]["lon"], *boat_at(2500)) < 0.01
    # fixes 5000..7000 lost: the reading at 4200 is held until vehicle time passes 4000 + 2500 ms
    c.handle(nvf(4200, "CUR_U", 1.0)), c.handle(nvf(4200, "CUR_V", 2.0))
    c.handle(nvf(6500, "CUR_U", 1.0))  # (a lone half: vehicle time 6500, the bound not yet passed)
    assert c.counts["gap"] == 0 and len(out) == 2
    c.handle(nvf(6600, "CUR_U", 1.0))  # vehicle time 6600 > 4000 + 2500: no fix can place 4200 any more
    assert c.counts["gap"] == 1 and len(out) == 2
    c.handle(gpi(8000, *boat_at(8000)))  # 4000 -> 8000 is too long anyway
    assert len(out) == 2 and c.counts["readings"] == 3 and c.counts["emitted"] == 2


def test_held_readings_of_a_boot_are_dropped_at_a_reboot_and_flush_decides_the_rest():
    out = []
    c = SampleCollector(out.append)
    c.leg = 0
    c.handle(gpi(100_000, *boat_at(100_000)))
    c.handle(nvf(100_400, "CUR_U", 1.0)), c.handle(nvf(100_400, "CUR_V", 1.0))  # waits for the fix at 101000
    c.handle(gpi(1000, *boat_at(1000)))  # reboot: time went back; the old boot's next fix never comes
    assert out == [] and c.counts["reboots"] == 1 and c.counts["gap"] == 1
    c.handle(nvf(1250, "CUR_U", 1.0)), c.handle(nvf(1250, "CUR_V", 1.0))
    c.handle(gpi(2000, *boat_at(2000)))
    assert len(out) == 1 and out[0]["boot"] == 1 and out[0]["gap_ms"] == 1000
    assert metres(out[0]["lat"], out[0]["lon"], *boat_at(1250)) < 0.01
    c.handle(nvf(2100, "CUR_U", 1.0)), c.handle(nvf(2100, "CUR_V", 1.0))
    assert c.flush() == [] and c.counts["gap"] == 2  # no fix after it: dropped, counted
    assert c.leg_counts(0) == {"readings": 3, "emitted": 1, "gap": 2}


def test_duplicates_dropped_and_unmatched_halves_expire():
    out = []
    c = SampleCollector(out.append, expire_ms=5000, u_name="U", v_name="V")
    msgs = [gpi(1000, 40.0, -63.0), nvf(1000, "U", 0.1), nvf(1000, "V", 0.2)]
    for m in msgs + msgs:  # retransmitted / replayed after a reconnect
        c.handle(m)
    assert len(out) == 1 and c.counts["duplicates"] == 2
    c.handle(nvf(2000, "U", 0.3))  # its V and position never come
    c.handle(nvf(2000, "CUR_U", 9))  # another name: ignored
    c.handle(gpi(9000, 40.0, -63.0))
    assert c.counts["expired"] == 1 and 2000 not in c.pairer and c.counts["readings"] == 1
    c.handle(nvf(2000, "V", 0.4))  # the late half cannot resurrect an expired sample
    assert len(out) == 1
    # a fix without GPS (0, 0) never pairs
    c.handle(gpi(10000, 0.0, 0.0))
    c.handle(nvf(10000, "U", 1.0))
    c.handle(nvf(10000, "V", 1.0))
    assert len(out) == 1


def test_reboot_resets_the_duplicate_memory():
    out = []
    c = SampleCollector(out.append)
    for tb in (100_000, 1000):  # the second is after a reboot (vehicle time jumped back)
        for m in (gpi(tb, 40.0, -63.0), nvf(tb, "CUR_U", 0.1), nvf(tb, "CUR_V", 0.2)):
            c.handle(m)
    assert len(out) == 2 and c.counts["reboots"] == 1


def gradient_field():
    """u, v linear in lon/lat and time: the field's bilinear + linear-in-time interpolation is exact."""
    n = 6
    grid = geo.RegionGrid(HOME[0] - 0.01, HOME[1] - 0.01, HOME[0] + 0.01, HOME[1] + 0.01, n, n)
    lats, lons = grid.centres_latlon()
    times = np.array([0.0, 600.0, 1200.0])
    data = np.zeros((3, 2, n, n), np.float32)
    for i, tt in enumerate(times):
        data[i, 0] = 0.2 + 50.0 * (lons - HOME[1]) + tt / 6000.0
        data[i, 1] = -0.1 + 80.0 * (lats - HOME[0]) - tt / 12000.0
    return FlowField(data, grid, times, time_origin="2020-01-01T00:00:00Z")


def test_samples_during_a_mission_match_the_field_and_two_links_give_no_duplicates():
    field = gradient_field()
    noise = 0.01
    cfg = SimConfig.fast(params=(("WP_SPEED", 5.0),), current_noise_std=noise, current_rate_hz=2.0, seed=4)
    with served(cfg, field=field) as (sim, link):
        out = []
        collector = SampleCollector(out.append, source="sim").attach(link)
        # a second link to the same vehicle delivers every reading again
        link2 = Link(
            link_config(source_system=254, stream_rates_hz=()), connection_factory=inprocess_factory(sim)
        ).connect()
        collector.attach(link2)
        try:
            v = vehicle(link)
            v.mission.upload_verified(with_home(waypoints([(2e-3, 0.0), (2e-3, 2e-3)])))
            v.wait_ready(timeout=5)
            v.arm(timeout=5)
            v.start_mission()
            v.wait_mission_complete(2, timeout=20)
        finally:
            link.remove_listener(collector.handle)
            link2.close()
        rec = np.array([(r["time_boot_ms"] / 1000.0, r["lat"], r["lon"], r["u"], r["v"]) for r in out])
    tb = rec[:, 0]
    assert len(rec) > 40 and len(set(tb)) == len(tb)  # one record per reading
    assert collector.counts["duplicates"] >= len(rec)  # the second link's copies were recognised
    truth = field.sample_latlon(tb, rec[:, 1], rec[:, 2])  # start_time = first snapshot, 1 s per field s
    err = rec[:, 3:5] - truth
    assert np.abs(err).max() < 5 * noise
    assert err.std() == pytest.approx(noise, rel=0.3)
    assert np.ptp(rec[:, 3]) > 0.1 and np.ptp(rec[:, 4]) > 0.1  # the boat did cross the gradient
    assert np.all(np.diff(tb) > 0)
