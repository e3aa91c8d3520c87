"""Exports of a run directory for other tools: CF-1.8 NetCDF, GeoJSON, KML, CSV.

``passt-mav export RUN_DIR --format netcdf|geojson|kml|csv [--samples] [--out FILE]``;
in Python :func:`export_run`. The run is read, never changed; the file is written to a
temporary name beside ``FILE`` and renamed, so a failed export leaves nothing half-written.

NetCDF: two files, not one. CF's ``featureType`` is a global attribute that applies to
every data variable of a file, so one file cannot be both a gridded time series (no
featureType) and a discrete-sampling-geometry trajectory (``featureType = "trajectory"``)
without a checker (and readers like xarray or ncdump-based tools) misreading one of them; CF
1.8 groups would allow it but most readers, ``passt-mav data import`` included, open the root
group only. So:

* ``--format netcdf`` (default file ``estimate.nc``): the field estimate after each leg on the
  mission grid, ``u``/``v`` (CF ``eastward/northward_sea_water_velocity``, m s-1, east/north)
  with their GP posterior std ``u_std``/``v_std`` (standard-name modifier ``standard_error``),
  one time step per leg (the estimate's field time, ``leg`` and ``boat`` per step),
  ``lat``/``lon`` cell centres and a WGS84 ``crs`` grid mapping. ``passt-mav data import``
  reads it back (tested to 1e-6). A metric field (the cylinder CFD placed on the sea) keeps its
  data-frame ``x``/``y`` (m) with 2-D ``lat``/``lon`` auxiliary coordinates instead, with no standard
  name (they are data-frame components, not east/north). Speeds are in m s-1 wherever the run had a
  velocity scale (a mission always has one: the field times ``field.velocity_scale``,
  :mod:`passt_mav.units`); only a run that records none keeps the field's own units. ``rmse`` and
  ``rmse_model`` (per time step, m s-1) give the leg's RMSE against the true field, NaN where no truth
  was known.
* ``--format netcdf --samples`` (default ``samples.nc``): every stored sample as a CF DSG
  trajectory per boat (contiguous ragged array: ``rowSize`` per trajectory, ``trajectory``
  with ``cf_role = "trajectory_id"``), IOOS-style ``platform`` variable; ``u``/``v`` in m s-1.

Times: one clock for every file of a run, the field's (docs/clock.md). The estimate's time is
the field's time; for a field with a UTC origin (every geographic field) it is written as
``seconds since 1970-01-01T00:00:00Z``; a field without one (the cylinder: non-dimensional time)
gets ``field_time`` (units ``1``, no time axis) and says so. A sample's time is the field time the
loop gave it (the run's clock in summary.json, per boat for a fleet: ``t_boot0 + time_boot_ms /
1000 / time_scale``), as the field's UTC where the field has a UTC origin; the vehicle's own UTC of
the reading is kept beside it (``vehicle_utc``), never instead of it. A field without a UTC origin
keeps the vehicle's UTC as the samples' time axis and their ``field_time`` beside it; a run that
records no clock (no summary.json) has only the vehicle's UTC, and the files say so.

Global attributes: ``Conventions = "CF-1.8, ACDD-1.3"``, title, summary, source, history,
``date_created``, the mission, model, planner and reward, ``passt_mav_version`` and
``source_commit`` (the git commit of the installed checkout, ``"unknown"`` otherwise), and the
ACDD extents. GeoJSON / KML / CSV: :mod:`passt_mav.analysis.export_geo`.

What the std is: the GP's predictive standard deviation per cell (scikit-learn's convention, with
the sensor-noise variance in it: never below the fitted noise level, and equal to it everywhere when
the evidence gate found no signal beyond noise in the leg's samples, as on the demo's first legs);
the uncertainty of the GP's correction to the forecast, not of the model's forecast itself.

The posterior std: runs record it in ``legs/NNN/estimate.nc`` since this export exists (the
loop built by :func:`passt_mav.loop.legstep.build_loop` keeps it); an older run's estimate has none
and its export says so in the ``comment`` attribute instead of inventing one.
"""

from __future__ import annotations

import datetime as _dt
import os
import sqlite3
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from passt_mav.errors import UserError
from passt_mav.runs.records import RunRecords
from passt_mav.runs.rundir import RunDir, RunDirError
from passt_mav.units import MPS, SpeedUnit, run_speed_unit

__all__ = [
    "FORMATS",
    "ExportError",
    "RunData",
    "load_run",
    "export_run",
    "default_name",
    "source_commit",
    "estimate_dataset",
    "samples_dataset",
    "write_atomic",
]

#: formats of :func:`export_run`
FORMATS = ("netcdf", "geojson", "kml", "csv")
_EPOCH_UNITS = "seconds since 1970-01-01T00:00:00Z"
_STD_COMMENT = (
    "the GP's predictive standard deviation at the cell as the PASST loop computes it (scikit-learn's "
    "convention: it includes the sensor-noise (WhiteKernel) variance, so it never falls below the fitted "
    "noise level, which it equals everywhere when the leg's samples showed no signal beyond noise); it "
    "is the uncertainty of the GP's correction to the model forecast, not of the forecast itself"
)


class ExportError(UserError):
    """A run cannot be exported (nothing to export, unknown format, unwritable output)."""


@dataclass
class RunData:
    """What an export reads from a run directory.

    ``grid``: the mission's :class:`geo.RegionGrid` / ``MetricRegionGrid``; ``legs``: leg records
    (``leg.json``); ``samples``: :class:`~passt_mav.runs.store.Sample` list (arrival order);
    ``boat_of``: sample source -> boat index (0-based); ``mission``: the mission mapping as flown.
    """

    rd: RunDir
    summary: dict
    mission: dict
    grid: Any
    legs: list[dict]
    samples: list
    boat_of: dict[str, int] = field(default_factory=dict)
    damage: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return str(self.summary.get("mission") or self.mission.get("name") or self.rd.root.name)

    @property
    def margin_m(self) -> float:
        return float(self.mission.get("geofence_margin_m") or 0.0)

    @property
    def n_boats(self) -> int:
        return max([len(self.mission.get("vehicles") or [None])] + [b + 1 for b in self.boat_of.values()])


def load_run(run_dir: str | Path) -> RunData:
    """Read a run directory for export (RunDirError if it is not one)."""
    import yaml

    import geo
    from passt_mav.runs.store import SampleStore, SampleStoreError

    rd = RunDir(run_dir)
    if not rd.root.is_dir():
        raise RunDirError(f"run directory not found: {rd.root}")
    if not rd.is_run_dir():
        raise RunDirError(f"{rd.root} is not a run directory (no summary.json, mission.yaml, samples or legs)")
    recs = RunRecords(rd)
    summary = recs.summary_dict() or {}
    try:
        mission = yaml.safe_load(rd.mission_file.read_text()) if rd.mission_file.exists() else {}
    except yaml.YAMLError as exc:
        raise RunDirError(f"{rd.mission_file} is not valid YAML: {str(exc).splitlines()[0]}") from None
    mission = mission if isinstance(mission, dict) else {}
    grid = None
    if isinstance(summary.get("grid"), dict):
        grid = geo.grid_from_dict(summary["grid"])
    elif mission:
        from passt_mav.mission.config import validate_mission

        grid = validate_mission(mission, source=str(rd.mission_file), base_dir=rd.root).grid()
    if grid is None:
        raise RunDirError(f"{rd.root} records no grid (neither summary.json nor mission.yaml)")
    samples, damage = [], []
    if rd.samples_db.exists():
        try:
            with SampleStore(rd.samples_db, readonly=True) as st:
                samples = st.all()
        except (SampleStoreError, sqlite3.DatabaseError) as exc:
            samples, damage = _log_samples(rd, exc)
    legs = recs.leg_dicts()
    return RunData(rd, summary, mission, grid, legs, samples, _boats_of(samples, mission), damage)


def _log_samples(rd: RunDir, exc: BaseException) -> tuple[list, list[str]]:
    """A damaged store (``exc``): the samples of the run's telemetry log instead (legs as the log's windows
    place them), and what was lost, one phrase each."""
    from passt_mav.runs.tlog import read_tlog

    why = f"{rd.SAMPLES} unreadable ({str(exc).rsplit(': ', 1)[-1]})"
    if not rd.tlog.exists():
        return [], [why, f"no {rd.TLOG} to take the samples from"]
    try:
        return list(read_tlog(rd.tlog).samples), [f"{why}: the samples are the telemetry log's"]
    except UserError as exc2:
        return [], [why, f"{rd.TLOG} unreadable ({exc2})"]


def _boats_of(samples, mission: dict) -> dict[str, int]:
    """Sample source (``mav:SYSID/COMP``) -> boat index: a fleet's boat I is system id I+1 (vehicle-sim and
    SITL ``-I N``); a source that is not ``mav:`` or a one-boat run's only source is boat 0."""
    sources = sorted({s.source for s in samples})
    fleet = len(mission.get("vehicles") or []) > 1
    out: dict[str, int] = {}
    for k, src in enumerate(sources):
        sysid = None
        if src.startswith("mav:"):
            try:
                sysid = int(src[4:].split("/")[0])
            except ValueError:
                sysid = None
        out[src] = (sysid - 1) if (fleet and sysid) else (0 if len(sources) == 1 else k)
    return out


# -- common ----------------------------------------------------------------------------------
def source_commit() -> str:
    """The git commit of the installed passt_mav when it is a git checkout, else ``"unknown"``."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return "unknown"
    try:
        r = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    sha = r.stdout.strip()
    return sha if r.returncode == 0 and len(sha) == 40 else "unknown"


def _global_attrs(run: RunData, title: str, summary: str, command: str) -> dict[str, Any]:
    """CF/ACDD global attributes shared by both NetCDF files."""
    from passt_mav import __version__

    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    s = run.summary
    return {
        "Conventions": "CF-1.8, ACDD-1.3",
        "title": title,
        "summary": summary,
        "source": f"passt_mav {__version__} PASST mission controller (GP reconstruction of current samples "
        "taken by ArduPilot Rover boats over MAVLink)",
        "history": f"{now} {command}",
        "date_created": now,
        "institution": "unknown",
        "mission": run.name,
        "model": str(s.get("model") or run.mission.get("model") or "unknown"),
        "planner": str(s.get("planner") or (run.mission.get("planner") or {}).get("name") or "unknown"),
        "reward": str(s.get("reward") or (run.mission.get("planner") or {}).get("reward") or "unknown"),
        "run_status": str(s.get("status", "unknown")),
        "run_directory": run.rd.root.name,
        "passt_mav_version": __version__,
        "source_commit": source_commit(),
        "platform": "unmanned surface vehicle",
        "instrument": "current sensor (CUR_U/CUR_V over MAVLink NAMED_VALUE_FLOAT)",
    }


def _geo_extent(attrs: dict, lat: np.ndarray, lon: np.ndarray) -> None:
    lat, lon = np.asarray(lat, float), np.asarray(lon, float)
    if lat.size:
        attrs.update(
            geospatial_lat_min=float(np.nanmin(lat)),
            geospatial_lat_max=float(np.nanmax(lat)),
            geospatial_lon_min=float(np.nanmin(lon)),
            geospatial_lon_max=float(np.nanmax(lon)),
            geospatial_lat_units="degrees_north",
            geospatial_lon_units="degrees_east",
        )


def _time_extent(attrs: dict, epoch_s: np.ndarray) -> None:
    if epoch_s.size:
        iso = [
            _dt.datetime.fromtimestamp(float(x), _dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
            for x in (np.min(epoch_s), np.max(epoch_s))
        ]
        attrs.update(time_coverage_start=iso[0], time_coverage_end=iso[1])


def _epoch_of_field_times(origin: str | None, t: np.ndarray) -> np.ndarray | None:
    """Field times (s since ``origin``, ISO-8601 UTC) as UNIX epoch seconds; None without an origin."""
    if origin is None:
        return None
    from passt_mav.fields.field import parse_iso

    return parse_iso(origin).timestamp() + np.asarray(t, float)


# -- NetCDF: the gridded estimate ------------------------------------------------------------
def _estimates(run: RunData) -> tuple[list, list[dict], list[str]]:
    """(FlowField and std per kept estimate, their leg records, notes), in time order.

    Two estimates at the same field time (a fleet's boats finishing together) would repeat a
    value of the time coordinate, which CF forbids: the one absorbed last (it holds every
    sample of the other) is kept and the note names the other.
    """
    from passt_mav.fields.field import FlowField, load_std

    found = []
    by_index = {int(r.get("index", -1)): r for r in run.legs}
    for i in run.rd.leg_indices():
        p = run.rd.estimate_file(i)
        if p.exists():
            rec = by_index.get(i, {"index": i})
            order = (rec.get("fleet_seq") or {}).get("absorb")
            f = FlowField.from_netcdf(p)
            found.append((float(f.times[-1]), i if order is None else int(order), f, load_std(p), rec))
    found.sort(key=lambda x: (x[0], x[1]))
    kept, notes = [], []
    for item in found:
        if kept and item[0] == kept[-1][0]:
            notes.append(
                f"leg {int(kept[-1][4].get('index', -1)) + 1}'s estimate at the same time as leg "
                f"{int(item[4].get('index', -1)) + 1}'s is left out (the later is the fleet's newest "
                "estimate at that time)"
            )
            kept[-1] = item
        else:
            kept.append(item)
    return [(x[2], x[3]) for x in kept], [x[4] for x in kept], notes


def estimate_dataset(run: RunData, command: str = "passt-mav export"):
    """The CF-1.8 gridded estimate of a run as an ``xarray.Dataset`` (module docstring)."""
    import xarray as xr

    fields, recs, notes = _estimates(run)
    if not fields:
        raise ExportError(f"{run.rd.root} has no leg estimate (legs/NNN/estimate.nc): nothing to export as a grid")
    f0 = fields[0][0]
    data = np.concatenate([f.data for f, _ in fields]).astype(np.float32)
    t_field = np.array([float(f.times[-1]) for f, _ in fields])
    have_std = all(s is not None for _, s in fields)
    std = np.concatenate([s for _, s in fields]).astype(np.float32) if have_std else None
    dims, coords, crs = _grid_coords(f0)
    epoch = _epoch_of_field_times(f0.time_origin, t_field)
    coords["time"] = _estimate_time_coord(t_field, epoch)
    unit = _unit(run, f0)
    k = np.float32(unit.per_field_unit)
    dvars = _estimate_velocity_vars(f0, dims, data * k, None if std is None else std * k, unit)
    dvars["crs"] = ((), np.int32(0), crs)
    dvars.update(_estimate_leg_vars(recs))
    dvars.update(_estimate_rmse_vars(recs, unit, _cf_units(unit, f0)))
    attrs = _global_attrs(
        run,
        f"PASST field estimate of run {run.name}",
        "Gaussian-process estimate of the surface current after each leg of a PASST adaptive "
        "sampling mission, on the mission grid, with its posterior standard deviation.",
        command,
    )
    attrs["cdm_data_type"] = "Grid"
    attrs["field_time_origin"] = str(f0.time_origin or "none (non-dimensional field time)")
    attrs["passt_grid"] = __import__("json").dumps(f0.grid.describe())
    comment = [] if have_std else ["posterior std not recorded by this run (estimate.nc without u_std/v_std)"]
    attrs["comment"] = "; ".join(comment + notes) or "one time step per leg"
    lat, lon = (coords["lat"][1], coords["lon"][1])
    _geo_extent(attrs, lat, lon)
    if epoch is not None:
        _time_extent(attrs, epoch)
    ds = xr.Dataset(dvars, coords=coords, attrs=attrs)
    # a non-dimensional field time is no CF time axis: named so that no reader takes it for one
    return ds if epoch is not None else ds.rename({"time": "field_time"})


def _estimate_time_coord(t_field: np.ndarray, epoch: np.ndarray | None) -> tuple:
    """The estimate's time coordinate: UTC (s since the epoch) where the field has a UTC origin, else
    the field time ``t_field`` itself (non-dimensional)."""
    if epoch is not None:
        return (
            "time",
            epoch,
            {
                "standard_name": "time",
                "long_name": "field time of the estimate (UTC)",
                "units": _EPOCH_UNITS,
                "calendar": "standard",
                "axis": "T",
            },
        )
    return (
        "time",
        t_field,
        {"units": "1", "long_name": "field time of the estimate (non-dimensional: the field has no UTC origin)"},
    )


def _unit(run: RunData, f0) -> SpeedUnit:
    """How the run's field-derived speeds are exported: m/s times the velocity scale the run flew with
    (summary.json's mission ``config``, else an explicit ``field.velocity_scale`` in its mission.yaml); a
    run that records neither keeps the field's own units (``f0.units``)."""
    return run_speed_unit(run.summary, (run.mission or {}).get("field"), f0.units)


def _cf_units(unit: SpeedUnit, f0) -> str:
    """The CF ``units`` of a speed in ``unit``: ``m s-1``, else the field's own."""
    return "m s-1" if unit.label == MPS else f0.units


def _estimate_rmse_vars(recs: list[dict], unit: SpeedUnit, cf_units: str) -> dict[str, Any]:
    """Per estimate the leg's RMSE against the truth (the estimate's and the model alone's), in ``unit``
    (CF ``cf_units``); NaN where the run knew no truth (a real boat)."""

    def col(key):
        return np.array([np.nan if r.get(key) is None else unit(r[key]) for r in recs], np.float64)

    what = {"rmse": "the estimate after the leg", "rmse_model": "the model alone (never re-initialised)"}
    return {
        key: (
            "time",
            col(f"rmse_{'passt' if key == 'rmse' else 'model'}"),
            {
                "units": cf_units,
                "long_name": f"RMSE of {w} against the true field over water cells (u and v pooled)",
                "coverage_content_type": "qualityInformation",
            },
        )
        for key, w in what.items()
    }


def _estimate_velocity_vars(
    f0, dims: tuple, data: np.ndarray, std: np.ndarray | None, unit: SpeedUnit
) -> dict[str, Any]:
    """The estimate's u and v (each after its ``_std`` if the posterior std was recorded), already in ``unit``
    (m/s for a run with a velocity scale): east/north on a lat/lon field, x/y of the data frame on a metric one."""
    geographic = f0.is_geographic and _cf_units(unit, f0) == "m s-1"
    dvars: dict[str, Any] = {}
    for k, name, std_name, word in (
        (0, "u", "eastward_sea_water_velocity", "eastward"),
        (1, "v", "northward_sea_water_velocity", "northward"),
    ):
        a = {
            "units": _cf_units(unit, f0),
            "long_name": f"{word} current, GP estimate after the leg",
            "grid_mapping": "crs",
        }
        if geographic:
            a["standard_name"] = std_name
        if not f0.is_geographic:
            a["coordinates"] = "lat lon"
            a["long_name"] = f"{'x' if k == 0 else 'y'} velocity in the data frame, GP estimate after the leg"
        if std is not None:
            a["ancillary_variables"] = f"{name}_std"
            sa = {kk: vv for kk, vv in a.items() if kk in ("units", "grid_mapping", "coordinates")}
            sa["long_name"] = f"posterior standard deviation of {name} (GP)"
            sa["comment"] = _STD_COMMENT
            if geographic:
                sa["standard_name"] = f"{std_name} standard_error"
            dvars[f"{name}_std"] = (dims, std[:, k], sa)
        dvars[name] = (dims, data[:, k], a)
    return dvars


def _estimate_leg_vars(recs: list[dict]) -> dict[str, Any]:
    """Per estimate (time step) the leg (numbered from 1) whose samples made it and the boat that flew it."""
    return {
        "leg": (
            "time",
            np.array([int(r.get("index", -1)) + 1 for r in recs], np.int32),
            {
                "long_name": "leg (numbered from 1, as the console and the report count) whose samples made this "
                "estimate; the run directory's legs/NNN folder is NNN = leg - 1",
                "units": "1",
            },
        ),
        "boat": (
            "time",
            np.array([int(r.get("boat", 0) or 0) for r in recs], np.int32),
            {"long_name": "boat (0-based) that flew the leg", "units": "1"},
        ),
    }


def _grid_coords(f) -> tuple[tuple, dict, dict]:
    """(dims of u/v, coordinate variables, crs attributes) of a field's grid: 1-D lat/lon (deg) for a
    geographic grid; data-frame x/y (m) with 2-D lat/lon auxiliary coordinates for a metric one."""
    g = f.grid
    wgs84 = {
        "grid_mapping_name": "latitude_longitude",
        "semi_major_axis": 6378137.0,
        "inverse_flattening": 298.257223563,
        "longitude_of_prime_meridian": 0.0,
        "long_name": "WGS84 geographic coordinates",
    }
    lat_a = {"standard_name": "latitude", "units": "degrees_north", "long_name": "cell-centre latitude"}
    lon_a = {"standard_name": "longitude", "units": "degrees_east", "long_name": "cell-centre longitude"}
    if f.is_geographic:
        return (
            ("time", "lat", "lon"),
            {
                "lat": ("lat", np.asarray(g.lats, float), {**lat_a, "axis": "Y"}),
                "lon": ("lon", np.asarray(g.lons, float), {**lon_a, "axis": "X"}),
            },
            wgs84,
        )
    rr, cc = np.meshgrid(np.arange(g.rows), np.arange(g.cols), indexing="ij")
    la, lo = (np.asarray(x, float) for x in g.cell_to_latlon(rr, cc))
    # data-frame metres are no projection coordinates (scaled and rotated onto the sea): no axis or
    # standard name, the 2-D lat/lon auxiliary coordinates place the cells
    coords = {
        "y": (
            "y",
            np.asarray(g.ys, float),
            {"units": "m", "long_name": "cell-centre y in the field's data frame (before scale and rotation)"},
        ),
        "x": (
            "x",
            np.asarray(g.xs, float),
            {"units": "m", "long_name": "cell-centre x in the field's data frame (before scale and rotation)"},
        ),
        "lat": (("y", "x"), la, lat_a),
        "lon": (("y", "x"), lo, lon_a),
    }
    return ("time", "y", "x"), coords, wgs84


# -- NetCDF: the samples as a DSG trajectory ---------------------------------------------------
def _boat_clocks(run: RunData) -> dict[int, Any]:
    """Boat index -> the :class:`~passt_mav.loop.legstep.FieldClock` its samples were placed in field
    time with (summary.json ``clock``, a fleet's ``boats[k].clock``); boats without a record are absent."""
    from passt_mav.loop.legstep import FieldClock

    def of(rec) -> FieldClock | None:
        if not isinstance(rec, dict) or "t_boot0" not in rec:
            return None
        later = tuple(float(x) for x in rec.get("later_boots") or ())
        return FieldClock(float(rec["t_boot0"]), float(rec.get("time_scale", 1.0)), later_boots=later)

    s = run.summary
    found = {int(b.get("boat", k)): of(b.get("clock")) for k, b in enumerate(s.get("boats") or [])}
    if not found:
        found = {0: of(s.get("clock"))}
    return {b: c for b, c in found.items() if c is not None}


def sample_times(run: RunData) -> np.ndarray:
    """The field time the loop gave each of the run's samples (arrival order; its boat's clock,
    :func:`_boat_clocks`; s since the field's ``time_origin`` for a geographic field), NaN for a
    sample whose boat has no recorded clock."""
    from passt_mav.loop.measurement import sample_columns

    c = sample_columns(run.samples)
    boat = np.array([run.boat_of[x.source] for x in run.samples], np.int64)
    t = np.full(len(run.samples), np.nan)
    clocks = _boat_clocks(run)
    for b, clock in clocks.items():
        k = boat == b
        t[k] = clock.field_time(c["time_boot_ms"][k], c["boot"][k])
    return t


def sample_table(run: RunData) -> dict[str, np.ndarray]:
    """The run's samples as columns sorted by (boat, time): ``utc`` (UNIX s: the field's UTC of the
    sample where the field has a UTC origin and the run its clock, else the vehicle's UTC; see
    ``time_is``), ``vehicle_utc`` (UNIX s: the vehicle's UTC of the reading, SYSTEM_TIME, or the time
    of reception where the vehicle sends none), ``field_time`` (field units, NaN where unknown),
    ``lat``/``lon`` (deg), ``u``/``v`` (m/s east/north), ``boat``, ``leg`` (the run's 0-based leg index, -1
    outside any leg: the writers show it numbered from 1, :func:`passt_mav.loop.measurement.leg_number`),
    ``time_boot_ms``, ``boot``; and ``time_is``, a 0-d string array: ``"field"`` or ``"vehicle"``."""
    from passt_mav.loop.measurement import sample_columns

    s = run.samples
    c = sample_columns(s)  # time_boot_ms float64 (exact ms below 2**53): CF 1.8 has no int64
    t_field = sample_times(run)
    epoch = _epoch_of_field_times(run.summary.get("field_time_origin"), t_field)
    on_field = epoch is not None and bool(np.isfinite(epoch).all())
    cols = {
        "utc": epoch if on_field else c["utc"],
        "vehicle_utc": c["utc"],
        "field_time": t_field,
        "lat": c["lat"],
        "lon": c["lon"],
        "u": c["u"],
        "v": c["v"],
        "boat": np.array([run.boat_of[x.source] for x in s], np.int32),
        "leg": c["leg"].astype(np.int32),
        "time_boot_ms": c["time_boot_ms"],
        "boot": c["boot"].astype(np.int32),
    }
    order = np.lexsort((np.arange(len(s)), cols["utc"], cols["boat"]))
    out = {k: v[order] for k, v in cols.items()}
    out["time_is"] = np.array("field" if on_field else "vehicle")
    return out


def samples_dataset(run: RunData, command: str = "passt-mav export --samples"):
    """Every sample of a run as a CF-1.8 DSG ``trajectory`` file, one trajectory per boat (module docstring)."""
    import xarray as xr

    if not run.samples:
        raise ExportError(f"{run.rd.root} has no samples (samples.sqlite missing or empty)")
    c = sample_table(run)
    boats = np.unique(c["boat"]).astype(np.int32)
    rows = np.array([int(np.count_nonzero(c["boat"] == b)) for b in boats], np.int32)
    dv: dict[str, Any] = {
        "trajectory": (
            "trajectory",
            boats,
            {
                "cf_role": "trajectory_id",
                "long_name": "boat (0-based) of the track",
                "comment": "a fleet's boat I is MAVLink system id I+1",
            },
        ),
        "rowSize": ("trajectory", rows, {"sample_dimension": "obs", "long_name": "number of samples of this boat"}),
        **_sample_obs_vars(c),
        "platform": (
            (),
            np.int32(0),
            {
                "long_name": f"passt_mav boats of mission {run.name}",
                "type": "unmanned surface vehicle",
                "comment": "ArduPilot Rover (boat frame)",
            },
        ),
    }
    attrs = _global_attrs(
        run,
        f"PASST current samples of run {run.name}",
        "Surface-current samples taken by the boats of a PASST adaptive sampling mission, one "
        "trajectory per boat (CF contiguous ragged array).",
        command,
    )
    attrs.update(featureType="trajectory", cdm_data_type="Trajectory", cdm_trajectory_variables="trajectory")
    attrs["field_time_origin"] = str(run.summary.get("field_time_origin") or "none (non-dimensional field time)")
    attrs["comment"] = _SAMPLE_TIME_NOTE[str(c["time_is"])]
    _geo_extent(attrs, c["lat"], c["lon"])
    _time_extent(attrs, c["utc"])
    return xr.Dataset(dv, coords=_sample_coords(c), attrs=attrs)


#: how a samples file's ``time`` was made (``sample_table``'s ``time_is``)
_SAMPLE_TIME_NOTE = {
    "field": "time: the field's UTC of each sample (the run's clock, as estimate.nc); vehicle_utc: the "
    "vehicle's own UTC of the reading, kept beside it",
    "vehicle": "time: the vehicle's UTC of each reading (the field has no UTC origin, or the run records no "
    "clock); field_time: the field time the loop gave it, where known",
}


#: ``leg`` in the NetCDF exports counts from 1; this, its fill value, marks a reading outside any leg
LEG_FILL = 0


def _sample_obs_vars(c: dict[str, np.ndarray]) -> dict[str, Any]:
    """The per-sample (``obs``) variables of the trajectory file: the measured current u/v (m/s,
    east/north), the leg, the vehicle's UTC of the reading, the field time (where the field has no
    UTC origin), and the autopilot's time since boot (ms) and boot counter."""
    obs = {"coordinates": "time lat lon", "platform": "platform"}
    times: dict[str, Any] = {
        "vehicle_utc": (
            "obs",
            c["vehicle_utc"],
            {
                "units": _EPOCH_UNITS,
                "calendar": "standard",
                "coordinates": "time lat lon",
                "long_name": "the vehicle's UTC of the reading (SYSTEM_TIME; time of reception where the "
                "vehicle sends none): its own clock, not the field's",
            },
        )
    }
    if str(c["time_is"]) == "vehicle":
        times["field_time"] = (
            "obs",
            c["field_time"],
            {
                "units": "1",
                "coordinates": "time lat lon",
                "long_name": "field time the loop gave the sample (the field's own time units; NaN: unknown)",
            },
        )
    return {
        **times,
        "u": (
            "obs",
            c["u"],
            {
                **obs,
                "standard_name": "eastward_sea_water_velocity",
                "units": "m s-1",
                "long_name": "eastward current measured by the boat",
            },
        ),
        "v": (
            "obs",
            c["v"],
            {
                **obs,
                "standard_name": "northward_sea_water_velocity",
                "units": "m s-1",
                "long_name": "northward current measured by the boat",
            },
        ),
        "leg": (
            "obs",
            np.where(c["leg"] >= 0, c["leg"] + 1, LEG_FILL).astype(np.int32),
            {
                "coordinates": "time lat lon",
                "units": "1",
                "long_name": "leg (numbered from 1, as the console and the report count) the sample was taken in",
                "comment": f"the fill value {LEG_FILL}: a reading outside any leg (on the way to the first leg, "
                "holding between legs, after the last)",
            },
        ),
        "time_boot_ms": (
            "obs",
            c["time_boot_ms"],
            {"units": "ms", "coordinates": "time lat lon", "long_name": "autopilot time since boot of the reading"},
        ),
        "boot": (
            "obs",
            c["boot"],
            {
                "units": "1",
                "coordinates": "time lat lon",
                "long_name": "autopilot boot counter (bumped when time_boot_ms jumps back)",
            },
        ),
    }


def _sample_coords(c: dict[str, np.ndarray]) -> dict[str, Any]:
    """The trajectory file's ``obs`` coordinates: UTC receive time (s since the epoch) and the boat's
    WGS84 latitude/longitude (degrees) at the reading."""
    return {
        "time": (
            "obs",
            c["utc"],
            {
                "standard_name": "time",
                "units": _EPOCH_UNITS,
                "calendar": "standard",
                "axis": "T",
                "long_name": "the field's UTC of the sample (the run's clock)"
                if str(c["time_is"]) == "field"
                else "the vehicle's UTC of the reading (no field UTC: see the comment attribute)",
            },
        ),
        "lat": (
            "obs",
            c["lat"],
            {
                "standard_name": "latitude",
                "units": "degrees_north",
                "axis": "Y",
                "long_name": "boat latitude at the reading (WGS84)",
            },
        ),
        "lon": (
            "obs",
            c["lon"],
            {
                "standard_name": "longitude",
                "units": "degrees_east",
                "axis": "X",
                "long_name": "boat longitude at the reading (WGS84)",
            },
        ),
    }


# -- writing -----------------------------------------------------------------------------------
def write_atomic(out: Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``out``, then rename it to ``out`` (nothing
    half-written on failure). ExportError when ``out``'s folder is missing or not writable."""
    out = Path(out)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise ExportError(f"cannot write {out}: folder {parent} does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=parent)
    except OSError as exc:
        raise ExportError(f"cannot write {out}: {exc.strerror or exc}") from None
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def _write_netcdf(ds, path: Path) -> None:
    enc = {k: {"zlib": True, "complevel": 4} for k in ds.data_vars if ds[k].ndim > 0}
    for k in ds.data_vars:
        if ds[k].dtype.kind == "f":
            enc[k]["_FillValue"] = np.asarray(np.nan, ds[k].dtype)[()]
        elif k in enc:
            enc[k]["_FillValue"] = np.int32(LEG_FILL) if k == "leg" else None
    for k in ds.coords:
        enc[k] = {"_FillValue": None, "dtype": "float64"}
    ds.to_netcdf(path, format="NETCDF4", engine="netcdf4", encoding=enc)


def default_name(fmt: str, samples: bool = False) -> str:
    """The file name an export gets under ``RUN_DIR/export/`` without ``--out``."""
    return {
        "netcdf": "samples.nc" if samples else "estimate.nc",
        "geojson": "run.geojson",
        "kml": "run.kml",
        "csv": "samples.csv",
    }[fmt]


def export_run(
    run_dir: str | Path, fmt: str, out: str | Path | None = None, *, samples: bool = False, command: str | None = None
) -> tuple[Path, dict]:
    """Export a run directory in ``fmt`` (:data:`FORMATS`) to ``out`` (default ``RUN_DIR/export/NAME``,
    an existing folder gets NAME inside it). Returns ``(path written, summary dict of counts)``."""
    from passt_mav.analysis import export_geo

    fmt = str(fmt).lower()
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if samples and fmt != "netcdf":
        raise ExportError("--samples selects the NetCDF samples file: use it with --format netcdf")
    run = load_run(run_dir)
    if out is None:
        (run.rd.root / "export").mkdir(exist_ok=True)
        out = run.rd.root / "export" / default_name(fmt, samples)
    out = Path(out)
    if out.is_dir():
        out = out / default_name(fmt, samples)
    command = command or (
        f"passt-mav export {run.rd.root} --format {fmt}" + (" --samples" if samples else "") + f" --out {out}"
    )
    if fmt == "netcdf":
        ds = samples_dataset(run, command) if samples else estimate_dataset(run, command)
        write_atomic(out, lambda p: _write_netcdf(ds, p))
        info = (
            {"trajectories": int(ds.sizes["trajectory"]), "samples": int(ds.sizes["obs"])}
            if samples
            else {"legs": int(ds["leg"].size), "posterior_std": "u_std" in ds}
        )
    else:
        text, info = {"geojson": export_geo.geojson_text, "kml": export_geo.kml_text, "csv": export_geo.csv_text}[fmt](
            run
        )
        write_atomic(out, lambda p: p.write_text(text, encoding="utf-8"))
    info = {"out": str(out), "format": fmt, "samples": samples, **info}
    if run.damage:
        info["damaged"] = "; ".join(run.damage)
    return out, info
