"""The measurement rules (passt_mav.loop.measurement, issue 30): one pairing, one reboot rule, one truth, one RMSE,
one records-to-columns, and the live collector and the log readers giving the same samples from the same stream."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as M

from passt_mav.errors import UserError
from passt_mav.loop.measurement import RULES, BootCounter, HalfPairer, rmse, sample_columns, truth_at


# -- the constants ------------------------------------------------------------------------------
def test_one_set_of_constants_in_seconds_with_ms_views():
    from geo.track import DEFAULT_MAX_GAP_MS

    assert RULES.describe() == {"pair_tolerance_s": 0.05, "max_gap_s": 3.0, "reboot_back_s": 3.0}
    assert (RULES.pair_tolerance_ms, RULES.max_gap_ms, RULES.reboot_back_ms) == (50, DEFAULT_MAX_GAP_MS, 3000)


def test_the_users_take_their_defaults_from_the_rules():
    """The live collector and both log readers default to the one set (no private constants left)."""
    import inspect

    from passt_mav.mavlink import SampleCollector
    from passt_mav.runs.dataflash_legs import rebuild_from_dataflash
    from passt_mav.runs.tlog import read_dataflash, read_tlog

    c = SampleCollector(lambda r: None)
    assert (c.pairer.tolerance_ms, c.track.max_gap_ms, c.reboot_back_ms) == (
        RULES.pair_tolerance_ms,
        RULES.max_gap_ms,
        RULES.reboot_back_ms,
    )
    for f in (read_tlog, read_dataflash, rebuild_from_dataflash):
        p = inspect.signature(f).parameters
        assert (p["pair_tolerance_ms"].default, p["max_gap_ms"].default) == (RULES.pair_tolerance_ms, RULES.max_gap_ms)


# -- 1. halves ----------------------------------------------------------------------------------
def test_halves_a_few_ms_apart_make_one_reading_stamped_with_its_u_half():
    """ArduPilot stamps each send_named_float with its own clock: halves 1-2 ms apart are one reading."""
    p = HalfPairer()
    assert p.add("u", 1000, 0.1, "a") is None
    assert p.add("v", 1002, 0.2, "b") == (1000, 0.1, 0.2, "a", "b")
    assert p.add("v", 1250, 0.4) is None  # v first: the reading still takes the u half's time
    assert p.add("u", 1251, 0.3) == (1251, 0.3, 0.4, None, None)
    assert len(p) == 0


def test_halves_beyond_the_tolerance_stay_apart_and_a_lost_half_never_takes_a_neighbours():
    p = HalfPairer()
    assert p.add("u", 0, 1.0) is None
    assert p.add("v", 51, 2.0) is None  # 51 ms > 50 ms
    assert p.add("v", 50 + 1000, 2.0) is None and len(p) == 3
    # a 10 Hz sensor whose v half of 2000 was lost: the u of 2000 keeps waiting, the 2100 reading pairs itself
    p = HalfPairer()
    p.add("u", 2000, 1.0)
    p.add("u", 2100, 1.1)
    assert p.add("v", 2100, 2.1).u == 1.1
    assert 2000 in p and 2100 not in p


def test_the_nearest_waiting_half_wins_and_lone_halves_expire():
    p = HalfPairer(tolerance_ms=50, keep_ms=5000)
    p.add("u", 1000, 1.0)
    p.add("u", 1030, 2.0)
    assert p.add("v", 1025, 9.0).u == 2.0  # 5 ms from 1030, 25 ms from 1000
    assert p.add("u", 7000, 3.0) is None  # 1000 is 6 s older than the newest half: expired
    assert p.expired == 1 and 1000 not in p
    assert p.expire(8000) == 1 and len(p) == 0 and p.expired == 2
    p.add("u", 1, 1.0)
    p.clear()  # a reboot: forgotten, not expired
    assert len(p) == 0 and p.expired == 2
    with pytest.raises(ValueError):
        HalfPairer(tolerance_ms=-1)
    with pytest.raises(ValueError):
        p.add("w", 1, 1.0)


# -- 3. boots -----------------------------------------------------------------------------------
def test_the_clock_going_back_more_than_3_s_is_a_reboot():
    b = BootCounter()
    assert [b.see(t) for t in (5000, 9000, 8000, 6000)] == [None] * 4  # 3 s back exactly: reordering at most
    assert b.boot == 0 and b.newest == 9000
    assert b.see(5999) == 9000 and b.boot == 1 and b.newest == 5999
    assert b.see(7000) is None and b.boot == 1


# -- 4. truth, 5. RMSE ----------------------------------------------------------------------------
class _Field:
    def __init__(self, times, data):
        self.times, self.data, self.n_times = np.asarray(times, float), np.asarray(data, np.float32), len(times)


def test_truth_at_snapshots_exact_linear_between_none_outside():
    rng = np.random.default_rng(0)
    data = rng.normal(size=(3, 2, 4, 5)).astype(np.float32)
    f = _Field([0.0, 600.0, 1200.0], data)
    for k, t in enumerate(f.times):
        got = truth_at(f, t + 1e-10 * max(1.0, t))  # within 1e-9 (relative): the snapshot itself, bit for bit
        assert got.dtype == np.float64 and np.array_equal(got, data[k].astype(np.float64))
    np.testing.assert_allclose(truth_at(f, 150.0), 0.75 * data[0] + 0.25 * data[1], rtol=1e-6)
    assert truth_at(f, -1.0) is None and truth_at(f, 1200.01) is None
    one = _Field([5.0], data[:1])
    assert np.array_equal(truth_at(one, 5.0), data[0].astype(np.float64)) and truth_at(one, 6.0) is None
    got = truth_at(f, 600.0)
    got[:] = 0.0  # a copy: the field is not written through
    assert f.data[1].any()


def test_rmse_one_nan_rule_cells_whole_or_not_at_all():
    truth = np.zeros((2, 3, 4))
    est = truth.copy()
    est[0] += 0.3
    est[1, 0, 0] = np.nan  # the cell (0, 0) is left out whole: its u error does not count either
    assert rmse(est, truth) == pytest.approx(np.sqrt(0.09 / 2), rel=1e-15)
    truth[0, 2, 3] = np.nan  # missing in the truth (land): left out the same way
    assert rmse(est, truth) == pytest.approx(np.sqrt(0.09 / 2), rel=1e-15)
    assert rmse(np.full((2, 2, 2), np.nan), np.zeros((2, 2, 2))) is None
    assert rmse(est, None) is None
    # a stack of states (..., 2, rows, cols) pools every cell of every state
    assert rmse(np.ones((3, 2, 2, 2)), np.zeros((3, 2, 2, 2))) == 1.0
    with pytest.raises(UserError, match="does not match"):
        rmse(np.zeros((2, 3, 4)), np.zeros((2, 4, 3)))
    with pytest.raises(UserError, match="2, rows, cols"):
        rmse(np.zeros((3, 3, 4)), np.zeros((3, 3, 4)))


# -- 6. columns ---------------------------------------------------------------------------------
def test_sample_columns_of_store_rows_and_collector_dicts():
    from passt_mav.runs.store import Sample

    rows = [
        Sample(1000, 1.7e9, 40.0, -63.0, 0.1, 0.2, 3, "mav:1/1", boot=1),
        {"time_boot_ms": 2000.5, "lat": 40.1, "lon": -63.1, "u": 0.3, "v": 0.4, "boot": None},
    ]
    c = sample_columns(rows)
    assert set(c) == {"time_boot_ms", "utc", "lat", "lon", "u", "v", "leg", "boot"}
    assert c["time_boot_ms"].tolist() == [1000.0, 2000.5]  # float64: field times of in_field_time records survive
    assert np.isnan(c["utc"][1]) and c["utc"][0] == 1.7e9
    assert c["leg"].tolist() == [3, -1] and c["boot"].tolist() == [1, 0]
    assert c["leg"].dtype == np.int64 and c["u"].dtype == np.float64
    assert all(len(v) == 0 for v in sample_columns([]).values())


# -- the live collector and the log readers on the same stream -------------------------------------
def _stream():
    """Vehicle messages of two boots (sysid 1): 1 Hz fixes, 4 Hz readings whose halves are 0-2 ms apart
    (one 60 ms apart: never a reading), a reboot 6.5 s back in time (the old tlog reader's 10 s missed it),
    then readings at the first boot's times again."""
    veh = M.MAVLink(None, srcSystem=1, srcComponent=1)
    out = [veh.heartbeat_encode(11, 3, 129, 10, 4)]
    for boot, (t0, t1) in enumerate(((2000, 8000), (1500, 6500))):
        for tb in range(t0, t1 + 1, 250):
            if tb % 1000 == 0 or (boot and tb % 1000 == 500):
                out.append(
                    veh.global_position_int_encode(
                        tb, int(4e8 + 10 * tb + boot * 1e5), int(-6.3e8 + 7 * tb), 0, 0, 0, 0, 0, 0
                    )
                )
            dv = 60 if tb == 4500 else (tb // 250) % 3
            out.append(veh.named_value_float_encode(tb, b"CUR_U", 0.001 * tb + boot))
            out.append(veh.named_value_float_encode(tb + dv, b"CUR_V", -0.001 * tb))
    return out


def test_live_collector_and_tlog_reader_agree_on_pairs_positions_and_boots(tmp_path):
    from passt_mav.mavlink import SampleCollector
    from passt_mav.runs.tlog import read_tlog

    msgs = _stream()
    live: list[dict] = []
    col = SampleCollector(live.append)
    raw = bytearray()
    for k, m in enumerate(msgs):
        buf = bytes(m.pack(M.MAVLink(None, srcSystem=1, srcComponent=1)))
        col.handle(M.MAVLink(None).decode(bytearray(buf)))
        raw += struct.pack(">Q", int(1.7e15) + 10_000 * k) + buf
    col.flush()
    path = tmp_path / "two_boots.tlog"
    path.write_bytes(bytes(raw))
    log = read_tlog(path)

    def key(t, boot, u, v, lat, lon):
        return (int(t), int(boot), round(u, 6), round(v, 6), round(lat, 9), round(lon, 9))

    got_live = [key(r["time_boot_ms"], r["boot"], r["u"], r["v"], r["lat"], r["lon"]) for r in live]
    got_log = [key(s.time_boot_ms, s.boot, s.u, s.v, s.lat, s.lon) for s in log.samples]
    assert sorted(got_live) == sorted(got_log)
    assert col.counts["reboots"] == 1 and {x[1] for x in got_log} == {0, 1}
    assert all(x[0] != 4500 for x in got_log)  # the halves 60 ms apart
    # halves 1-2 ms apart are readings like the others: every reading between two fixes of its boot is placed
    assert col.counts["readings"] == log.n_readings == 24 + 20 == len(got_log)
    # the report splits the track by the reader's boots: the positions carry them
    assert [p.boot for p in log.track] == [0] * 7 + [1] * 11


def test_dataflash_pairs_nvf_halves_by_the_same_rule(tmp_path):
    from test_tlog import _write_bin  # tests/ is on sys.path (pytest rootdir conftest)

    from passt_mav.runs.tlog import read_dataflash

    pos = [(1_000_000 * i, 50.0 + 1e-4 * i, -30.0) for i in range(1, 11)]
    nvf = []
    for i in range(1, 10):
        tus = 1_000_000 * i + 250_000
        dv = {3: 1_800, 5: 49_000, 7: 51_000}.get(i, 300)  # µs between the halves
        nvf += [(tus, b"CUR_U", 0.1 * i), (tus + dv, b"CUR_V", 0.2)]
    b = tmp_path / "nvf.bin"
    _write_bin(b, pos, [], nvf)
    c = read_dataflash(b)
    assert c.n_readings == 8 and [s.time_boot_ms for s in c.samples] == [1000 * i + 250 for i in range(1, 10) if i != 7]
