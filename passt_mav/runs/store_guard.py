"""The readings a run keeps when the machine fails its sample store (docs/resilience.md, "The machine's faults").

:class:`StoreGuard` stands between the controller's store writer and the :class:`~passt_mav.runs.store.SampleStore`.
Before each write it checks the file (:meth:`SampleStore.check_file`); a write the machine refuses (a full disk,
a read-only file system, the file removed or replaced: :class:`~passt_mav.runs.store.StoreUnwritable`, or the
OSError/sqlite3 error under it) is never retried into a store that may now hold it nowhere. From then on:

* :attr:`StoreGuard.reason` says what failed in one line (``disk full: /run/x/samples.sqlite``): the controller
  reads it between its steps and stops the run (status ``stopped``, ``stopped_by`` that line);
* every reading of the failed batch and after it is kept in memory (:attr:`StoreGuard.kept`) and appended to a
  spare file, one JSON object a line with the store's fields, in the run's spare folder under the system's temp
  dir (:func:`spare_folder`: ``passt-mav-RUN-HASH``, one per run directory; another disk than the run's, most of
  the time); when the store file was removed or replaced, the readings the open connection still reads from the
  old file are rescued into it first;
* ``--resume`` with the store writable again finds the spare file there (the run's summary.json may be the one
  the full disk refused) and imports it (:func:`import_spare`): the readings lost to the store are flown with.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import sqlite3
import tempfile
from pathlib import Path

from passt_mav.runs.store import Sample, SampleStore, StoreUnwritable, write_fault

__all__ = ["StoreGuard", "import_spare", "spare_folder", "SPARE_NAME"]

log = logging.getLogger(__name__)

#: the spare file's name in :func:`spare_folder`
SPARE_NAME = "samples-unsaved.jsonl"


def spare_folder(store_path: str | Path, *, make: bool = False) -> Path:
    """The run's spare folder: ``passt-mav-RUN-HASH`` under the system's temp dir (RUN: the run directory's name,
    HASH: of its absolute path), the same for every session of the run. ``make``: create it (private to this
    user; a folder of that name owned by someone else gives way to a new one of a random name)."""
    run = Path(store_path).absolute().parent
    tag = hashlib.sha1(str(run).encode()).hexdigest()[:10]
    folder = Path(tempfile.gettempdir()) / f"passt-mav-{run.name}-{tag}"
    if make:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        if folder.stat().st_uid != os.getuid():
            folder = Path(tempfile.mkdtemp(prefix=f"passt-mav-{run.name}-"))
    return folder


class StoreGuard:
    """Appends to ``store``, keeping the readings when the machine fails it (module docstring). ``spare_dir``:
    the folder of the spare file (default: the run's :func:`spare_folder`)."""

    def __init__(self, store: SampleStore, *, spare_dir: str | Path | None = None):
        self.store = store
        self.spare_dir = spare_dir
        #: one line saying what failed (``disk full: PATH``), None while the store takes every write
        self.reason: str | None = None
        #: the readings not in the store (the store's fields, as dicts), oldest first
        self.kept: list[dict] = []
        #: readings rescued from a removed or replaced store file (in :attr:`kept` too)
        self.rescued = 0
        #: the spare file (JSON lines), None until the store failed or when it could not be written either
        self.spare: Path | None = None
        self.spare_error: str | None = None

    def append_many(self, rows: list[dict]) -> int:
        """Store ``rows`` (dicts of :class:`Sample`'s fields); returns how many were new. Once the store failed,
        they are kept (memory, spare file) instead, and 0 is returned."""
        if self.reason is None:
            try:
                self.store.check_file()
                return self.store.append_many(rows)
            except (StoreUnwritable, OSError, sqlite3.Error) as exc:
                self._failed(exc)
        self._keep(rows)
        return 0

    def _failed(self, exc: BaseException) -> None:
        reason = exc.reason if isinstance(exc, StoreUnwritable) else write_fault(exc, self.store.path)
        try:
            folder = Path(self.spare_dir) if self.spare_dir is not None else spare_folder(self.store.path, make=True)
            folder.mkdir(parents=True, exist_ok=True)
            self.spare = folder / SPARE_NAME
        except OSError as e2:
            self.spare_error = f"{type(e2).__name__}: {e2}"
        if reason.startswith(("store removed", "store replaced")):
            try:  # the open connection still reads the old file: its readings are not lost yet
                old = [dataclasses.asdict(s) for s in self.store.all()]
            except Exception as e3:  # noqa: BLE001 - a rescue that fails leaves the readings after it
                log.debug("rescue from the removed store failed: %s", e3)
                old = []
            self.rescued = len(old)
            self._keep(old)
        log.debug("sample store failed: %s", reason)
        self.reason = reason  # last: whoever reads it finds the spare file named

    def _keep(self, rows: list[dict]) -> None:
        self.kept.extend(rows)
        if self.spare is None or not rows:
            return
        try:
            with open(self.spare, "a", encoding="utf-8") as f:
                f.writelines(json.dumps(r, default=float) + "\n" for r in rows)
        except OSError as exc:
            self.spare_error = f"{type(exc).__name__}: {exc}"
            self.spare = None
            log.debug("spare file not written: %s", exc)

    def where(self) -> str:
        """Where the readings not in the store are, in words (for the one line that says the store failed)."""
        n = len(self.kept)
        if self.spare is not None:
            return f"{n} readings kept in {self.spare}"
        return f"{n} readings kept in memory only (no spare file: {self.spare_error})"

    def record(self) -> dict | None:
        """summary.json's ``machine_faults.store``: None while the store takes every write."""
        if self.reason is None:
            return None
        return {
            "reason": self.reason,
            "readings_kept": len(self.kept),
            "rescued_from_old_file": self.rescued,
            "spare": None if self.spare is None else str(self.spare),
            "spare_error": self.spare_error,
        }


def import_spare(store: SampleStore, path: str | Path) -> int:
    """The readings of a spare file (:class:`StoreGuard`) into ``store``; returns how many were new (a reading
    already stored lands once: the store's key). The file is then renamed ``samples-imported-N.jsonl`` (kept,
    not imported again)."""
    path = Path(path)
    rows = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.strip():
                rows.append(Sample(**json.loads(line)))
    n = store.append_many(rows) if rows else 0
    k = 1
    while (done := path.with_name(f"samples-imported-{k}.jsonl")).exists():
        k += 1
    path.rename(done)
    return n
