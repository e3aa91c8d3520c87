"""The crash-safe sample store (passt_mav.runs.store) and the run directory layout."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from passt_mav.errors import UserError
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import Sample, SampleStore

REPO = Path(__file__).resolve().parent.parent


def _s(tb: int, leg: int = 0, source: str = "mav:1/1", **kw) -> Sample:
    return Sample(
        time_boot_ms=tb,
        utc=1.7e9 + tb / 1000,
        lat=40.0 + tb * 1e-7,
        lon=-63.0 - tb * 1e-7,
        u=0.001 * tb,
        v=-0.5,
        leg=leg,
        source=source,
        **kw,
    )


def test_round_trip_exact(tmp_path):
    p = tmp_path / "samples.sqlite"
    samples = [_s(1000), _s(2000, row=3, col=4), _s(3000, leg=1)]
    with SampleStore(p) as st:
        assert all(st.append(s) for s in samples)
        assert st.count() == 3
    with SampleStore(p) as st:
        got = st.all()
    assert got == samples  # floats round-trip exactly through SQLite REAL
    assert (got[1].row, got[1].col) == (3, 4) and got[0].row is None
    assert sqlite3.connect(p).execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_duplicates_ignored(tmp_path):
    with SampleStore(tmp_path / "s.sqlite") as st:
        assert st.append(_s(1000)) is True
        # the same measurement again (retransmission / second link / reconnect), even labelled with the next leg
        assert st.append(_s(1000, leg=1)) is False
        assert st.append(dict(time_boot_ms=1000, utc=0.0, lat=0.0, lon=0.0, u=9.0, v=9.0, source="mav:1/1")) is False
        # another vehicle at the same time_boot_ms, or the same vehicle after a reboot: new
        assert st.append(_s(1000, source="mav:2/1")) is True
        assert st.append(_s(1000, boot=1)) is True
        assert st.append_many([_s(1000), _s(2000), _s(2000), _s(3000)]) == 2
        assert st.count() == 5
        assert st.all()[0].u == pytest.approx(1.0) and st.all()[0].leg == 0  # the first copy is kept


def test_leg_filter_and_validation(tmp_path):
    with SampleStore(tmp_path / "s.sqlite") as st:
        st.append_many([_s(1000, leg=-1), _s(2000, leg=0), _s(3000, leg=0), _s(4000, leg=1)])
        assert [s.time_boot_ms for s in st.for_leg(0)] == [2000, 3000]
        assert [s.time_boot_ms for s in st.for_leg(-1)] == [1000]
        assert st.count(leg=1) == 1 and st.for_leg(7) == []
        with pytest.raises(UserError, match="finite"):
            st.append(_s(5000, leg=1).__class__(5000, 1.0, 40.0, float("nan"), 0.1, 0.1))
        with pytest.raises(UserError, match="unknown sample field"):
            st.append(dict(time_boot_ms=1, utc=1.0, lat=1.0, lon=1.0, u=0.0, v=0.0, speed=3))
        # append_many is all or nothing
        with pytest.raises(UserError):
            st.append_many([_s(6000), _s(7000).__class__(7000, float("inf"), 0.0, 0.0, 0.0, 0.0)])
        assert st.count() == 4


def test_not_a_store(tmp_path):
    bad = tmp_path / "junk.sqlite"
    bad.write_bytes(b"this is not sqlite at all" * 100)
    with pytest.raises(UserError, match="not a readable sample store"):
        SampleStore(bad)
    with pytest.raises(UserError, match="not found"):
        SampleStore(tmp_path / "none.sqlite", readonly=True)


def test_reader_thread_appends_while_main_reads(tmp_path):
    st = SampleStore(tmp_path / "s.sqlite")
    n = 300

    def writer():
        for k in range(n):
            st.append(_s(1000 + k))

    th = threading.Thread(target=writer)
    th.start()
    seen = []
    while th.is_alive():
        seen.append(st.count())
    th.join()
    assert st.count() == n and seen == sorted(seen)
    # and another process-level reader sees everything committed
    with SampleStore(tmp_path / "s.sqlite", readonly=True) as ro:
        assert ro.count() == n
        with pytest.raises(UserError, match="read-only"):
            ro.append(_s(99))
    st.close()


_CHILD = r"""
import sys
from passt_mav.runs.store import Sample, SampleStore
st = SampleStore(sys.argv[1])
k = 0
while True:
    st.append(Sample(1000 * k, 1.7e9 + k, 40.0, -63.0, 0.1 * k, 0.0, k // 10, "sim"))
    print(k, flush=True)  # acknowledged: append has returned
    k += 1
"""


def test_survives_sigkill(tmp_path):
    """A writer killed with SIGKILL mid-stream loses nothing it had acknowledged."""
    db = tmp_path / "samples.sqlite"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(db)], stdout=subprocess.PIPE, text=True, env=env)
    acked = []
    deadline = time.monotonic() + 30
    try:
        while len(acked) < 40 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            acked.append(int(line))
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=10)
    acked += [int(x) for x in proc.stdout.read().split()]  # lines printed before the kill
    assert proc.returncode == -signal.SIGKILL
    assert len(acked) >= 40
    with SampleStore(db) as st:
        rows = st.all()
    stored = {s.time_boot_ms // 1000 for s in rows}
    assert set(acked) <= stored
    assert len(rows) - len(acked) in (0, 1)  # at most the one committed but not yet printed
    assert rows[5] == Sample(5000, 1.7e9 + 5, 40.0, -63.0, 0.1 * 5, 0.0, 0, "sim")


def test_rundir_layout(tmp_path):
    rd = RunDir(tmp_path / "r").create()
    assert rd.create() is rd and rd.is_run_dir()
    assert rd.samples_db.name == "samples.sqlite" and rd.tlog.name == "flight.tlog"
    assert rd.mission_file.name == "mission.yaml"
    assert rd.leg_dir(3) == rd.root / "legs" / "003" and rd.leg_dir(3).is_dir()
    assert rd.estimate_file(3).name == "estimate.nc" and rd.plan_file(3).name == "mission.plan"
    rd.write_leg(12, {"path": [[0, 0], [1, 1]], "planning_s": 1.5})
    assert rd.leg_indices() == [3, 12]
    assert json.loads(rd.path_file(12).read_text()) == [[0, 0], [1, 1]]
    assert rd.read_legs() == [{"schema_version": 1, "path": [[0, 0], [1, 1]], "planning_s": 1.5, "index": 12}]
    rd.write_summary({"status": "complete", "x": 1.25})
    assert rd.read_summary() == {"schema_version": 1, "status": "complete", "x": 1.25}
    assert [p.name for p in rd.root.iterdir() if p.name.endswith(".tmp")] == []
    with pytest.raises(UserError, match="not valid JSON"):
        rd.summary_file.write_text("{oops")
        rd.read_summary()
    (tmp_path / "empty").mkdir()
    assert not RunDir(tmp_path / "empty").is_run_dir() and not RunDir(tmp_path / "nope").is_run_dir()
    new = RunDir.new(tmp_path / "runs", "ocean demo", utc="2026-05-01T10-00-00Z")
    again = RunDir.new(tmp_path / "runs", "ocean demo", utc="2026-05-01T10-00-00Z")
    assert new.root.name == "2026-05-01T10-00-00Z_ocean-demo" and again.root.name.endswith("_2")


def test_a_version_1_store_without_gap_ms_still_opens_and_gets_the_column(tmp_path):
    """Run folders written before the interpolation gap was stored: read-only gives gap_ms None; a
    writer adds the column (old rows NULL) and stores the gap of new samples."""
    import sqlite3

    path = tmp_path / "samples.sqlite"
    con = sqlite3.connect(path)
    con.executescript("""
        CREATE TABLE samples (id INTEGER PRIMARY KEY AUTOINCREMENT, time_boot_ms INTEGER NOT NULL, utc REAL NOT NULL,
            lat REAL NOT NULL, lon REAL NOT NULL, u REAL NOT NULL, v REAL NOT NULL, leg INTEGER NOT NULL,
            source TEXT NOT NULL, row INTEGER, col INTEGER, boot INTEGER NOT NULL DEFAULT 0,
            UNIQUE (source, boot, time_boot_ms));
        PRAGMA user_version=1;
        INSERT INTO samples (time_boot_ms, utc, lat, lon, u, v, leg, source, row, col, boot)
            VALUES (1000, 1.7e9, 40.0, -63.0, 0.5, -0.25, 0, 'mav:1/1', 3, 4, 0);
    """)
    con.commit(), con.close()
    with SampleStore(path, readonly=True) as ro:
        (old,) = ro.all()
        assert (old.time_boot_ms, old.u, old.row, old.gap_ms) == (1000, 0.5, 3, None)
    with SampleStore(path) as st:
        assert st.append(
            time_boot_ms=1250, utc=1.7e9, lat=40.0, lon=-63.0, u=0.1, v=0.2, leg=0, source="mav:1/1", gap_ms=1000
        )
        assert [s.gap_ms for s in st.all()] == [None, 1000]
    con = sqlite3.connect(path)
    assert con.execute("PRAGMA user_version").fetchone()[0] == 2
    con.close()


def test_since_follows_a_store_being_written(tmp_path):
    """A reader following a live store (the live view) gets each sample once, in arrival order."""
    db = tmp_path / "s.sqlite"
    with SampleStore(db) as w:
        w.append_many(
            [
                {"time_boot_ms": k, "utc": 1.0e9 + k, "lat": 40.0, "lon": -62.0 + k, "u": 0.1 * k, "v": 0.0}
                for k in range(3)
            ]
        )
        with SampleStore(db, readonly=True) as r:
            first = r.since(0)
            assert [s.u for _, s in first] == pytest.approx([0.0, 0.1, 0.2])
            w.append(time_boot_ms=9, utc=1.0e9 + 9, lat=40.0, lon=-61.0, u=0.9, v=0.0)
            later = r.since(first[-1][0])
    assert [s.u for _, s in later] == pytest.approx([0.9]) and later[0][0] > first[-1][0]
