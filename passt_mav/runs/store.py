"""The crash-safe sample store of a run: one SQLite file, one row per measurement.

Every current measurement the controller receives (a ``CUR_U``/``CUR_V`` pair
matched with the vehicle's position) is appended here the moment it arrives, so
that a controller killed mid-mission (``kill -9``, a flat laptop battery) keeps
every sample it had acknowledged.

Durability: the database runs in WAL mode with ``synchronous=FULL``. In WAL mode
``NORMAL`` would already survive a crash of the *process* (a committed
transaction is in the WAL file, i.e. in the OS page cache), but not a crash of
the *machine* or a power cut: the last transactions could be lost. ``FULL``
fsyncs the WAL at each commit, so an acknowledged ``append`` survives a power
cut too. Samples arrive at a few per second; an fsync each is cheap next to the
cost of the field work that produced them.

Duplicates: a measurement is identified by ``(source, boot, time_boot_ms)``: the
sending system, the vehicle's boot counter (the controller bumps it when
``time_boot_ms`` jumps backwards, i.e. the autopilot rebooted) and the
autopilot's timestamp. A MAVLink retransmission, a message seen on two links, or
the same message replayed after a reconnect therefore lands once
(``INSERT OR IGNORE`` on a UNIQUE constraint). The leg index is deliberately not
part of the key: a late copy that arrives after the leg switched is still the
same measurement.

Threads: one connection guarded by a lock, so a telemetry reader thread may
append while the main thread reads. Other processes (``passt-mav report`` on a
run in progress) can read concurrently: WAL readers never block the writer.

Record format (:class:`Sample`): ``time_boot_ms`` (int, ms since autopilot
boot), ``utc`` (float, UNIX epoch seconds of reception), ``lat``/``lon``
(WGS84 degrees), ``u``/``v`` (m/s, east/north), ``leg`` (int, -1 outside any
leg), ``source`` (str, e.g. ``"mav:1/1"`` or ``"sim"``), optional ``row``/``col``
(grid cell, or None), ``boot``, ``gap_ms`` (int ms or None): the time between the two
position fixes the sample's lat/lon were interpolated from (:class:`geo.track.Track`;
0 = a fix at the reading's own time; None = not recorded: a simulator's exact position,
or a store written before the column existed).

Schema versions (``PRAGMA user_version``): 1 without ``gap_ms``; 2 adds it. A version-1
store opened for writing gets the column (``ALTER TABLE ... ADD COLUMN``, NULL in the
old rows); opened read-only it reads ``gap_ms`` as None. Old run folders keep opening.

The machine's faults: a full disk, a file system made read-only, the file removed or replaced under the
controller. Each write first checks the file (:meth:`SampleStore.check_file`: the same inode at the path, the
file system writable with some room left) and a failed write is raised as :class:`StoreUnwritable`, whose
``reason`` says what failed in a few words and the path (``disk full: /run/x/samples.sqlite``): a writer keeps
the readings elsewhere and the controller stops the run (:mod:`passt_mav.runs.store_guard`). The file is read
with ``mmap_size=0`` (read() calls, no memory map of the database: a file that shrinks or vanishes under a map
kills the process with SIGBUS); WAL's small index file (``-shm``) stays mapped, it is what lets a report read
while the controller writes, and the check before each write keeps it from growing on a read-only or full disk.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import sqlite3
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Self

from passt_mav.errors import UserError

log = logging.getLogger(__name__)

__all__ = ["Sample", "SampleStore", "SampleStoreError", "StoreUnwritable", "write_fault"]

#: a write is refused (as a full disk) when less than this many bytes are free on the store's file system
MIN_FREE_BYTES = 256 * 1024


class SampleStoreError(UserError):
    """The sample store file cannot be opened or is not a sample store."""


class StoreUnwritable(SampleStoreError):
    """The machine refuses the store's writes (disk full, read-only, the file removed or replaced): ``reason``,
    one line naming what failed and the path, e.g. ``disk full: /run/x/samples.sqlite``."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


#: errno of a failed write -> what failed, in the words of :class:`StoreUnwritable`'s reason
_ERRNO_WHAT = {
    errno.ENOSPC: "disk full",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "file system read-only",
    errno.EACCES: "store not writable",
    errno.EPERM: "store not writable",
    errno.ENOENT: "store removed",
    errno.EIO: "disk I/O error",
}


def write_fault(exc: BaseException, path: str | Path) -> str:
    """One line of what failed, from a write's OSError or sqlite3.Error on ``path`` (``disk full: PATH``)."""
    return f"{_fault_what(exc)}: {path}"


def _fault_what(exc: BaseException) -> str:
    if isinstance(exc, StoreUnwritable):
        return exc.reason.rsplit(": ", 1)[0]
    if isinstance(exc, OSError) and exc.errno in _ERRNO_WHAT:
        return _ERRNO_WHAT[exc.errno]
    text = str(exc).lower()
    for key, what in (
        ("full", "disk full"),
        ("readonly", "store read-only"),
        ("read-only", "store read-only"),
        ("i/o", "disk I/O error"),
        ("malformed", "store damaged"),
        ("not a database", "store damaged"),
    ):
        if key in text:
            return what
    return f"store write failed ({type(exc).__name__}: {exc})"


@dataclass(frozen=True)
class Sample:
    """One current measurement (see module docstring for units and frames)."""

    time_boot_ms: int
    utc: float
    lat: float
    lon: float
    u: float
    v: float
    leg: int = -1
    source: str = "sim"
    row: int | None = None
    col: int | None = None
    boot: int = 0
    gap_ms: int | None = None

    @classmethod
    def coerce(cls, obj: Sample | Mapping[str, Any]) -> Sample:
        """A :class:`Sample` from a Sample or a mapping with the same keys."""
        if isinstance(obj, Sample):
            return obj
        if isinstance(obj, Mapping):
            names = {f.name for f in fields(cls)}
            unknown = set(obj) - names
            if unknown:
                raise SampleStoreError(f"unknown sample field(s): {', '.join(sorted(unknown))}")
            return cls(**obj)
        raise SampleStoreError(f"cannot store a {type(obj).__name__} as a sample")


_COLUMNS = ("time_boot_ms", "utc", "lat", "lon", "u", "v", "leg", "source", "row", "col", "boot", "gap_ms")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS samples (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    time_boot_ms INTEGER NOT NULL,
    utc REAL NOT NULL,
    lat REAL NOT NULL,
    lon REAL NOT NULL,
    u REAL NOT NULL,
    v REAL NOT NULL,
    leg INTEGER NOT NULL,
    source TEXT NOT NULL,
    row INTEGER,
    col INTEGER,
    boot INTEGER NOT NULL DEFAULT 0,
    gap_ms INTEGER,
    UNIQUE (source, boot, time_boot_ms)
);
CREATE INDEX IF NOT EXISTS samples_leg ON samples (leg);
"""

_SCHEMA_VERSION = 2


def _ident(path: Path) -> tuple[int, int] | None:
    """(device, inode) of ``path``, None when nothing is there."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _row_values(s: Sample) -> tuple:
    for name in ("utc", "lat", "lon", "u", "v"):
        x = getattr(s, name)
        if not isinstance(x, (int, float)) or not math.isfinite(x):
            raise SampleStoreError(f"sample {name} must be a finite number, got {x!r}")
    return (
        int(s.time_boot_ms),
        float(s.utc),
        float(s.lat),
        float(s.lon),
        float(s.u),
        float(s.v),
        int(s.leg),
        str(s.source),
        None if s.row is None else int(s.row),
        None if s.col is None else int(s.col),
        int(s.boot),
        None if s.gap_ms is None else int(s.gap_ms),
    )


class SampleStore:
    """Append-only SQLite store of :class:`Sample` records (see module docstring).

    Args:
        path: the database file (created with its table if absent).
        readonly: open without creating or changing anything (for reports).
    """

    def __init__(self, path: str | Path, *, readonly: bool = False):
        self.path = Path(path)
        self.readonly = readonly
        self._lock = threading.RLock()
        try:
            if readonly:
                if not self.path.exists():
                    raise SampleStoreError(f"sample store not found: {self.path}")
                self._con = sqlite3.connect(
                    f"{self.path.resolve().as_uri()}?mode=ro", uri=True, check_same_thread=False, isolation_level=None
                )
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                # autocommit mode: every statement outside an explicit BEGIN is its own committed transaction
                self._con = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None, timeout=10.0)
                self._con.execute("PRAGMA mmap_size=0")  # read(), no memory map: see the module docstring
                self._con.execute("PRAGMA journal_mode=WAL")
                self._con.execute("PRAGMA synchronous=FULL")
                self._con.executescript(_SCHEMA)
                if "gap_ms" not in self._table_columns():  # a version-1 store (CREATE IF NOT EXISTS kept it)
                    self._con.execute("ALTER TABLE samples ADD COLUMN gap_ms INTEGER")
                self._con.execute(f"PRAGMA user_version={_SCHEMA_VERSION}")
            # fail now, with the file's name, if it is not a sample store
            self._con.execute("SELECT time_boot_ms, utc, lat, lon, u, v, leg, source FROM samples LIMIT 1").fetchall()
            have = self._table_columns()
            self._select_cols = ", ".join(c if c in have else f"NULL AS {c}" for c in _COLUMNS)
        except sqlite3.DatabaseError as exc:
            raise SampleStoreError(f"{self.path} is not a readable sample store: {exc}") from None
        #: (device, inode) of the file opened for writing: :meth:`check_file` finds it removed or replaced
        self._ident = None if readonly else _ident(self.path)

    def check_file(self) -> None:
        """Raise :class:`StoreUnwritable` when a write would fail or land nowhere: the file removed or replaced
        (another inode at the path: the open connection would go on writing the old one), its file system
        read-only, the file not writable, or less than :data:`MIN_FREE_BYTES` free."""
        if self._ident is None:
            return
        now = _ident(self.path)
        if now != self._ident:
            raise StoreUnwritable(f"{'store removed' if now is None else 'store replaced'}: {self.path}")
        try:
            st = os.statvfs(self.path)
        except OSError as exc:
            raise StoreUnwritable(write_fault(exc, self.path)) from exc
        if st.f_flag & os.ST_RDONLY:
            raise StoreUnwritable(f"file system read-only: {self.path}")
        if not os.access(self.path, os.W_OK):
            raise StoreUnwritable(f"store not writable: {self.path}")
        if st.f_blocks and st.f_bavail * st.f_frsize < MIN_FREE_BYTES:  # (f_blocks 0: a file system that tells none)
            raise StoreUnwritable(f"disk full: {self.path} ({st.f_bavail * st.f_frsize // 1024} KiB free)")

    def _table_columns(self) -> set[str]:
        return {r[1] for r in self._con.execute("PRAGMA table_info(samples)").fetchall()}

    # -- writing ---------------------------------------------------------------
    def append(self, sample: Sample | Mapping[str, Any] | None = None, /, **kw: Any) -> bool:
        """Store one sample (a :class:`Sample`, a mapping, or keyword fields); committed on return.

        Returns True if it was new, False if the same ``(source, boot,
        time_boot_ms)`` was already stored (the stored row is kept).
        """
        s = Sample.coerce(kw if sample is None else sample)
        vals = _row_values(s)
        with self._lock:
            cur = self._execute(
                f"INSERT OR IGNORE INTO samples ({', '.join(_COLUMNS)}) VALUES ({', '.join('?' * len(_COLUMNS))})", vals
            )
            return cur.rowcount == 1

    def append_many(self, samples: Iterable[Sample | Mapping[str, Any]]) -> int:
        """Store several samples in one transaction (all or none); returns how many were new."""
        rows = [_row_values(Sample.coerce(s)) for s in samples]
        with self._lock:
            before = self._con.total_changes
            try:
                self._execute("BEGIN IMMEDIATE")
                self._con.executemany(
                    f"INSERT OR IGNORE INTO samples ({', '.join(_COLUMNS)}) VALUES ({', '.join('?' * len(_COLUMNS))})",
                    rows,
                )
                self._execute("COMMIT")
            except BaseException as exc:
                if self._con.in_transaction:
                    try:
                        self._con.execute("ROLLBACK")
                    except sqlite3.Error:  # (a full disk may refuse that too: the transaction is lost either way)
                        log.debug("rollback after a failed write failed too")
                if isinstance(exc, (OSError, sqlite3.OperationalError, sqlite3.DatabaseError)):
                    raise StoreUnwritable(write_fault(exc, self.path)) from exc
                raise
            return self._con.total_changes - before

    def _execute(self, sql: str, params: tuple = ()):
        if self.readonly and not sql.lstrip().upper().startswith("SELECT"):
            raise SampleStoreError(f"sample store {self.path} was opened read-only")
        try:
            return self._con.execute(sql, params)
        except sqlite3.ProgrammingError as exc:  # closed store
            raise SampleStoreError(f"sample store {self.path}: {exc}") from None

    # -- reading ---------------------------------------------------------------
    def _select(self, where: str = "", params: tuple = ()) -> list[Sample]:
        with self._lock:
            rows = self._execute(f"SELECT {self._select_cols} FROM samples {where} ORDER BY id", params).fetchall()
        return [Sample(*r) for r in rows]

    def all(self) -> list[Sample]:
        """Every stored sample, in arrival order."""
        return self._select()

    def since(self, last_id: int) -> list[tuple[int, Sample]]:
        """``(id, sample)`` of the samples stored after row ``last_id`` (0: all), in arrival order: a
        reader following a store that is still being written (the live view)."""
        with self._lock:
            rows = self._execute(
                f"SELECT id, {self._select_cols} FROM samples WHERE id > ? ORDER BY id", (int(last_id),)
            ).fetchall()
        return [(int(r[0]), Sample(*r[1:])) for r in rows]

    def for_leg(self, leg: int) -> list[Sample]:
        """The samples of leg ``leg`` (-1: those taken outside any leg), in arrival order."""
        return self._select("WHERE leg = ?", (int(leg),))

    def count(self, leg: int | None = None) -> int:
        """Number of stored samples (of one leg if ``leg`` is given)."""
        with self._lock:
            if leg is None:
                return int(self._execute("SELECT COUNT(*) FROM samples").fetchone()[0])
            return int(self._execute("SELECT COUNT(*) FROM samples WHERE leg = ?", (int(leg),)).fetchone()[0])

    def __len__(self) -> int:
        return self.count()

    # -- lifetime ----------------------------------------------------------------
    def close(self) -> None:
        """Close the connection (idempotent). Committed samples are already on disk."""
        with self._lock:
            try:
                self._con.close()
            except sqlite3.Error:  # pragma: no cover - closing twice is harmless
                pass

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SampleStore({str(self.path)!r})"
