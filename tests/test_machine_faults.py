"""The machine's faults are not the boat's: a full disk, a vanished sample store, a telemetry log that cannot be
written (docs/resilience.md, "The machine's faults"), on vehicle-sim in lockstep.

A store the machine fails stops the run cleanly (status ``stopped``, ``stopped_by`` what failed, the boat in its
wait mode, the readings it could not store kept in a spare file that ``--resume`` imports); a telemetry log that
cannot be written never takes the link down: the run completes and the lost messages are counted.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import tempfile
from pathlib import Path

import pytest
from test_console import LOITER, lockstep_session

from passt_mav.runs import read_tlog
from passt_mav.runs.live import read_events
from passt_mav.runs.store import SampleStore


def _in_leg(ctl, leg: int = 0, reached: int = 2) -> bool:
    """Leg ``leg`` flies with ``reached`` items behind it (read from any thread)."""
    c = ctl.collector
    return c is not None and c.leg == leg and len(ctl.vehicle.progress.reached) >= reached


def _no_traceback(caplog) -> None:
    bad = [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]
    assert not bad, [r.getMessage() for r in bad]


def _said(caplog, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if text in r.getMessage()]


def _stored(rd) -> list:
    with SampleStore(rd.samples_db, readonly=True) as st:
        return st.all()


def _own_temp_dir(tmp_path, monkeypatch) -> Path:
    """The system's temp dir (where the spare folder goes) inside the test's own folder."""
    tmp = tmp_path / "system-tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    return tmp


def _spare_lines(kept: dict) -> list[str]:
    return Path(kept["spare"]).read_text().splitlines()


def test_a_full_disk_mid_leg_stops_in_loiter_keeps_the_readings_and_resume_imports_them(tmp_path, monkeypatch, caplog):
    real = SampleStore.append_many
    full = {"on": False}
    tmp = _own_temp_dir(tmp_path, monkeypatch)
    with lockstep_session(tmp_path) as (sim, make, rd):
        ctl = make(legs=2)

        def append_many(self, samples):  # the disk fills once leg 1 has flown past its second item
            if full["on"] or _in_leg(ctl):
                full["on"] = True
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(self, samples)

        monkeypatch.setattr(SampleStore, "append_many", append_many)
        with caplog.at_level(logging.INFO):
            summary = ctl.run()
        mode = sim.autopilot.mode
        assert summary["status"] == "stopped" and summary["stopped_by"] == f"disk full: {rd.samples_db}"
        assert mode == LOITER  # out of AUTO: the boat waits in its wait_mode
        monkeypatch.setattr(SampleStore, "append_many", real)  # the disk has room again
        before, lines = _stored(rd), _spare_lines(summary["machine_faults"]["store"])
        again = make(legs=2, resume=True).run()
    _no_traceback(caplog)
    kept = summary["machine_faults"]["store"]
    assert kept["reason"] == summary["stopped_by"] and kept["readings_kept"] > 0
    assert Path(kept["spare"]).parent.parent == tmp and len(lines) == kept["readings_kept"]
    spare_tb = {json.loads(x)["time_boot_ms"] for x in lines}
    assert not spare_tb & {r.time_boot_ms for r in before}  # the readings the store missed, none it has
    said = _said(caplog, "stopped: disk full")
    assert len(said) == 1 and kept["spare"] in said[0] and "--resume" in said[0], said
    ev = [e for e in read_events(rd.root)[0] if e["kind"] == "stopped"]
    assert ev and "disk full" in ev[0]["text"]
    # --resume: the spare file's readings into the store, the run to its end
    assert again["status"] == "complete" and len(again["legs"]) == 2
    assert spare_tb <= {r.time_boot_ms for r in _stored(rd)}
    assert any("imported from" in e for e in again["events"])
    assert not Path(kept["spare"]).exists()  # (kept as samples-imported-1.jsonl: not imported twice)
    print(f"full disk: stopped by {summary['stopped_by']!r}, {kept['readings_kept']} readings kept; resumed: complete")


def test_the_store_deleted_mid_run_is_never_complete_and_its_readings_are_rescued(tmp_path, monkeypatch, caplog):
    real = SampleStore.append_many
    gone = {"done": False}
    _own_temp_dir(tmp_path, monkeypatch)
    with lockstep_session(tmp_path) as (sim, make, rd):
        ctl = make(legs=2)

        def append_many(self, samples):  # someone removes samples.sqlite once leg 1 has flown past its second item
            if not gone["done"] and _in_leg(ctl):
                gone["done"] = True
                os.unlink(rd.samples_db)
            return real(self, samples)

        monkeypatch.setattr(SampleStore, "append_many", append_many)
        with caplog.at_level(logging.INFO):
            summary = ctl.run()
        mode = sim.autopilot.mode
        assert not rd.samples_db.exists()
        assert summary["status"] == "stopped" and summary["stopped_by"] == f"store removed: {rd.samples_db}"
        lines = _spare_lines(summary["machine_faults"]["store"])
        again = make(legs=2, resume=True).run()
    _no_traceback(caplog)
    assert rd.read_summary()["status"] == "complete" == again["status"]  # (the resumed run's)
    assert mode == LOITER
    kept = summary["machine_faults"]["store"]
    assert kept["rescued_from_old_file"] > 0 and kept["readings_kept"] > kept["rescued_from_old_file"]
    assert len(lines) == kept["readings_kept"]
    stored = {(r.boot, r.time_boot_ms) for r in _stored(rd)}  # the resumed run's store has them again
    assert {(json.loads(x)["boot"], json.loads(x)["time_boot_ms"]) for x in lines} <= stored


def test_a_leg_file_the_disk_refuses_stops_the_run_cleanly(tmp_path, monkeypatch, caplog):
    """leg 1's timings.json refused (ENOSPC) at its end: stopped as for the store, the boat waiting in LOITER."""
    from passt_mav.runs.rundir import RunDir

    with lockstep_session(tmp_path) as (sim, make, rd):
        ctl = make(legs=2)

        def write_timings(self, i, timings):
            raise OSError(errno.ENOSPC, "No space left on device", str(self.timings_file(i)))

        monkeypatch.setattr(RunDir, "write_timings", write_timings)
        with caplog.at_level(logging.INFO):
            summary = ctl.run()
        mode = sim.autopilot.mode
    assert summary["status"] == "stopped" and summary["stopped_by"] == f"disk full: {rd.timings_file(0)}"
    assert mode == LOITER and rd.read_summary()["status"] == "stopped"
    _no_traceback(caplog)
    assert len(_said(caplog, "stopped: disk full")) == 1


class _FullDisk:
    """The telemetry log's file, refusing writes (ENOSPC) while ``full()`` says so."""

    def __init__(self, f, full):
        self.f, self.full = f, full
        self.refused = self.after = 0

    def write(self, data):
        if self.full():
            self.refused += 1
            raise OSError(errno.ENOSPC, "No space left on device")
        if self.refused:
            self.after += 1
        return self.f.write(data)

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_a_telemetry_log_that_cannot_be_written_never_takes_the_link_down(tmp_path, caplog):
    with lockstep_session(tmp_path, tlog=True) as (sim, make, rd):
        ctl = make(legs=2)
        window: dict = {}

        def full() -> bool:  # 20 s of the simulator's time, from leg 1's second item on
            if "t0" not in window and _in_leg(ctl):
                window["t0"] = sim.t
            return "t0" in window and sim.t < window["t0"] + 20.0

        tlog = ctl.link._tlog
        tlog._f = disk = _FullDisk(tlog._f, full)
        tlog.RETRY_S = 0.05  # (wall s: the lockstep simulator's 20 s pass in a fraction of a second)
        with caplog.at_level(logging.INFO):
            summary = ctl.run()
    assert summary["status"] == "complete" and len(summary["legs"]) == 2
    assert summary["outages"] == [] and not [e for e in summary["events"] if "link lost" in e]
    _no_traceback(caplog)
    lost = summary["machine_faults"]["tlog"]
    assert disk.refused >= 1 and lost["frames"] > disk.refused and lost["error"] == "No space left on device"
    assert disk.after > 0  # written again once the disk had room
    log = read_tlog(rd.tlog)  # whole frames only: the log reads clean, its gap is the lost messages
    assert log.bad_frames == 0 and log.skipped_bytes == 0 and len(log.legs) == 2
    assert len(_said(caplog, "write failed")) == 1  # said once, not per frame
    said = _said(caplog, "telemetry log: ")
    assert len(said) == 1 and f"{lost['frames']} messages" in said[0]
    print(f"tlog: {lost['frames']} messages ({lost['bytes']} bytes) lost, the run complete")


def test_the_store_says_what_failed_in_one_line(tmp_path):
    import sqlite3

    from passt_mav.runs.store import StoreUnwritable, write_fault

    path = tmp_path / "samples.sqlite"
    st = SampleStore(path)
    assert st.append_many([{"time_boot_ms": 1, "utc": 1.0, "lat": 40.0, "lon": -70.0, "u": 0.1, "v": 0.2}]) == 1
    assert st._con.execute("PRAGMA mmap_size").fetchone()[0] == 0  # read(), never a map of the file
    st.check_file()  # (there, writable, room left)
    with pytest.MonkeyPatch.context() as mp:  # (root may write a read-only file: the check is asked to refuse)
        mp.setattr(os, "access", lambda *a, **k: False)
        with pytest.raises(StoreUnwritable, match=f"^store not writable: {path}$"):
            st.check_file()
    path.rename(tmp_path / "moved.sqlite")
    with pytest.raises(StoreUnwritable, match=f"^store removed: {path}$"):
        st.check_file()
    path.write_bytes(b"")
    with pytest.raises(StoreUnwritable, match=f"^store replaced: {path}$"):
        st.check_file()
    st.close()
    assert write_fault(sqlite3.OperationalError("database or disk is full"), path) == f"disk full: {path}"
    assert write_fault(OSError(errno.EROFS, "Read-only file system"), path) == f"file system read-only: {path}"
    assert write_fault(sqlite3.OperationalError("attempt to write a readonly database"), path).startswith("store read")


def test_a_telemetry_log_write_cut_short_leaves_whole_frames(tmp_path):
    """A write the disk cuts short (ENOSPC part way) is cut back to the last whole frame: the log reads clean."""
    from passt_mav.mavlink.clock import SYSTEM_CLOCK
    from passt_mav.mavlink.link import _Tlog

    path = tmp_path / "x.tlog"
    tlog = _Tlog(str(path), SYSTEM_CLOCK)
    tlog.write(b"\xfd" + bytes(20))
    real = tlog._f

    class Short:
        closed = False

        def write(self, data):
            return real.write(data[:5])  # the disk had room for 5 bytes

        def fileno(self):
            return real.fileno()

    tlog._f = Short()
    tlog.write(b"\xfd" + bytes(20))
    tlog.write(b"\xfd" + bytes(20))  # within RETRY_S: not tried, counted
    tlog._f = real
    assert path.stat().st_size == 8 + 21  # the first frame whole, nothing of the cut one
    lost = tlog.lost()
    assert lost["frames"] == 2 and lost["bytes"] == 2 * 29 and "short write" in lost["error"]
    tlog.close()
