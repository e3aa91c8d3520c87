"""SampleCollector: pairing, duplicates, expiry (hand-made messages) and a mission in a known field."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as M

import geo
from mavlink_helpers import HOME, served, vehicle, waypoints
from passt_mav.fields import FlowField
from passt_mav.mavlink import Link, SampleCollector, with_home
from mavlink_helpers import inprocess_factory, link_config
from vehicle_sim import SimConfig


def gpi(tb, lat, lon):
    return M.MAVLink_global_position_int_message(tb, int(round(lat * 1e7)), int(round(lon * 1e7)), 0, 0, 0, 0, 0, 0)


def nvf(tb, name, value):
    return M.MAVLink_named_value_float_message(tb, name.encode(), value)


def test_pairs_u_v_with_the_fix_of_the_same_time_in_any_order():
    out = []
    c = SampleCollector(out.append, tolerance_ms=50)
    c.handle(M.MAVLink_system_time_message(int(1.7e15 + 5000e3), 5000))  # unix = 1.7e9 s + 5 s at boot 5 s
    c.handle(nvf(1000, "CUR_U", 0.5))
    assert out == []
    c.handle(gpi(1000, 40.1, -63.2))
    assert out == []  # v missing
    c.handle(nvf(1000, "CUR_V", -0.25))
    assert len(out) == 1
    r = out[0]
    assert (r["time_boot_ms"], r["u"], r["v"], r["source"]) == (1000, 0.5, -0.25, "mavlink")
    assert r["lat"] == pytest.approx(40.1, abs=1e-7) and r["lon"] == pytest.approx(-63.2, abs=1e-7)
    assert r["utc"] == pytest.approx(1.7e9 + 1.0)
    # reversed order, fix 30 ms off (within tolerance), the nearest of two fixes wins
    c.handle(gpi(1970, 40.0, -63.0))
    c.handle(nvf(2000, "CUR_V", 1.0))
    c.handle(nvf(2000, "CUR_U", 2.0))
    c.handle(gpi(2020, 41.0, -64.0))  # 20 ms off: nearer, but the sample was already emitted with the 30 ms fix
    assert len(out) == 2 and out[1]["lat"] == pytest.approx(40.0)
    # a fix 200 ms away does not pair
    c.handle(nvf(3000, "CUR_U", 1.0))
    c.handle(nvf(3000, "CUR_V", 1.0))
    c.handle(gpi(3200, 40.0, -63.0))
    assert len(out) == 2


def test_duplicates_dropped_and_unmatched_halves_expire():
    out = []
    c = SampleCollector(out.append, expire_ms=5000, u_name="U", v_name="V")
    msgs = [gpi(1000, 40.0, -63.0), nvf(1000, "U", 0.1), nvf(1000, "V", 0.2)]
    for m in msgs + msgs:  # retransmitted / replayed after a reconnect
        c.handle(m)
    assert len(out) == 1 and c.counts["duplicates"] == 2
    c.handle(nvf(2000, "U", 0.3))   # its V and position never come
    c.handle(nvf(2000, "CUR_U", 9))  # another name: ignored
    c.handle(gpi(9000, 40.0, -63.0))
    assert c.counts["expired"] == 1 and 2000 not in c._halves
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
        link2 = Link(link_config(source_system=254, stream_rates_hz=()), connection_factory=inprocess_factory(sim)).connect()
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
