"""The run directory: everything one mission run leaves on disk, in one place.

Layout (``RunDir(root)``)::

    ROOT/
      mission.yaml            the mission file as run (copied at start)       .mission_file
      flight.tlog             every MAVLink frame sent/received, pymavlink    .tlog
                              tlog format (8-byte big-endian µs UTC + frame),
                              readable by MAVExplorer / mavlogdump
      flight_boatN.tlog       a fleet run: one telemetry log per boat N       .boat_tlog(N)
                              (0-based; leg records then name their "boat")
      samples.sqlite          the crash-safe sample store (SQLite, WAL)       .samples_db
      summary.json            written at the end (and updated after each      .summary_file
                              leg); absent while the first leg is running
      legs/NNN/               one folder per leg, NNN = 000, 001, ...         .leg_dir(i)
          leg.json            the leg record (start cell, planned path,       .leg_file(i)
                              waypoints, t_start/t_end in field time,
                              planning_s/upload_s/duration_s, link, RMSE)
          path.json           planned grid path [[row, col], ...]             .path_file(i)
          mission.waypoints   the uploaded mission, WPL 110                   .waypoints_file(i)
          mission.plan        the uploaded mission, QGroundControl .plan      .plan_file(i)
          estimate.nc         the GP reconstruction after this leg (NetCDF)   .estimate_file(i)
          prediction.nc       the model forecast used to plan this leg        .prediction_file(i)
          timings.json        planning / upload / leg wall times (s)          .timings_file(i)
      report/                 written by ``passt-mav report``                 .report_dir

``summary.json`` keys read by the report (all optional): ``mission``, ``status``
(``complete``/``aborted``/...), ``started_utc``, ``finished_utc`` (ISO-8601),
``field`` (``builtin:NAME`` or a ``.nc`` path, absolute or relative to ROOT),
``field_time_origin``, ``grid`` (``RegionGrid.describe()``), ``model``,
``planner``, ``reward``, ``seeds``, ``legs`` (list of leg records as in
``leg.json``), ``n_samples``, ``rmse`` ``{"t": [...], "passt": [...], "model":
[...]}`` (field time; None = not evaluated) and ``pod`` ``{"truth"|"passt"|"model":
[cumulative energy fraction of modes 1..k]}``.

``leg.json`` and ``summary.json`` carry ``schema_version`` (:data:`SCHEMA_VERSION`); their schema, and the
one reader of a run's records, is :mod:`passt_mav.runs.records`.

JSON files are written atomically (temporary file, fsync, rename): a crash
leaves either the old or the new file, never half of one.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

from passt_mav.errors import UserError

__all__ = ["RunDir", "RunDirError", "SCHEMA_VERSION", "read_json", "write_json_atomic"]

#: the version of the record schema (:mod:`passt_mav.runs.records`) the writers follow: every leg.json,
#: summary.json and events.jsonl line carries it as ``schema_version``
SCHEMA_VERSION = 1


class RunDirError(UserError):
    """A run directory is missing, not a run directory, or holds an unreadable file."""


_LEG_RE = re.compile(r"^\d{3,}$")


def write_json_atomic(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically (old or new content after any crash)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(obj, f, indent=2, allow_nan=False, default=_json_default)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _versioned(record: dict[str, Any]) -> dict[str, Any]:
    """A copy of ``record`` whose first key is ``schema_version`` (:data:`SCHEMA_VERSION`): what the writer follows
    now, whatever the record held before."""
    return {"schema_version": SCHEMA_VERSION, **{k: v for k, v in record.items() if k != "schema_version"}}


def _json_default(x: Any) -> Any:
    # numpy scalars and arrays appear in leg records; convert without importing numpy here
    if hasattr(x, "tolist"):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


def read_json(path: Path) -> Any:
    """The JSON value in ``path``; :class:`RunDirError` when it is missing, unreadable or not JSON."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise RunDirError(f"{path} not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RunDirError(f"{path} is not valid JSON: {exc}") from None
    except RecursionError:
        raise RunDirError(f"{path} is not valid JSON: nested too deep") from None
    except OSError as exc:
        raise RunDirError(f"cannot read {path}: {exc.strerror or exc}") from None


class RunDir:
    """Paths and small readers/writers of one run directory (layout in the module docstring).

    ``RunDir(root)`` only names the directory; :meth:`create` makes it.
    """

    MISSION = "mission.yaml"
    TLOG = "flight.tlog"
    SAMPLES = "samples.sqlite"
    SUMMARY = "summary.json"
    LEGS = "legs"
    REPORT = "report"

    def __init__(self, root: str | Path):
        self.root = Path(root)

    # -- creation / checks -------------------------------------------------------
    def create(self) -> RunDir:
        """Make the directory (and ``legs/``); returns self. An existing run directory is reused."""
        if self.root.exists() and not self.root.is_dir():
            raise RunDirError(f"{self.root} exists and is not a directory")
        (self.root / self.LEGS).mkdir(parents=True, exist_ok=True)
        return self

    def create_fresh(self) -> RunDir:
        """:meth:`create` for a new run: a directory that already holds a run is refused (its sample
        store would take the new run's samples beside the old ones, and both runs' legs would count
        them), with one line that says what to do instead."""
        if self.is_run_dir():
            raise RunDirError(
                f"{self.root} already holds a run; choose another --out (or continue that run with passt-mav run "
                f"MISSION --out {self.root} --resume)"
            )
        return self.create()

    @classmethod
    def new(cls, parent: str | Path, name: str = "run", *, utc: str | None = None) -> RunDir:
        """A fresh run directory ``PARENT/YYYY-MM-DDTHH-MM-SSZ_NAME`` (suffix ``_2``, ``_3`` if taken)."""
        import datetime as _dt

        stamp = utc or _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H-%M-%SZ")
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip("-") or "run"
        base = Path(parent) / f"{stamp}_{safe}"
        cand, k = base, 1
        while cand.exists():
            k += 1
            cand = base.with_name(f"{base.name}_{k}")
        return cls(cand).create()

    def is_run_dir(self) -> bool:
        """True if the directory holds anything a run writes (summary, legs, samples, tlog, mission)."""
        if not self.root.is_dir():
            return False
        if any(p.exists() for p in (self.summary_file, self.samples_db, self.tlog, self.mission_file)):
            return True
        if self.boat_tlogs():
            return True
        return bool(self.leg_indices()) or (self.root / self.LEGS).is_dir()

    # -- top-level paths -----------------------------------------------------------
    @property
    def mission_file(self) -> Path:
        return self.root / self.MISSION

    @property
    def tlog(self) -> Path:
        return self.root / self.TLOG

    def boat_tlog(self, boat: int) -> Path:
        """The telemetry log of boat ``boat`` (0-based) of a fleet run: ``flight_boatN.tlog``."""
        return self.root / f"flight_boat{int(boat)}.tlog"

    def boat_tlogs(self) -> list[Path]:
        """Every boat's telemetry log of a fleet run, in boat order (empty for a one-boat run)."""
        return sorted(self.root.glob("flight_boat*.tlog"), key=lambda p: int(p.stem[len("flight_boat") :] or 0))

    @property
    def samples_db(self) -> Path:
        return self.root / self.SAMPLES

    @property
    def summary_file(self) -> Path:
        return self.root / self.SUMMARY

    @property
    def report_dir(self) -> Path:
        return self.root / self.REPORT

    @property
    def legs_dir(self) -> Path:
        return self.root / self.LEGS

    # -- legs ------------------------------------------------------------------------
    def leg_dir(self, i: int, *, create: bool = True) -> Path:
        """``legs/NNN`` of leg ``i`` (created unless ``create=False``)."""
        if int(i) != i or i < 0:
            raise RunDirError(f"leg index must be a non-negative integer, got {i!r}")
        d = self.legs_dir / f"{int(i):03d}"
        if create:
            d.mkdir(parents=True, exist_ok=True)
        return d

    def leg_indices(self) -> list[int]:
        """Indices of the leg folders present, ascending."""
        if not self.legs_dir.is_dir():
            return []
        return sorted(int(p.name) for p in self.legs_dir.iterdir() if p.is_dir() and _LEG_RE.match(p.name))

    def leg_file(self, i: int) -> Path:
        return self.leg_dir(i, create=False) / "leg.json"

    def path_file(self, i: int) -> Path:
        return self.leg_dir(i, create=False) / "path.json"

    def waypoints_file(self, i: int) -> Path:
        return self.leg_dir(i, create=False) / "mission.waypoints"

    def plan_file(self, i: int) -> Path:
        return self.leg_dir(i, create=False) / "mission.plan"

    def estimate_file(self, i: int) -> Path:
        """The reconstruction (GP estimate) after leg ``i``, NetCDF."""
        return self.leg_dir(i, create=False) / "estimate.nc"

    def prediction_file(self, i: int) -> Path:
        """The model forecast leg ``i`` was planned on, NetCDF."""
        return self.leg_dir(i, create=False) / "prediction.nc"

    def timings_file(self, i: int) -> Path:
        return self.leg_dir(i, create=False) / "timings.json"

    def write_leg(self, i: int, record: dict[str, Any]) -> Path:
        """Write the leg record ``legs/NNN/leg.json`` (atomic, with ``schema_version``); also ``path.json`` if it
        has a ``path``."""
        d = self.leg_dir(i)
        rec = _versioned(record)
        rec.setdefault("index", int(i))
        if "path" in rec:
            write_json_atomic(d / "path.json", rec["path"])
        return write_json_atomic(d / "leg.json", rec)

    def read_leg(self, i: int) -> dict[str, Any]:
        """The leg record of leg ``i`` (raises :class:`RunDirError` if absent or invalid)."""
        rec = read_json(self.leg_file(i))
        if not isinstance(rec, dict):
            raise RunDirError(f"{self.leg_file(i)} does not hold a leg record (a JSON object)")
        return rec

    def read_legs(self) -> list[dict[str, Any]]:
        """All leg records found under ``legs/`` (folders without ``leg.json`` are skipped)."""
        return [self.read_leg(i) for i in self.leg_indices() if self.leg_file(i).exists()]

    def write_timings(self, i: int, timings: dict[str, float]) -> Path:
        return write_json_atomic(self.timings_file(i), timings)

    # -- summary -----------------------------------------------------------------------
    def write_summary(self, summary: dict[str, Any]) -> Path:
        """Write ``summary.json`` atomically, with ``schema_version``."""
        self.root.mkdir(parents=True, exist_ok=True)
        return write_json_atomic(self.summary_file, _versioned(summary))

    def read_summary(self) -> dict[str, Any]:
        """``summary.json`` as a dict (raises :class:`RunDirError` if absent or not a JSON object)."""
        s = read_json(self.summary_file)
        if not isinstance(s, dict):
            raise RunDirError(f"{self.summary_file} does not hold a JSON object")
        return s

    def __repr__(self) -> str:
        return f"RunDir({str(self.root)!r})"
