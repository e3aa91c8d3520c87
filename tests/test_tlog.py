"""Reading MAVLink telemetry logs and DataFlash logs (passt_mav.runs.tlog).

The tlog is recorded by pymavlink's own writer: a scripted exchange between a
Rover-like vehicle (sysid 1) and a GCS (sysid 255) is written as a raw MAVLink
byte stream, then read back through ``mavfile.setup_logfile`` - the code path
MAVProxy uses to write ``.tlog`` files (8-byte big-endian µs timestamp + frame).
"""

from __future__ import annotations

import os
import random

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import DFReader, mavutil

from passt_mav.errors import UserError
from passt_mav.loop.measurement import RULES
from passt_mav.runs.tlog import read_dataflash, read_tlog

LAT0, LON0 = 50.10, -30.20
VEH, GCS = 1, 255


def _deg7(x: float) -> int:
    return int(round(x * 1e7))


def _scenario():
    """Frames (bytes) of a two-leg mission and the answers a reader must find.

    Returns (frames, expected) where expected has 'samples' [(tb, lat, lon, u, v, leg)],
    'track' [(tb, lat, lon)], 'missions' [[(lat, lon), ...] of accepted uploads].
    """
    mavutil.set_dialect("ardupilotmega") if mavutil.current_dialect not in ("ardupilotmega", "all") else None
    ml = mavutil.mavlink
    veh = ml.MAVLink(None, srcSystem=VEH, srcComponent=1)
    gcs = ml.MAVLink(None, srcSystem=GCS, srcComponent=190)
    frames: list[bytes] = []
    exp = {"samples": [], "track": [], "missions": []}

    def V(msg):
        frames.append(bytes(msg.pack(veh)))

    def G(msg):
        frames.append(bytes(msg.pack(gcs)))

    def hb(mode, armed):
        V(veh.heartbeat_encode(11, 3, 1 | (128 if armed else 0), mode, 4))
        G(gcs.heartbeat_encode(6, 8, 0, 0, 4))

    def upload(wps, result=0, use_int=True, resend=None):
        n = len(wps) + 1
        G(gcs.mission_count_encode(VEH, 1, n))
        items = [(LAT0, LON0)] + list(wps)  # seq 0 = home placeholder
        for seq, (la, lo) in enumerate(items):
            V(veh.mission_request_encode(GCS, 190, seq))
            if use_int:
                G(gcs.mission_item_int_encode(VEH, 1, seq, 6, 16, 0, 1, 0, 2, 0, 0, _deg7(la), _deg7(lo), 0))
            else:
                G(gcs.mission_item_encode(VEH, 1, seq, 3, 16, 0, 1, 0, 2, 0, 0, la, lo, 0))
            if seq == resend:  # vehicle re-requests after silence; the GCS sends the item again
                V(veh.mission_request_encode(GCS, 190, seq))
                G(gcs.mission_item_int_encode(VEH, 1, seq, 6, 16, 0, 1, 0, 2, 0, 0, _deg7(la), _deg7(lo), 0))
        V(veh.mission_ack_encode(GCS, 190, result))
        if result == 0:
            exp["missions"].append([(_deg7(a) * 1e-7, _deg7(b) * 1e-7) for a, b in wps])

    tb = 10_000
    hb(16, False)
    V(veh.global_position_int_encode(tb, 0, 0, 0, 0, 0, 0, 0, 0))  # before GPS: 0/0, must be ignored
    hb(0, False)

    k = 0

    def step(leg, *, v_offset=0, pos_offset=0, with_v=True, with_pos=True, name_u=b"CUR_U"):
        nonlocal tb, k
        tb += 1000
        k += 1
        la, lo = LAT0 + 1e-4 * k, LON0 + 2e-4 * k
        if with_pos:
            V(veh.global_position_int_encode(tb + pos_offset, _deg7(la), _deg7(lo), 0, 0, 0, 0, 0, 0))
            exp["track"].append((tb + pos_offset, _deg7(la) * 1e-7, _deg7(lo) * 1e-7))
        u, v = round(0.01 * k, 4), round(-0.02 * k, 4)
        V(veh.named_value_float_encode(tb, name_u, u))
        V(veh.named_value_float_encode(tb, b"WATER_DEP", 12.5))  # another sensor: not a sample
        if with_v:
            V(veh.named_value_float_encode(tb + v_offset, b"CUR_V", v))
        if with_v and abs(v_offset) <= RULES.pair_tolerance_ms and name_u == b"CUR_U":
            exp["samples"].append((tb, None, None, float(np.float32(u)), float(np.float32(v)), leg))

    step(-1)  # before any upload: a sample outside every leg
    upload([(LAT0 + 0.01, LON0), (LAT0 + 0.01, LON0 + 0.01), (LAT0, LON0 + 0.01)], resend=2)
    hb(10, True)
    V(veh.mission_current_encode(1, 3, 3))
    step(0)
    step(0, v_offset=3)  # u and v 3 ms apart: still one sample
    step(0, pos_offset=150)  # fixes at -1000 and +150 ms: interpolated, gap 1150 ms
    step(0, pos_offset=450)  # fixes at -850 and +450 ms: interpolated, gap 1300 ms
    step(0, with_v=False)  # u without v: dropped
    for s in (1, 2, 3):
        V(veh.mission_item_reached_encode(s))
    V(veh.statustext_encode(6, b"Reached waypoint #3"))
    V(veh.mission_current_encode(3, 3, 5))
    V(veh.statustext_encode(6, b"Mission Complete"))
    step(-1)  # between legs
    upload([(LAT0 + 0.02, LON0)], result=4)  # NO_SPACE: no leg
    upload([(LAT0 + 0.02, LON0 + 0.02), (LAT0 + 0.03, LON0 + 0.02)], use_int=False)
    V(veh.mission_current_encode(3, 3, 5))  # still reporting the old mission complete
    step(1)
    V(veh.mission_current_encode(1, 2, 3))
    step(1, name_u=b"XX_U")  # other name: not a sample
    step(1)
    hb(4, True)  # HOLD
    # every reading lies on the track: straight lines between the 1 Hz fixes (np.interp, not geo.track)
    tr = np.array(exp["track"])
    exp["samples"] = [
        (tb, float(np.interp(tb, tr[:, 0], tr[:, 1])), float(np.interp(tb, tr[:, 0], tr[:, 2])), u, v, leg)
        for tb, _, _, u, v, leg in exp["samples"]
    ]
    return frames, exp


def _record_tlog(frames: list[bytes], tmp_path, name="flight.tlog"):
    """Write frames to a tlog with pymavlink's own tlog writer (mavfile.setup_logfile)."""
    raw = tmp_path / (name + ".raw")
    raw.write_bytes(b"".join(frames))
    tlog = tmp_path / name
    src = mavutil.mavlogfile(str(raw), notimestamps=True)
    src.setup_logfile(str(tlog))
    n = 0
    while src.recv_msg() is not None:
        n += 1
    src.logfile.close()
    src.close()
    assert n == len(frames)
    return tlog


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tlog")
    frames, exp = _scenario()
    return _record_tlog(frames, tmp), frames, exp


def _sample_tuples(c):
    """(tb, lat, lon, u, v, leg); lat/lon rounded to 1e-9 deg (a lost fix changes an interpolation's rounding)."""
    return [(s.time_boot_ms, round(s.lat, 9), round(s.lon, 9), s.u, s.v, s.leg) for s in c.samples]


def test_reads_exact_samples_track_legs(recorded):
    path, frames, exp = recorded
    c = read_tlog(path)
    assert c.skipped_bytes == 0 and c.bad_frames == 0
    assert c.n_messages == len(frames)
    assert c.vehicle_sysid == VEH
    got = _sample_tuples(c)
    assert len(got) == len(exp["samples"]) == 8 and c.n_readings == 8
    for g, e in zip(got, exp["samples"]):
        assert g[0] == e[0] and g[5] == e[5]
        assert g[1:5] == pytest.approx(e[1:5], abs=1e-9)
    assert [s.gap_ms for s in c.samples] == [0, 0, 0, 1150, 1300, 0, 0, 0]
    np.testing.assert_allclose(c.track_array(), np.array(exp["track"]), rtol=0, atol=1e-9)
    # legs: two accepted uploads; the rejected NO_SPACE upload starts none
    assert [m.accepted for m in c.missions] == [True, False, True]
    assert c.missions[1].result == 4
    accepted = [m for m in c.missions if m.accepted]
    for m, wps in zip(accepted, exp["missions"]):
        assert m.complete
        # int32 degE7 round-trips exactly; float MISSION_ITEM carries float32 degrees (ulp ~4e-6 deg at 50 N)
        atol = 1e-9 if m.int_items else 4e-6
        np.testing.assert_allclose(np.array(m.waypoints), np.array(wps), rtol=0, atol=atol)
    assert not accepted[1].int_items  # float MISSION_ITEM upload
    assert len(c.missions[0].items) == 4  # the re-sent item is kept once
    assert len(c.legs) == 2
    assert c.legs[0].complete and c.legs[0].n_samples == 4 and c.legs[0].n_waypoints == 3
    assert c.legs[0].n_readings == 4
    # the second leg is not closed by the stale "complete" report right after its upload
    assert not c.legs[1].complete and c.legs[1].t_end is None and c.legs[1].n_samples == 2
    assert c.legs[0].t_end <= c.legs[1].t_start
    kinds = [e.kind for e in c.events]
    assert [e.value for e in c.events if e.kind == "item_reached"] == [1, 2, 3]
    assert [e.detail for e in c.events if e.kind == "mode"] == ["INITIALISING", "MANUAL", "AUTO", "HOLD"]
    assert kinds.count("complete") == 1  # state 5 and "Mission Complete" text are one completion
    assert [e.value for e in c.events if e.kind == "armed"] == [0, 1]


def test_custom_names_and_gap_bound(recorded):
    path, _, _ = recorded
    c = read_tlog(path, u_name="XX_U")
    assert len(c.samples) == 1 and c.samples[0].leg == 1
    # a tighter gap bound drops the two readings whose fixes are 1150 and 1300 ms apart, and only them
    c2 = read_tlog(path, max_gap_ms=1100)
    assert len(c2.samples) == 6 and c2.n_readings == 8 and max(s.gap_ms for s in c2.samples) == 0
    assert c2.legs[0].n_samples == 2 and c2.legs[0].n_readings == 4


def _record_offsets(path):
    """Byte offset where each record (timestamp + frame) of an intact tlog ends."""
    c = mavutil.mavlogfile(str(path))
    ends, pos = [], 0
    while (m := c.recv_msg()) is not None:
        pos += 8 + len(m.get_msgbuf())
        ends.append(pos)
    c.close()
    return ends


def test_truncated_tlog(recorded, tmp_path):
    path, _, _ = recorded
    data = path.read_bytes()
    ends = _record_offsets(path)
    full = read_tlog(path)
    cut = ends[len(ends) * 2 // 3] + 13  # 13 bytes into the next record: mid-frame
    bad = tmp_path / "cut.tlog"
    bad.write_bytes(data[:cut])
    c = read_tlog(bad)
    assert c.n_messages == len(ends) * 2 // 3 + 1
    assert c.skipped_bytes == 13
    got, ref = _sample_tuples(c), _sample_tuples(full)
    assert 0 < len(got) < len(ref) and got == ref[: len(got)]
    assert [p.time_boot_ms for p in c.track] == [p.time_boot_ms for p in full.track][: len(c.track)]


def _insert_junk(data: bytes, seed: int, n: int = 4) -> tuple[bytes, int]:
    rng = random.Random(seed)
    out, inserted = bytearray(data), 0
    for _ in range(n):
        p = rng.randrange(100, len(out) - 100)
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(5, 60)))
        out[p:p] = junk
        inserted += len(junk)
    return bytes(out), inserted


@pytest.mark.parametrize("seed", range(12))
def test_random_bytes_inserted(recorded, tmp_path, seed):
    """Junk at 4 random places: what is read is true, the junk is counted, little else is lost.

    Measurement values are never invented; leg labels can change when the junk hits
    the upload frames themselves (then the leg boundary is unknowable), so they are
    compared exactly only for seed 7, where it does not.
    """
    path, _, _ = recorded
    full = read_tlog(path)
    data, inserted = _insert_junk(path.read_bytes(), seed)
    bad = tmp_path / "junk.tlog"
    bad.write_bytes(data)
    c = read_tlog(bad)
    assert c.bad_frames >= 1
    assert c.skipped_bytes >= inserted
    ref, got = _sample_tuples(full), _sample_tuples(c)
    assert {g[:5] for g in got} <= {r[:5] for r in ref}  # no invented measurement
    assert len(got) >= len(ref) - 4  # at most one sample lost per damaged spot
    track_ref = {(p.time_boot_ms, p.lat, p.lon) for p in full.track}
    assert {(p.time_boot_ms, p.lat, p.lon) for p in c.track} <= track_ref
    assert c.n_messages >= full.n_messages - 4 * 3  # a damaged spot costs at most ~3 messages
    if seed == 7:
        assert set(got) <= set(ref) and len(c.legs) == 2


def test_no_heartbeat_in_log(recorded, tmp_path):
    """Without any vehicle HEARTBEAT the vehicle is the system sending positions."""
    path, _frames, _ = recorded
    full = read_tlog(path)
    ends = _record_offsets(path)
    data = path.read_bytes()
    c = mavutil.mavlogfile(str(path))
    keep, pos = bytearray(), 0
    for end in ends:
        m = c.recv_msg()
        if not (m.get_type() == "HEARTBEAT" and m.get_srcSystem() == VEH):
            keep += data[pos:end]
        pos = end
    c.close()
    nohb = tmp_path / "nohb.tlog"
    nohb.write_bytes(bytes(keep))
    r = read_tlog(nohb)
    assert r.vehicle_sysid == VEH
    assert _sample_tuples(r) == _sample_tuples(full)
    assert len(r.legs) == 2


def test_garbage_file_and_missing(tmp_path):
    g = tmp_path / "noise.tlog"
    g.write_bytes(bytes(random.Random(1).randrange(256) for _ in range(5000)))
    c = read_tlog(g)
    assert c.samples == [] and c.legs == []
    assert c.skipped_bytes > 4500
    with pytest.raises(UserError):
        read_tlog(tmp_path / "nope.tlog")


def _write_bin(path, pos_rows, cur_rows, nvf_rows=()):
    """A minimal ArduPilot DataFlash .bin via DFReader's own format classes (FMT records + data)."""
    fmt_fmt = DFReader.DFFormat(0x80, "FMT", 89, "BBnNZ", "Type,Length,Name,Format,Columns")
    fmts = {
        "POS": DFReader.DFFormat(0x81, "POS", 0, "QLLf", "TimeUS,Lat,Lng,Alt"),
        "CUR": DFReader.DFFormat(0x82, "CUR", 0, "Qff", "TimeUS,U,V"),
        "NVF": DFReader.DFFormat(0x83, "NVF", 0, "QNf", "TimeUS,Name,Value"),
    }
    import struct

    out = bytearray()

    def fmt_record(f):
        cols = ",".join(f.columns).encode()
        return struct.pack("<BBB", 0xA3, 0x95, 0x80) + struct.pack(
            fmt_fmt.msg_struct, f.type, struct.calcsize(f.msg_struct) + 3, f.name.encode(), f.format.encode(), cols
        )

    out += fmt_record(fmt_fmt)
    for f in fmts.values():
        out += fmt_record(f)

    def rec(f, *vals):
        return struct.pack("<BBB", 0xA3, 0x95, f.type) + struct.pack(f.msg_struct, *vals)

    for tus, la, lo in pos_rows:
        out += rec(fmts["POS"], tus, _deg7(la), _deg7(lo), 1.0)
    for tus, u, v in cur_rows:
        out += rec(fmts["CUR"], tus, u, v)
    for tus, name, val in nvf_rows:
        out += rec(fmts["NVF"], tus, name, val)
    path.write_bytes(bytes(out))


def test_read_dataflash(tmp_path):
    pos = [(1_000_000 * i, LAT0 + 1e-4 * i, LON0 - 1e-4 * i) for i in range(1, 11)]
    cur = [(1_000_000 * i + 50_000, 0.25 * i, -0.5) for i in range(1, 11)]
    cur.append((60_000_000, 9.0, 9.0))  # no position after it
    b = tmp_path / "log.bin"
    _write_bin(b, pos, cur)
    c = read_dataflash(b)
    assert len(c.track) == 10
    assert c.track[3].lat == pytest.approx(LAT0 + 4e-4, abs=1e-7)
    assert len(c.samples) == 9 and c.n_readings == 11  # 10050 and 60000 ms have no fix after them
    s = c.samples[4]
    assert (s.time_boot_ms, s.u, s.v, s.leg, s.gap_ms) == (5050, pytest.approx(1.25), pytest.approx(-0.5), -1, 1000)
    # 50 ms into the straight 1 s stretch from fix 5 to fix 6 (degE7 rounding: 1e-7 deg)
    assert (s.lat, s.lon) == pytest.approx((LAT0 + 5.05e-4, LON0 - 5.05e-4), abs=1.5e-7)
    assert c.skipped_bytes == 0

    # named values (NVF) paired by time instead of a script message
    b2 = tmp_path / "nvf.bin"
    nvf = [(1_000_000 * i, b"CUR_U", 0.1 * i) for i in range(1, 4)] + [
        (1_000_000 * i + 2000, b"CUR_V", 0.2) for i in range(1, 4)
    ]
    _write_bin(b2, pos, [], nvf)
    c2 = read_dataflash(b2)
    assert [round(x.u, 5) for x in c2.samples] == [0.1, 0.2, 0.3]
    assert all(x.v == pytest.approx(0.2) for x in c2.samples)


def test_tlog_written_by_the_simulator(tmp_path):
    """A tlog the boat simulator writes (its own TlogWriter) while a plain pymavlink GCS runs two legs.

    The expected answers come from what the GCS itself received, in order.
    """
    from simclient import SimClient  # tests/ is on sys.path (pytest rootdir conftest)

    from vehicle_sim import MODES, SimConfig, Simulator

    M = mavutil.mavlink
    home = (40.0, -63.0)
    tlog = tmp_path / "sim.tlog"
    sim = Simulator(None, home=home, config=SimConfig.fast(tlog=str(tlog)), uniform_current=(0.2, -0.1))
    sim.run_until(2.0)
    c = SimClient(sim)
    legs = [
        [(home[0] + 1e-4, home[1]), (home[0] + 2e-4, home[1])],
        [(home[0] + 2e-4, home[1] + 1e-4), (home[0] + 2e-4, home[1] + 2e-4)],
    ]
    try:
        assert c.arm().result == 0
        for wps in legs:
            items = [SimClient.waypoint(0, *home)] + [
                SimClient.waypoint(i, la, lo) for i, (la, lo) in enumerate(wps, 1)
            ]
            assert c.upload(items).type == M.MAV_MISSION_ACCEPTED
            assert c.set_mode(MODES["AUTO"]).result == 0
            assert c.wait("STATUSTEXT", lambda m: m.text == "Mission Complete", timeout=120) is not None
            assert c.set_mode(MODES["HOLD"]).result == 0
            c.collect(3.0)
    finally:
        sim.close()
    # what the GCS saw: CUR_U/CUR_V readings and the leg open when each arrived
    leg, n_acc, seen = -1, 0, []
    for _, m in c.log:
        t = m.get_type()
        if t == "MISSION_ACK" and m.type == 0 and m.mission_type == 0:
            leg, n_acc = n_acc, n_acc + 1
        elif t == "STATUSTEXT" and m.text == "Mission Complete":
            leg = -1
        elif t == "NAMED_VALUE_FLOAT" and m.name == "CUR_U":
            seen.append((m.time_boot_ms, leg))
    r = read_tlog(tlog)
    assert r.bad_frames == 0 and r.skipped_bytes == 0
    assert [(s.time_boot_ms, s.leg) for s in r.samples] == seen
    assert all(s.u == pytest.approx(0.2, abs=1e-6) and s.v == pytest.approx(-0.1, abs=1e-6) for s in r.samples)
    assert [(L.complete, L.n_waypoints) for L in r.legs] == [(True, 2), (True, 2)]
    for m, wps in zip([m for m in r.missions if m.accepted], legs):
        np.testing.assert_allclose(np.array(m.waypoints), np.array(wps), atol=1e-9)
    # the boat ends near the last waypoint of the last leg
    last = r.track[-1]
    assert geo_dist(last.lat, last.lon, *legs[-1][-1]) < 5.0


def geo_dist(lat1, lon1, lat2, lon2) -> float:
    import geo

    return float(geo.geodesic_distance_m(lat1, lon1, lat2, lon2))


def test_read_dataflash_truncated_and_junk(tmp_path):
    pos = [(1_000_000 * i, LAT0 + 1e-4 * i, LON0) for i in range(1, 21)]
    cur = [(1_000_000 * i, 0.1, 0.2) for i in range(1, 21)]
    b = tmp_path / "log.bin"
    _write_bin(b, pos, cur)
    data = b.read_bytes()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[:-7])  # the last CUR record (3 + 16 bytes) loses 7 bytes
    c = read_dataflash(cut)
    assert len(c.track) == 20 and len(c.samples) == 19
    # a cut-off last record is a truncated tail (a log copied while written, a power cut), not damage
    assert c.truncated_bytes == 3 + 16 - 7 and c.bad_frames == 0 and c.skipped_bytes == 0
    junk = tmp_path / "junk.bin"
    p = len(data) // 2
    junk.write_bytes(data[:p] + bytes(random.Random(3).randrange(256) for _ in range(40)) + data[p:])
    c2 = read_dataflash(junk)
    assert c2.skipped_bytes >= 40
    ref = {(s.time_boot_ms, s.u, s.v) for s in read_dataflash(b).samples}
    assert {(s.time_boot_ms, s.u, s.v) for s in c2.samples} <= ref and len(c2.samples) >= 17
    with pytest.raises(UserError):
        read_dataflash(tmp_path / "none.bin")


def test_invalid_sequence_ack_mid_upload_does_not_end_it(tmp_path):
    """ArduPilot answers a duplicate/out-of-order item with MISSION_ACK 13 (INVALID_SEQUENCE)
    and keeps the transfer open; the upload is accepted by the final ACK 0, so the reader
    must not close it at the first ack."""
    ml = mavutil.mavlink
    veh = ml.MAVLink(None, srcSystem=VEH, srcComponent=1)
    gcs = ml.MAVLink(None, srcSystem=GCS, srcComponent=190)
    wps = [(LAT0 + 0.01, LON0), (LAT0 + 0.02, LON0 + 0.01)]
    items = [(LAT0, LON0)] + wps
    frames = [
        bytes(veh.heartbeat_encode(11, 3, 1, 0, 4).pack(veh)),
        bytes(gcs.mission_count_encode(VEH, 1, len(items)).pack(gcs)),
    ]
    for seq, (la, lo) in enumerate(items):
        frames.append(bytes(veh.mission_request_encode(GCS, 190, seq).pack(veh)))
        frames.append(
            bytes(gcs.mission_item_int_encode(VEH, 1, seq, 6, 16, 0, 1, 0, 2, 0, 0, _deg7(la), _deg7(lo), 0).pack(gcs))
        )
        if seq == 1:  # a late duplicate of item 0 is refused, the transfer goes on
            frames.append(
                bytes(
                    gcs.mission_item_int_encode(VEH, 1, 0, 6, 16, 0, 1, 0, 2, 0, 0, _deg7(LAT0), _deg7(LON0), 0).pack(
                        gcs
                    )
                )
            )
            frames.append(bytes(veh.mission_ack_encode(GCS, 190, 13).pack(veh)))
    # and one after the last item, before the final ACK (seen in a demo run at 150x: the report then
    # counted the upload as rejected and drew the wrong leg's track)
    frames.append(bytes(veh.mission_ack_encode(GCS, 190, 13).pack(veh)))
    frames.append(bytes(veh.mission_ack_encode(GCS, 190, 0).pack(veh)))
    c = read_tlog(_record_tlog(frames, tmp_path))
    assert len(c.missions) == 1 and c.missions[0].accepted
    assert len(c.legs) == 1
    np.testing.assert_allclose(
        np.array(c.missions[0].waypoints), np.array([(_deg7(a) * 1e-7, _deg7(b) * 1e-7) for a, b in wps]), atol=1e-9
    )
