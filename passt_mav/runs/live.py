"""What a running mission writes for a live view: events, per-boat status, the view's metadata.

One :class:`RecordWriter` per run (a fleet's boats share it through :meth:`RecordWriter.for_boat`)
writes, beside the run directory's other files::

    ROOT/events.jsonl         append-only, one JSON object a line: schema_version, utc (ISO-8601),
                              field_time (None when the vehicle's clock is not known), boat, kind,
                              level, text (schema: passt_mav.runs.records.EventRecord)         EVENTS
    ROOT/live/meta.json       written once at start: grid, land mask, geofence margin, boats, legs,
                              the model's skill warning (anything the page needs that no other file has)
    ROOT/live/boat_K.json     boat K's status, rewritten atomically about once a second: lat, lon,
                              heading_deg (true), mode, armed, link RTT ms and loss %, leg k of n,
                              samples this leg, time to the leg's end (vehicle s)

``kind`` is one of :data:`KINDS`. Nothing here may stop a mission: every write logs its failure
and returns (a full disk loses the view, not the boat). The view (:mod:`passt_mav.view`) only reads
these files, so a crashed view never touches the mission, and a finished run can be reopened.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from passt_mav.runs.rundir import SCHEMA_VERSION

__all__ = ["RecordWriter", "KINDS", "EVENTS", "read_events", "read_jsonl", "read_statuses"]

log = logging.getLogger(__name__)

EVENTS = "events.jsonl"
LIVE = "live"

#: event kind -> level (the page shows "alert" and "warn" as banners; "ok" closes one)
KINDS = {
    "run_start": "info",
    "run_end": "info",
    "leg_start": "info",
    "leg_end": "info",
    "link_lost": "alert",
    "link_back": "ok",
    "pilot_takeover": "alert",
    "pilot_released": "ok",
    "reboot": "alert",
    "reboot_recovered": "ok",
    "fence_refused": "alert",
    "boat_dropped": "alert",
    "boat_back": "ok",
    "mission_replaced": "warn",
    "warning": "warn",
    "guard": "warn",
    "stopped": "alert",
    "command": "info",
    "budget": "alert",
    "fence_breach": "alert",
    "fence_clear": "ok",
    "vehicle_alert": "alert",
    "approval": "warn",
    "boat_end": "info",
}


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class RecordWriter:
    """Writes the live-view files of the run in ``root`` (module docstring); never raises.

    ``field_time``: a callable giving the field time now (None = unknown), set by the controller.
    """

    def __init__(self, root: str | Path, *, boat: int = 0, _shared: dict | None = None):
        self.root = Path(root)
        self.boat = int(boat)
        self.field_time: Callable[[], float | None] = lambda: None
        self._shared: dict[str, Any] = _shared if _shared is not None else {"lock": threading.Lock()}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def for_boat(self, boat: int) -> RecordWriter:
        """The writer of boat ``boat`` of a fleet: the same files, events tagged with its number."""
        return RecordWriter(self.root, boat=boat, _shared=self._shared)

    # -- files -----------------------------------------------------------------------------------
    def _guard(self, what: str, fn: Callable[[], Any]) -> None:
        failed = self._shared.setdefault("failed", set())  # files the machine refused (a full disk): said once
        try:
            fn()
        except OSError as exc:  # the machine's fault, not the code's: one line, once, until a write succeeds
            if what not in failed:
                failed.add(what)
                log.warning("live view: could not write %s (%s); the mission goes on", what, exc.strerror or exc)
        except Exception:  # noqa: BLE001 - the view's files must never stop a mission
            log.warning("live view: could not write %s", what, exc_info=True)
        else:
            failed.discard(what)

    def meta(self, info: dict[str, Any]) -> None:
        """``live/meta.json`` (atomic)."""
        from passt_mav.runs.rundir import write_json_atomic

        self._guard("live/meta.json", lambda: write_json_atomic(self.root / LIVE / "meta.json", info))

    def event(
        self, kind: str, text: str, *, level: str | None = None, boat: int | None = None, command_id: str | None = None
    ) -> None:
        """One line of ``events.jsonl`` (appended and flushed under a lock shared by the fleet); ``command_id``:
        the operator's command this event answers (:mod:`passt_mav.runs.commands`)."""

        def write():
            try:
                t = self.field_time()
            except Exception:  # noqa: BLE001 - a clock not ready yet
                t = None
            rec = {
                "schema_version": SCHEMA_VERSION,
                "utc": _utc_now(),
                "field_time": t,
                "boat": self.boat if boat is None else int(boat),
                "kind": kind,
                "level": level or KINDS.get(kind, "info"),
                "text": text,
            }
            if command_id is not None:
                rec["command_id"] = command_id
            line = json.dumps(rec, default=float) + "\n"
            with self._shared["lock"]:
                self.root.mkdir(parents=True, exist_ok=True)
                with open(self.root / EVENTS, "a") as f:
                    f.write(line)

        self._guard(EVENTS, write)

    def status(self, fields: dict[str, Any]) -> None:
        """``live/boat_K.json`` (atomic), with the time it was written."""
        from passt_mav.runs.rundir import write_json_atomic

        rec = {"boat": self.boat, "utc": _utc_now(), **fields}
        self._guard(
            f"live/boat_{self.boat}.json", lambda: write_json_atomic(self.root / LIVE / f"boat_{self.boat}.json", rec)
        )

    # -- the status thread -------------------------------------------------------------------------
    def start_status(self, fn: Callable[[], dict[str, Any]], period_s: float = 1.0) -> None:
        """Call ``fn`` every ``period_s`` in a thread of its own and write what it returns as the status."""
        self.stop_status()
        self._stop = threading.Event()

        def loop():
            while True:
                self._write_from(fn)
                if self._stop.wait(period_s):
                    return

        self._thread = threading.Thread(target=loop, name=f"live-status-{self.boat}", daemon=True)
        self._thread.start()

    def _write_from(self, fn: Callable[[], dict[str, Any]]) -> None:
        try:
            fields = fn()
        except Exception:  # noqa: BLE001 - a status that cannot be read now is tried again in a second
            log.debug("live view: no status now", exc_info=True)
            return
        self.status(fields)

    def stop_status(self, last: Callable[[], dict[str, Any]] | None = None) -> None:
        """Stop the status thread (after writing ``last()`` once more, when given)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if last is not None:
            self._write_from(last)


# -- readers (the view) ----------------------------------------------------------------------------
def read_jsonl(path: str | Path, offset: int = 0) -> tuple[list, int]:
    """(the JSON values of the lines after byte ``offset`` of ``path``, the new offset); a half-written last
    line waits for its newline, a line that is not JSON is skipped (logged), a missing file is empty."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read()
    except FileNotFoundError:
        return [], offset
    end = data.rfind(b"\n") + 1
    out = []
    for line in data[:end].splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            log.warning("live view: skipped a bad line of %s", path)
    return out, offset + end


def read_events(root: str | Path, offset: int = 0) -> tuple[list[dict], int]:
    """(events after byte ``offset`` of ``events.jsonl``, the new offset); a half-written last line waits."""
    return read_jsonl(Path(root) / EVENTS, offset)


def read_meta(root: str | Path) -> dict | None:
    """``live/meta.json`` (written once at the run's start), or None when it is missing or unreadable."""
    try:
        m = json.loads((Path(root) / LIVE / "meta.json").read_text())
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) else None


def read_statuses(root: str | Path) -> dict[int, dict]:
    """``{boat: status}`` from ``live/boat_K.json`` (files that cannot be read are left out)."""
    out = {}
    for p in sorted((Path(root) / LIVE).glob("boat_*.json")):
        try:
            rec = json.loads(p.read_text())
            out[int(rec.get("boat", p.stem.split("_")[1]))] = rec
        except (OSError, ValueError):
            continue
    return out
