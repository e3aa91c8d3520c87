"""The machine's faults are not the boat's: a full disk, a read-only or vanished sample store, a telemetry log
that cannot be written (docs/resilience.md, "The machine's faults").

None of them touches the link or the boat's mission by itself. The telemetry log's lost frames are counted by
the link (:attr:`~passt_mav.mavlink.Link.tlog_lost`) and said once at the run's end; the run flies on. A sample
store the machine fails (:class:`~passt_mav.runs.store_guard.StoreGuard`, the store writer's ``guard``) stops
the run: the controller checks it between its steps (:func:`check_store`: each turn of a flying leg and around
each leg; a leg's own file the disk refuses too: :func:`disk_fault`) and stops as a paused run does (the boat
to its ``vehicle.wait_mode``: LOITER, or HOLD), with status ``stopped`` and ``stopped_by`` the one line of what
failed (:func:`stop_for_store`); the readings it could not store are kept (memory, a spare file named in that
line); ``--resume`` imports the spare file (:func:`import_kept`). A summary.json the full disk refuses is
written beside the spare file instead (:func:`summary_or_spare`), and one line names it.

Functions of a :class:`~passt_mav.vehicle.controller.MissionController` ``ctl`` (its ``writer``, ``link``,
``journal``, ``rd``), so the controller class itself stays at its size.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Callable

from passt_mav.vehicle.flow import MachineFault, utc_now

__all__ = [
    "check_store",
    "disk_fault",
    "stop_for_store",
    "machine_faults_record",
    "say_tlog_loss",
    "import_kept",
    "summary_or_spare",
]

log = logging.getLogger(__name__)


def check_store(guard) -> None:
    """:class:`~passt_mav.vehicle.flow.MachineFault` once ``guard`` (a StoreGuard, or None) says the store failed."""
    if guard is not None and guard.reason is not None:
        raise MachineFault(guard.reason)


def disk_fault(exc: OSError) -> None:
    """:class:`~passt_mav.vehicle.flow.MachineFault` when ``exc`` (a run file's write that failed: leg.json,
    estimate.nc) is the disk's fault (full, read-only, I/O error); else nothing (the caller re-raises ``exc``)."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO):
        from passt_mav.runs.store import write_fault

        raise MachineFault(write_fault(exc, exc.filename or "a run file")) from exc


def stop_for_store(ctl, exc: MachineFault) -> None:
    """Controller ``ctl`` stops for a failed store (or a run file the disk refused): status ``stopped``,
    ``stopped_by`` what failed, one line and an event naming where the readings are (the caller then keeps the
    boat on station)."""
    guard = getattr(ctl.writer, "guard", None)
    ctl.status, ctl.stopped_by = "stopped", exc.reason
    where = "" if guard is None or guard.reason is None else f"; {guard.where()}"
    text = (
        f"stopped: {exc.reason}{where}; the boat waits in {ctl.vehicle.wait_mode}; free the disk (or put the store "
        "back), then continue with --resume"
    )
    ctl.journal.note("stopped", f"stopped at {utc_now()}: {exc.reason}{where}")
    ctl.journal.say(text)


def machine_faults_record(ctl) -> dict | None:
    """summary.json's ``machine_faults``: ``store`` (:meth:`StoreGuard.record`) and ``tlog`` (the link's
    :attr:`~passt_mav.mavlink.Link.tlog_lost`); None when the machine failed nothing."""
    guard = getattr(getattr(ctl, "writer", None), "guard", None)
    store = None if guard is None else guard.record()
    tlog = getattr(ctl.link, "tlog_lost", None)
    if store is None and not tlog:
        return None
    return {"store": store, "tlog": tlog or None}


def say_tlog_loss(ctl) -> None:
    """At the run's end: one line and an event when the telemetry log lost frames (the run itself flew on)."""
    lost = getattr(ctl.link, "tlog_lost", None)
    if not lost:
        return
    text = (
        f"telemetry log: {lost['frames']} messages ({lost['bytes']} bytes) not logged ({lost['error']}); "
        "the link and the run went on, the samples are in the store"
    )
    ctl.journal.note("warning", text)
    ctl.journal.say(f"WARNING: {text}")


def import_kept(ctl) -> None:
    """``--resume``: the readings a failed store left in the run's spare file
    (:func:`~passt_mav.runs.store_guard.spare_folder`) into the store again; one line says how many."""
    from passt_mav.runs.store_guard import SPARE_NAME, import_spare, spare_folder

    spare = spare_folder(ctl.store.path) / SPARE_NAME
    if not spare.exists():
        return
    n = import_spare(ctl.store, spare)
    ctl.journal.say(f"resuming: {n} readings the failed store missed imported from {spare}")
    ctl.journal.events.append(f"resumed: {n} readings imported from {spare} at {utc_now()}")


def summary_or_spare(ctl, write: Callable[[], None]) -> Callable[[], None]:
    """``write`` (controller ``ctl``'s summary writer), which on a machine's fault (OSError: a full disk) writes
    the summary into the run's spare folder (:func:`~passt_mav.runs.store_guard.spare_folder`) instead, said once."""
    from passt_mav.runs.rundir import write_json_atomic
    from passt_mav.runs.store_guard import spare_folder

    said: list[object] = []

    def write_or_spare() -> None:
        try:
            write()
        except OSError as exc:
            path = write_json_atomic(spare_folder(ctl.rd.samples_db, make=True) / "summary.json", ctl.summary())
            if not said:
                said.append(path)
                ctl.journal.say(f"summary.json not written ({exc.strerror or exc}): written to {path} instead")

    return write_or_spare
