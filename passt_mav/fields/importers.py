"""Import real ocean-model and HF-radar current files onto a region grid.

Supported layouts (detected from variable names, CF ``standard_name`` and
coordinate attributes, not from the product name):

* HYCOM / RTOFS: ``water_u``/``water_v`` (or ``u_velocity``/``v_velocity``),
  ``depth`` (or ``Depth``/``MT``), longitudes 0..360 or -180..180;
* Copernicus Marine: ``uo``/``vo`` with a ``depth`` dimension;
* HF radar (e.g. MARACOOS totals): ``u``/``v`` in cm/s with NaN gaps and a
  length-1 ``z`` or ``depth`` dimension;
* anything else whose velocity variables carry the CF standard names
  ``(surface_)eastward_sea_water_velocity`` / ``northward_...`` (or the grid-relative
  ``sea_water_x_velocity`` / ``sea_water_y_velocity``) as their ``standard_name``
  attribute or as their variable name (found with cf-xarray), or whose names are
  given explicitly with ``variables=(u_name, v_name)``.

Source grids: rectilinear latitude/longitude (1-D axes, or 2-D ones that are separable);
CF projected grids (a ``grid_mapping`` variable that pyproj reads: polar stereographic,
Lambert conformal, rotated pole, Mercator, ...; 1-D projection x/y axes in m or km, or
degrees for a rotated pole; positions from the file's 2-D latitude/longitude or else the
projection); curvilinear 2-D latitude/longitude (NEMO ``nav_lat``/``nav_lon``, ...); and
ROMS's C grid (``u`` on ``eta_u``/``xi_u`` and ``v`` on ``eta_v``/``xi_v``, averaged to the
``lat_rho``/``lon_rho`` points; ``mask_rho``/``mask_u``/``mask_v`` = 0 is land, NaN,
whatever value the file holds there). Unstructured meshes (FVCOM, SCHISM, ADCIRC) are refused.

What :func:`import_currents` does, in order:

1. **Units** from the variables' ``units`` attribute (m/s, cm/s, mm/s, knots in
   their usual spellings) converted to m/s; a missing or unknown unit is a
   :class:`FieldError` naming ``--units`` (``units=`` in Python) to override. Values
   outside the CF ``valid_min``/``valid_max``, and magnitudes >= 1e10 (fill values the
   file does not declare, e.g. 1.26765e30), are treated as missing.
2. **Surface**: a depth-like dimension (``depth``, ``z``, ``lev``, ...; or
   ``axis="Z"`` / ``positive``) is reduced to its level of smallest ``|depth|``.
3. **Time**: CF times are decoded by xarray; the window is
   ``start <= t < start + hours`` (``start`` defaults to the first time,
   ``hours`` to the rest of the file). An hourly or coarser file keeps its own
   snapshot times inside the window (no temporal interpolation: nothing is
   invented between model outputs); a finer file keeps only the snapshots on
   whole hours after ``start`` (+-60 s). The output's ``time_origin`` is the first
   kept snapshot.
4. **Region**: longitudes are wrapped to -180..180 and sorted, latitudes sorted
   south to north, and only the source window covering the grid (plus one node)
   is read. Coordinate rounding is tolerated, per axis: a target axis matching a
   run of the file's nodes within 1 % of a cell (the file's own grid, coordinates
   stored as float32 or rounded) takes those nodes, so its cells are the file's
   values exactly; one matching within half a cell keeps its first/last centres
   that lie beyond the outer nodes on them, so every cell keeps its data;
   otherwise only 0.1 % of a cell (at least 1e-6 deg) is forgiven. What was
   adjusted is in ``attrs["edges"]``.
5. **Regridding**: bilinear in lat/lon with :class:`scipy.interpolate.RegularGridInterpolator`
   (rectilinear, possibly non-uniform source nodes). A target cell whose
   bilinear stencil touches a missing source node stays NaN (masked); a missing
   node with weight below 1e-3 (target within 0.1 % of a cell of a valid node) is
   ignored and the rest renormalised, so grids that coincide with the source
   nodes reproduce them exactly. Cells outside the file's extent are NaN too.
   NaN is never turned into a current.

   **Projected and curvilinear sources** (:mod:`passt_mav.fields.curvilinear`): velocities along
   the grid's x/y axes (CF ``sea_water_x/y_velocity``; ROMS ``u``/``v``) are first rotated to
   east/north at each source node, ``u_east = ux cos(a) - uy sin(a)``, ``v_north = ux sin(a) +
   uy cos(a)``, with ``a`` the angle of the grid's x axis counter-clockwise from east: ROMS's
   ``angle`` variable; else, with a grid mapping, the direction of a short step along x
   projected back to latitude/longitude with pyproj; else the direction between x neighbours of
   the 2-D latitude/longitude. Grids whose axes are more than 1 deg from perpendicular on the
   ground are refused (grid-relative components would be ambiguous), and so are velocities on
   such grids whose direction the file does not give (no standard name, no ROMS layout). The
   nodes of the window around the region and the target's cell centres are projected to the
   target's local metric frame and triangulated (Delaunay); each cell takes the linear
   (barycentric) value of its triangle with the same missing-node rule as the bilinear stencils,
   and cells outside the nodes, or in a triangle longer than the source cells (across a gap or
   a concave boundary), are NaN. ``attrs["source_grid"]`` and ``attrs["rotation"]`` say what
   was read and how it was rotated.

The coverage of the result (fraction of cells with data) is in
``field.attrs["coverage"]`` and :func:`coverage_report`.

Plausibility (:func:`speed_check`, :func:`coverage_check`): a surface current's median speed
is well below 2.5 m/s and no surface current reaches 10 m/s, so a field in m/s beyond either
(over its valid cells) was read in the wrong units (an HF-radar file in cm/s taken for m/s is
100x too fast); ``passt-mav data import`` refuses it (``--allow-fast`` overrides) and ``plan``,
``run`` and ``vehicle-sim`` warn. A region whose cell-times hold data less than half the time
is imported with a warning; under :data:`MIN_IMPORT_COVERAGE` (a fifth) ``data import`` refuses it
(``--min-coverage`` sets the floor). Units given to the import that differ from the file's own
``units`` attribute (:func:`units_conflict`) are imported as given, with a warning.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from passt_mav.errors import FieldError
from passt_mav.fields.field import FlowField, parse_iso

__all__ = [
    "import_currents",
    "coverage_report",
    "velocity_scale",
    "speed_check",
    "coverage_check",
    "MAX_MEDIAN_SPEED",
    "MAX_SPEED",
    "MIN_COVERAGE",
    "MIN_IMPORT_COVERAGE",
    "units_conflict",
    "U_NAMES",
    "V_NAMES",
]

#: candidate variable names, tried in order after CF standard names
U_NAMES = ("water_u", "uo", "u", "u_velocity", "ugos", "ucur", "U", "east_vel", "eastward_velocity")
V_NAMES = ("water_v", "vo", "v", "v_velocity", "vgos", "vcur", "V", "north_vel", "northward_velocity")
_U_STD = (
    "eastward_sea_water_velocity",
    "surface_eastward_sea_water_velocity",
    "baroclinic_eastward_sea_water_velocity",
    "eastward_sea_water_velocity_assuming_no_tide",
)
_V_STD = (
    "northward_sea_water_velocity",
    "surface_northward_sea_water_velocity",
    "baroclinic_northward_sea_water_velocity",
    "northward_sea_water_velocity_assuming_no_tide",
)
#: grid-relative components (along the grid's x/y axes; ROMS writes the ``_at_u/v_location`` forms),
#: rotated to east/north on projected and curvilinear grids (module docstring, step 5)
_X_STD = (
    "sea_water_x_velocity",
    "x_sea_water_velocity",
    "surface_sea_water_x_velocity",
    "sea_water_x_velocity_at_u_location",
    "barotropic_sea_water_x_velocity",
)
_Y_STD = (
    "sea_water_y_velocity",
    "y_sea_water_velocity",
    "surface_sea_water_y_velocity",
    "sea_water_y_velocity_at_v_location",
    "barotropic_sea_water_y_velocity",
)
_LAT_NAMES = ("lat", "latitude", "Latitude", "LATITUDE", "nav_lat", "lat_rho")
_LON_NAMES = ("lon", "longitude", "Longitude", "LONGITUDE", "nav_lon", "lon_rho")
_DEPTH_NAMES = ("depth", "z", "Depth", "lev", "level", "deptht", "depthu", "depthv", "s_rho", "altitude", "height")
_TIME_NAMES = ("time", "MT", "t", "ocean_time", "Time", "TIME")

#: m/s: a surface current's median speed over a region stays well below this (strong western boundary
#: currents such as the Gulf Stream core reach ~2-2.5 m/s, tidal races ~5 m/s in places, never as a median)
MAX_MEDIAN_SPEED = 2.5
#: m/s: no surface current reaches this anywhere (the fastest tidal races are ~5-8 m/s)
MAX_SPEED = 10.0
#: fraction of (time, cell) pairs with data below which an imported region is warned about
MIN_COVERAGE = 0.5
#: fraction of (time, cell) pairs with data below which ``passt-mav data import`` refuses the region unless
#: ``--min-coverage`` lowers it: a region or time window that misses the file (a sign or corner off, a --start
#: past the file's end, the radar's far edge) keeps 0-4 % of its cell-times, while a region chosen over a
#: model's water or inside a radar's footprint keeps 40-100 % (MARACOOS over the shelf 42 %, RTOFS off
#: Washington with a third land 65 %); a fifth leaves room for coasts and gaps and still catches the misses
#: (the radar's whole domain, mostly land and open sea beyond its range, holds 12 %: no mission region)
MIN_IMPORT_COVERAGE = 0.2
#: unit factors to m/s a too-fast field is tried with for the hint, smallest first
_HINT_UNITS = (("cm/s", 0.01), ("mm/s", 0.001))

_KNOT = 1852.0 / 3600.0
_MISSING_WEIGHT_TOL = 1e-3  # see module docstring, step 5
_UNDECLARED_FILL = 1e10  # see module docstring, step 1


def velocity_scale(units: str | None) -> float:
    """Factor converting a velocity in ``units`` to m/s; FieldError if unknown.

    Accepts e.g. ``m/s``, ``m s-1``, ``m s**-1``, ``m.s-1``, ``meter second-1``,
    ``meters per second``, ``cm/s``, ``cm s-1``, ``mm/s``, ``knots``/``kt``.
    """
    if units is None or not str(units).strip():
        raise FieldError(
            "velocity variable has no 'units' attribute: give them with --units (e.g. --units m/s "
            "or --units cm/s; units= in Python)"
        )
    s = str(units).strip().lower()
    s = s.replace("**", "").replace("^", "").replace("·", " ").replace(".", " ").replace("_", " ")
    s = re.sub(r"\s+per\s+", "/", s)
    s = re.sub(r"\s*/\s*", "/", s)
    s = re.sub(r"\s+", " ", s).strip()
    lengths = {
        "m": 1.0,
        "meter": 1.0,
        "meters": 1.0,
        "metre": 1.0,
        "metres": 1.0,
        "cm": 0.01,
        "centimeter": 0.01,
        "centimeters": 0.01,
        "centimetre": 0.01,
        "centimetres": 0.01,
        "mm": 0.001,
        "millimeter": 0.001,
        "millimeters": 0.001,
        "km": 1000.0,
    }
    seconds = ("s", "sec", "second", "seconds")
    if s in ("kt", "kts", "knot", "knots", "kn"):
        return _KNOT
    m = re.fullmatch(r"([a-z]+)(?:/([a-z]+)| ([a-z]+)-1|/([a-z]+)1)", s)
    if m:
        length, sec = m.group(1), m.group(2) or m.group(3) or m.group(4)
        if length in lengths and sec in seconds:
            return lengths[length]
    raise FieldError(
        f"unknown velocity units {units!r} (expected m/s, cm/s, mm/s or knots): give the real ones "
        "with --units (e.g. --units m/s; units= in Python)"
    )


# -- detection ------------------------------------------------------------------
def _find_velocity(ds, variables) -> tuple[str, str]:
    if variables is not None:
        if len(variables) != 2:
            raise FieldError(f"variables must be two names (u, v), got {variables!r}")
        for name in variables:
            if name not in ds.variables:
                raise FieldError(f"variable {name!r} not in file (has: {', '.join(map(str, ds.data_vars))})")
        return str(variables[0]), str(variables[1])
    import cf_xarray  # noqa: F401 - registers the Dataset.cf accessor

    by_std: dict[str, str] = {}
    for std, names in ds.cf.standard_names.items():
        data = [str(n) for n in names if n in ds.data_vars]
        if data:
            by_std[str(std)] = data[0]
    # a CF standard name used as the variable's name (no standard_name attribute) counts too;
    # an attribute wins when both exist
    for k in ds.data_vars:
        by_std.setdefault(str(k), str(k))
    # east/north pairs first: a ROMS file holding both u/v (grid x/y) and u_eastward/v_northward
    # gives the geographic pair, which needs no rotation
    for su, sv in zip(_U_STD + _X_STD, _V_STD + _Y_STD):
        if su in by_std and sv in by_std:
            return by_std[su], by_std[sv]
    for nu, nv in zip(U_NAMES, V_NAMES):
        if nu in ds.data_vars and nv in ds.data_vars:
            return nu, nv
    raise FieldError(
        "no current variables found (looked for CF eastward/northward_sea_water_velocity and "
        f"{'/'.join(U_NAMES[:4])}...); file has: {', '.join(map(str, ds.data_vars)) or 'no variables'}"
    )


def _is_lat(name: str, var) -> bool:
    a = var.attrs
    return (
        a.get("standard_name") == "latitude"
        or str(a.get("units", "")).lower() in ("degrees_north", "degree_north", "degrees_n", "degree_n")
        or name in _LAT_NAMES
    )


def _is_lon(name: str, var) -> bool:
    a = var.attrs
    return (
        a.get("standard_name") == "longitude"
        or str(a.get("units", "")).lower() in ("degrees_east", "degree_east", "degrees_e", "degree_e")
        or name in _LON_NAMES
    )


def _velocity_frame(u, v) -> str | None:
    """``"geographic"`` when ``u``/``v`` are eastward/northward by their CF standard name (attribute,
    or the variable's name), ``"grid"`` when they are along the grid's x/y axes, None when the file
    does not say (names such as ``u``/``v`` alone)."""
    for std in (str(u.attrs.get("standard_name", "")), str(u.name)):
        if std in _U_STD:
            return "geographic"
        if std in _X_STD:
            return "grid"
    return None


def _horizontal(ds, u) -> tuple[str, str, np.ndarray, np.ndarray] | None:
    """(lat_dim, lon_dim, lat_1d, lon_1d) for the velocity variable ``u`` on a rectilinear
    latitude/longitude grid (1-D axes, or 2-D ones that are separable); None for a grid that is
    not (2-D latitude/longitude that vary along both axes, or projection x/y coordinates with a
    CF ``grid_mapping`` and no latitude/longitude), read by :func:`_read_curvilinear`."""
    lat_var = lon_var = None
    for name in list(u.coords) + list(ds.variables):
        var = ds[name]
        if lat_var is None and _is_lat(str(name), var) and set(var.dims) <= set(u.dims) and var.ndim in (1, 2):
            lat_var = var
        if lon_var is None and _is_lon(str(name), var) and set(var.dims) <= set(u.dims) and var.ndim in (1, 2):
            lon_var = var
    if lat_var is None or lon_var is None:
        if "grid_mapping" in u.attrs or "grid_mapping" in u.encoding:
            return None  # a CF projected grid: positions come from its grid mapping
        raise FieldError(f"cannot find latitude/longitude coordinates of {u.name!r} (dims {u.dims})")
    if lat_var.ndim == 1 and lon_var.ndim == 1:
        if lat_var.dims == lon_var.dims:
            raise FieldError(
                f"{u.name!r} is on an unstructured mesh (latitude and longitude both along {lat_var.dims[0]!r}, "
                "as FVCOM, SCHISM or ADCIRC write): only structured grids (rectilinear, projected, curvilinear) are read"
            )
        return lat_var.dims[0], lon_var.dims[0], lat_var.values.astype(float), lon_var.values.astype(float)
    # 2-D lat/lon (RTOFS, NEMO): usable when separable, i.e. a rectilinear grid stored as 2-D
    if lat_var.dims != lon_var.dims or lat_var.ndim != 2:
        raise FieldError("latitude/longitude coordinates have inconsistent shapes")
    la, lo = lat_var.values.astype(float), lon_var.values.astype(float)
    ydim, xdim = lat_var.dims
    if np.allclose(la, la[:, :1], atol=1e-6) and np.allclose(lo, lo[:1, :], atol=1e-6):
        return ydim, xdim, la[:, 0], lo[0, :]
    if np.allclose(la, la[:1, :], atol=1e-6) and np.allclose(lo, lo[:, :1], atol=1e-6):
        return xdim, ydim, la[0, :], lo[:, 0]
    return None  # curvilinear


def _time_dim(ds, u) -> str | None:
    for d in u.dims:
        if d in ds.coords and np.issubdtype(ds[d].dtype, np.datetime64):
            return str(d)
        if d in ds.variables and (
            str(d) in _TIME_NAMES or ds[d].attrs.get("axis") == "T" or ds[d].attrs.get("standard_name") == "time"
        ):
            return str(d)
    return None


def _is_depth(name: str, ds) -> bool:
    if name in _DEPTH_NAMES:
        return True
    if name in ds.variables:
        a = ds[name].attrs
        return a.get("axis") == "Z" or "positive" in a or a.get("standard_name") in ("depth", "height", "altitude")
    return False


def _to_datetime64(values) -> np.ndarray:
    """Decoded time values (datetime64 or cftime) -> datetime64[ns] UTC-naive."""
    v = np.asarray(values)
    if np.issubdtype(v.dtype, np.datetime64):
        return v.astype("datetime64[ns]")
    if v.dtype == object and v.size and hasattr(v.flat[0], "year"):
        return np.array(
            [np.datetime64(_dt.datetime(t.year, t.month, t.day, t.hour, t.minute, t.second), "ns") for t in v.flat]
        ).reshape(v.shape)
    raise FieldError("the time coordinate is not CF-encoded (needs units like 'hours since 2018-03-01')")


def _select_times(t64: np.ndarray, start, hours) -> tuple[np.ndarray, str]:
    """Indices of the snapshots kept (see module docstring, step 3) and a note saying how."""
    order_ok = t64.size < 2 or np.all(np.diff(t64) > np.timedelta64(0))
    if not order_ok:
        raise FieldError("file times are not strictly increasing")
    first, last = t64[0], t64[-1]
    if start is None:
        t0 = first
    else:
        try:
            t0 = np.datetime64(parse_iso(str(start)).replace(tzinfo=None), "ns")
        except ValueError:
            raise FieldError(f"--start must be an ISO-8601 time like 2018-03-01T00:00Z, got {start!r}") from None
    if hours is not None and (int(hours) != hours or hours < 1):
        raise FieldError(f"hours must be a positive integer, got {hours!r}")
    t1 = t64[-1] + np.timedelta64(1, "s") if hours is None else t0 + np.timedelta64(int(hours) * 3600, "s")
    sel = np.nonzero((t64 >= t0) & (t64 < t1))[0]
    span = f"{str(first)[:19]}Z..{str(last)[:19]}Z"
    if sel.size == 0:
        raise FieldError(f"no snapshot in {str(t0)[:19]}Z + {hours} h; the file covers {span}")
    step = np.median(np.diff(t64[sel]).astype("timedelta64[s]").astype(float)) if sel.size > 1 else 3600.0
    if sel.size == 1:
        note = "one snapshot in the window"
    elif step < 3600.0 - 60.0:
        off = (t64[sel] - t0).astype("timedelta64[s]").astype(float)
        r = np.mod(off + 60.0, 3600.0)
        sel = sel[r <= 120.0]
        note = f"file step {step:.0f} s is finer than hourly: kept the snapshots on whole hours after start"
        if sel.size == 0:
            raise FieldError(f"no snapshot of the file ({span}) falls on a whole hour after {str(t0)[:19]}Z")
    elif step > 3600.0 + 60.0:
        note = f"file step {step / 3600:.3g} h is coarser than hourly: kept the file's own times (no temporal interpolation)"
    else:
        note = "hourly file: kept its snapshots"
    if hours is not None and step <= 3600.0 + 60.0 and sel.size < int(hours):
        note += f"; only {sel.size} of the {int(hours)} hourly snapshots asked for are in the file ({span})"
    return sel, note


# -- the importer -----------------------------------------------------------------
def import_currents(path, grid, *, start=None, hours=None, variables=None, units=None) -> FlowField:
    """Read a model/radar current file and regrid its surface currents onto ``grid``.

    Args:
        path: NetCDF file (HYCOM/RTOFS, Copernicus Marine, HF radar, ...).
        grid: target :class:`geo.RegionGrid` (cell centres, -180..180 longitudes).
        start: first time to keep, ISO-8601 UTC string (default: the file's first).
        hours: length of the time window in hours (default: to the end of the file).
        variables: ``(u_name, v_name)`` to bypass detection.
        units: override the files' velocity units (e.g. ``"cm/s"``).

    Returns:
        A :class:`FlowField` ``(time, 2, rows, cols)`` float32 in m/s, NaN where the
        source has no data; ``attrs`` record the source, variables, unit factor,
        depth, time selection and ``coverage``.
    """
    import geo

    if not isinstance(grid, geo.RegionGrid) or isinstance(grid, geo.MetricRegionGrid):
        raise FieldError("importing needs a geographic RegionGrid (lat/lon) as target")
    path = Path(path)
    with _open_currents(path) as ds:
        src = _read_surface_currents(ds, path.name, grid, start, hours, variables, units)
    data = src.window.regrid(src.values, grid)
    origin = str(src.times[0].astype("datetime64[s]")) + "Z"
    times = (src.times - src.times[0]).astype("timedelta64[ms]").astype(np.float64) / 1000.0
    attrs: dict[str, Any] = {
        "title": "imported surface currents",
        "generator": "passt_mav.fields.importers.import_currents",
        "source_file": path.name,
        "source_attrs": src.attrs,
        "variables": list(src.variables),
        "units_factor_to_m_s": list(src.scales),
        "depth_m": src.depth_m,
        "time_selection": src.time_note,
        "start": None if start is None else str(start),
        "hours": None if hours is None else int(hours),
        "source_grid": src.source_grid,
        "rotation": src.rotation,
        "regrid": src.window.method,
        "edges": src.window.edges_note(),
        "undeclared_fill_values": src.n_fill,
        "units_given": None if units is None else str(units),
        "file_units": list(src.file_units),
    }
    field = FlowField(data, grid, times, origin, "m s-1", attrs)
    field.attrs["coverage"] = round(field.coverage, 6)
    return field


@dataclass(frozen=True)
class _SurfaceCurrents:
    """What :func:`import_currents` reads from a file: ``values`` ``(T, nlat, nlon, 2)`` float64 m/s
    on the region window's nodes (NaN = missing), their ``times`` (datetime64), the ``(u, v)``
    variable names and factors to m/s, the depth used (m, None without a depth axis), the time
    selection note, the count of undeclared fill values and the file's descriptive attrs."""

    values: np.ndarray
    window: _RegionWindow
    times: np.ndarray
    variables: tuple[str, str]
    scales: tuple[float, float]
    depth_m: float | None
    time_note: str
    n_fill: int
    attrs: dict[str, str]
    source_grid: str
    rotation: str
    file_units: tuple[str | None, str | None] = (None, None)


def _read_surface_currents(ds, name: str, grid, start, hours, variables, units) -> _SurfaceCurrents:
    """The surface currents of the open file ``ds`` (called ``name`` in messages) over ``grid``'s
    region and the time window ``start``/``hours``; see :func:`import_currents` for the options."""
    u_name, v_name = _find_velocity(ds, variables)
    u, v = ds[u_name], ds[v_name]
    su, sv = _velocity_scales(u, v, units, f"{name} ({u_name}/{v_name})")
    own = tuple(None if x.attrs.get("units") is None else str(x.attrs["units"]) for x in (u, v))
    horizontal = _horizontal(ds, u) if u.dims == v.dims else None
    if horizontal is None:  # projected, curvilinear or ROMS C grid (module docstring, step 5)
        src = _read_curvilinear(ds, name, grid, start, hours, u, v, (su, sv))
        return dataclasses.replace(src, file_units=own)
    lat_dim, lon_dim, lat, lon = horizontal
    tdim = _time_dim(ds, u)
    isel, depth_used = _surface_selection(ds, u, u_name, (lat_dim, lon_dim, tdim))
    t64 = _source_times(ds, u, u_name, tdim)
    tsel, time_note = _select_times(t64, start, hours)
    if tdim is not None:
        isel[tdim] = tsel
    win = _RegionWindow.of(lat, lon, grid)
    isel[lat_dim] = win.lat_idx
    isel[lon_dim] = win.lon_idx
    order = [tdim, lat_dim, lon_dim] if tdim is not None else [lat_dim, lon_dim]
    a_u, fill_u = _read_velocity(u, isel, order, su)
    a_v, fill_v = _read_velocity(v, isel, order, sv)
    return _SurfaceCurrents(
        values=np.stack([a_u, a_v], axis=-1),
        window=win,
        times=t64[tsel],
        variables=(u_name, v_name),
        scales=(su, sv),
        depth_m=depth_used,
        time_note=time_note,
        n_fill=fill_u + fill_v,
        attrs=_descriptive_attrs(ds),
        source_grid="rectilinear latitude/longitude",
        file_units=own,
        rotation="none ("
        + (
            "x/y components of a latitude/longitude grid are east/north"
            if _velocity_frame(u, v) == "grid"
            else "eastward/northward components"
        )
        + ")",
    )


def _descriptive_attrs(ds) -> dict[str, str]:
    return {k: str(v_) for k, v_ in ds.attrs.items() if k in ("title", "institution", "source", "product_id")}


def _open_currents(path: Path):
    """The file at ``path`` opened as an ``xarray.Dataset`` (a missing or unreadable file is a :class:`FieldError`)."""
    import xarray as xr

    if not path.exists():
        raise FieldError(f"current file not found: {path}")
    try:
        return xr.open_dataset(path)
    except Exception as exc:  # noqa: BLE001 - every reader failure means a bad file for the user
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FieldError(f"cannot read {path} as NetCDF: {msg}") from None


def _velocity_scales(u, v, units: str | None, where: str) -> tuple[float, float]:
    """Factors to m/s of ``u`` and ``v``: from ``units`` when given, else from each variable's
    ``units`` attribute (an unknown unit is a :class:`FieldError` prefixed with ``where``)."""
    if units is not None:
        s = velocity_scale(units)
        return s, s
    try:
        return velocity_scale(u.attrs.get("units")), velocity_scale(v.attrs.get("units"))
    except FieldError as exc:
        raise FieldError(f"{where}: {exc}") from None


def _surface_selection(ds, u, u_name: str, keep: tuple) -> tuple[dict[str, Any], float | None]:
    """``(isel, depth_m)``: indices reducing ``u``'s dimensions other than ``keep`` (lat, lon, time)
    to the surface: the level nearest depth 0 (``depth_m``, None without a depth axis) and
    index 0 of any other size-1 dimension; another extra dimension is a :class:`FieldError`."""
    isel: dict[str, Any] = {}
    depth_used = None
    for d in u.dims:
        if d in keep:
            continue
        if _is_depth(str(d), ds):
            z = ds[d].values.astype(float) if d in ds.variables else np.arange(u.sizes[d], dtype=float)
            k = int(np.nanargmin(np.abs(z)))
            isel[d] = k
            depth_used = float(z[k])
        elif u.sizes[d] == 1:
            isel[d] = 0
        else:
            raise FieldError(f"{u_name} has an extra dimension {d!r} of size {u.sizes[d]} that is not depth")
    return isel, depth_used


def _source_times(ds, u, u_name: str, tdim: str | None) -> np.ndarray:
    """The file's times as ``datetime64``: the time dimension ``tdim``, or else ``u``'s scalar time coordinate."""
    if tdim is not None:
        return _to_datetime64(ds[tdim].values)
    tc = [c for c in u.coords if u[c].ndim == 0 and (np.issubdtype(u[c].dtype, np.datetime64) or str(c) in _TIME_NAMES)]
    if not tc:
        raise FieldError(f"{u_name} has no time coordinate")
    return _to_datetime64(np.atleast_1d(u[tc[0]].values))


@dataclass(frozen=True)
class _RegionWindow:
    """The source nodes around the target region: ``lat_idx``/``lon_idx`` index the file's lat/lon
    axes (in ascending coordinate order), ``sub_lat``/``sub_lon`` are those nodes' coordinates
    (degrees, longitudes wrapped to -180..180), ``glat``/``glon`` the target centres adjusted to
    the nodes, and ``lat_note``/``lon_note`` say what was adjusted (module docstring, step 4)."""

    lat_idx: np.ndarray
    lon_idx: np.ndarray
    sub_lat: np.ndarray
    sub_lon: np.ndarray
    glat: np.ndarray
    glon: np.ndarray
    lat_note: str
    lon_note: str

    @classmethod
    def of(cls, lat: np.ndarray, lon: np.ndarray, grid) -> _RegionWindow:
        """The window of the file's axes ``lat``, ``lon`` (degrees) around ``grid``'s cell centres;
        duplicate coordinates or a region that misses the file are a :class:`FieldError`."""
        lon_w = (lon + 180.0) % 360.0 - 180.0
        lon_order = np.argsort(lon_w, kind="stable")
        lat_order = np.argsort(lat, kind="stable")
        lon_s, lat_s = lon_w[lon_order], lat[lat_order]
        if np.any(np.diff(lon_s) <= 0) or np.any(np.diff(lat_s) <= 0):
            raise FieldError("source latitudes/longitudes contain duplicates")
        # target centres that the file's float32 (or rounded) coordinates put just outside its
        # outer nodes are on them (module docstring, step 4)
        glat, lat_note = _align_to_nodes(grid.lats, lat_s)
        glon, lon_note = _align_to_nodes(grid.lons, lon_s)
        i0 = max(int(np.searchsorted(lat_s, glat[0], side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(lat_s, glat[-1], side="left")) + 1, lat_s.size)
        j0 = max(int(np.searchsorted(lon_s, glon[0], side="right")) - 1, 0)
        j1 = min(int(np.searchsorted(lon_s, glon[-1], side="left")) + 1, lon_s.size)
        if (
            i1 - i0 < 2
            or j1 - j0 < 2
            or lat_s[-1] < glat[0]
            or lat_s[0] > glat[-1]
            or lon_s[-1] < glon[0]
            or lon_s[0] > glon[-1]
        ):
            raise FieldError(
                f"region lat {glat[0]:.3f}..{glat[-1]:.3f}, lon {glon[0]:.3f}..{glon[-1]:.3f} does not overlap the file "
                f"(lat {lat_s[0]:.3f}..{lat_s[-1]:.3f}, lon {lon_s[0]:.3f}..{lon_s[-1]:.3f})"
            )
        return cls(lat_order[i0:i1], lon_order[j0:j1], lat_s[i0:i1], lon_s[j0:j1], glat, glon, lat_note, lon_note)

    method = "bilinear (scipy RegularGridInterpolator); stencils touching missing nodes stay NaN"

    def regrid(self, values: np.ndarray, grid) -> np.ndarray:
        """``values`` ``(T, nlat, nlon, 2)`` on the window's nodes -> ``(T, 2, rows, cols)`` on ``grid``."""
        return _regrid_bilinear(values, self, grid)

    def edges_note(self) -> str:
        """The ``edges`` attribute: the adjustments of the target centres, or ``"no edge adjustment"``."""
        return "; ".join(f"{ax}: {x}" for ax, x in (("lat", self.lat_note), ("lon", self.lon_note)) if x) or (
            "no edge adjustment"
        )


def _read_velocity(var, isel: dict, order: list, scale: float) -> tuple[np.ndarray, int]:
    """``(a, n_fill)``: the selected values of ``var`` as ``(T, nlat, nlon)`` float64 m/s (times
    ``scale``), NaN outside the valid range and at undeclared fill values (``n_fill`` of them)."""
    a = var.isel(isel).transpose(*order).values.astype(np.float64)
    if len(order) == 2:  # (lat, lon): a file without a time dimension holds one time
        a = a[None]
    lo_v, hi_v = _valid_range(var)
    a = np.where((a < lo_v) | (a > hi_v), np.nan, a)
    # fill values a file does not declare (1.26765e30 of GrADS/OPeNDAP, 9.96921e36 of
    # netCDF, 1e20 ...) are no current: |v| >= 1e10 in any unit is missing, never data
    fill = np.abs(a) >= _UNDECLARED_FILL
    return np.where(fill, np.nan, a) * scale, int(np.count_nonzero(fill))


def _regrid_bilinear(src: np.ndarray, win: _RegionWindow, grid) -> np.ndarray:
    """``src`` ``(T, nlat, nlon, 2)`` (m/s on the window's nodes, NaN = missing) bilinearly
    regridded onto ``grid``'s cells: ``(T, 2, rows, cols)`` float32, NaN where the stencil's weight
    on missing nodes reaches the tolerance (module docstring, step 5)."""
    from scipy.interpolate import RegularGridInterpolator

    sub_lat, sub_lon = win.sub_lat, win.sub_lon
    T = src.shape[0]
    valid = np.isfinite(src).all(axis=-1)  # (T, nlat, nlon)
    # RegularGridInterpolator interpolates trailing dims together: values (nlat, nlon, T*2)
    vals = np.where(valid[..., None], src, 0.0).transpose(1, 2, 0, 3).reshape(sub_lat.size, sub_lon.size, T * 2)
    wval = valid.transpose(1, 2, 0).astype(np.float64)
    pts = np.stack(np.meshgrid(win.glat, win.glon, indexing="ij"), axis=-1).reshape(-1, 2)
    kw = dict(method="linear", bounds_error=False, fill_value=np.nan)
    num = RegularGridInterpolator((sub_lat, sub_lon), vals, **kw)(pts)  # (cells, T*2)
    wv = RegularGridInterpolator((sub_lat, sub_lon), wval, **kw)(pts)  # (cells, T): weight on valid nodes
    # the 0 placeholder at missing nodes only ever meets weight < tol: below it the
    # valid weights are renormalised, above it the cell is NaN (module docstring, step 5)
    ok = np.isfinite(wv) & (wv >= 1.0 - _MISSING_WEIGHT_TOL)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num.reshape(-1, T, 2) / wv[..., None]
    out = np.where(ok[..., None], out, np.nan)
    return out.reshape(grid.rows, grid.cols, T, 2).transpose(2, 3, 0, 1).astype(np.float32)


def _align_to_nodes(x: np.ndarray, nodes: np.ndarray) -> tuple[np.ndarray, str]:
    """Target centres ``x`` (ascending, degrees) adjusted to the source's ``nodes`` (ascending),
    and a note saying what was adjusted (module docstring, step 4).

    * The file's own grid: when ``x`` matches a run of consecutive nodes, each within 1 % of
      the local node spacing (coordinates stored as float32 or rounded), the centres are those
      nodes: the cells are the file's values, exactly.
    * Aligned within half a cell: a first/last centre beyond the outer node is that node, so
      every cell keeps its data; inner centres are interpolated where they are.
    * Otherwise a centre within 0.1 % of the edge spacing (at least 1e-6 deg, ~0.1 m) outside
      is on the edge (rounding); anything farther stays outside (NaN): nothing is extrapolated.
    """
    x = np.asarray(x, float).copy()
    if nodes.size < 2:
        return x, ""
    n = x.size
    k = int(np.argmin(np.abs(nodes - x[0])))
    dev = np.inf
    if k + n <= nodes.size:
        run = nodes[k : k + n]
        local = np.diff(nodes[max(k - 1, 0) : min(k + n + 1, nodes.size)]).min()
        dev = float(np.max(np.abs(x - run)) / local)
    if dev < 0.01:
        return run.copy(), (
            f"the file's own grid (centres within {dev:.2g} cell of its nodes): its node values used" if dev > 0 else ""
        )
    if dev < 0.5:
        lo_tol = hi_tol = 0.5 * float(np.diff(nodes).min())
    else:
        lo_tol = max(1e-6, 1e-3 * float(nodes[1] - nodes[0]))
        hi_tol = max(1e-6, 1e-3 * float(nodes[-1] - nodes[-2]))
    moved = []
    lo = (x < nodes[0]) & (x > nodes[0] - lo_tol)
    hi = (x > nodes[-1]) & (x < nodes[-1] + hi_tol)
    if lo.any():
        moved.append(f"{float(np.max(nodes[0] - x[lo])):.3g} deg below")
        x[lo] = nodes[0]
    if hi.any():
        moved.append(f"{float(np.max(x[hi] - nodes[-1])):.3g} deg above")
        x[hi] = nodes[-1]
    if not moved:
        return x, ""
    why = "the target matches the file's nodes within half a cell" if dev < 0.5 else "coordinate rounding"
    return x, f"edge centres up to {' and '.join(moved)} the file's outer nodes taken as on them ({why})"


# -- projected and curvilinear source grids (module docstring, step 5) -------------------------
#: ROMS Arakawa C grid: u on (eta_u, xi_u), v on (eta_v, xi_v), positions and ``angle`` on (eta_rho, xi_rho)
_ROMS_U_DIMS = ("eta_u", "xi_u")
_ROMS_V_DIMS = ("eta_v", "xi_v")
_ROMS_RHO_DIMS = ("eta_rho", "xi_rho")
#: metres per unit of CF projection coordinates
_LENGTH_UNITS = {"m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0, "km": 1000.0}
_LENGTH_UNITS.update(kilometer=1000.0, kilometers=1000.0, kilometre=1000.0, kilometres=1000.0)


@dataclass(frozen=True)
class _NodeGrid:
    """Where a non-rectilinear file's velocity nodes are: ``lat``/``lon`` ``(ny, nx)`` degrees on the
    dimensions ``ydim``/``xdim`` (x along the last axis), and what gives their grid angle: ROMS's
    ``angle`` (radians, XI axis from east) or a grid mapping's ``crs`` with the nodes' projection
    coordinates ``px``/``py`` (the CRS's units), or neither (the angle comes from lat/lon)."""

    ydim: str
    xdim: str
    lat: np.ndarray
    lon: np.ndarray
    description: str
    angle: np.ndarray | None = None
    crs: Any = None
    crs_name: str = ""
    px: np.ndarray | None = None
    py: np.ndarray | None = None


@dataclass(frozen=True)
class _ScatteredWindow:
    """The box ``rows`` x ``cols`` of a curvilinear file's nodes around the target region, with their
    positions ``lat``/``lon`` (degrees); regridded by :func:`passt_mav.fields.curvilinear.regrid_scattered`."""

    rows: np.ndarray
    cols: np.ndarray
    lat: np.ndarray
    lon: np.ndarray

    method = (
        "linear on a Delaunay triangulation of the source nodes in the target's local metric frame "
        "(scipy LinearNDInterpolator); triangles touching missing nodes or longer than the source cells stay NaN"
    )

    def regrid(self, values: np.ndarray, grid) -> np.ndarray:
        """``values`` ``(T, ny, nx, 2)`` east/north m/s on the window's nodes -> ``(T, 2, rows, cols)``."""
        from passt_mav.fields.curvilinear import regrid_scattered

        data, _ = regrid_scattered(self.lat, self.lon, values, grid)
        return data

    def edges_note(self) -> str:
        return "not applicable (curvilinear source: cells outside its nodes' triangles are NaN)"


def _roms_cgrid(ds, u, v) -> bool:
    """Whether ``u``/``v`` are ROMS C-grid velocities (u at xi_u/eta_u, v at xi_v/eta_v)."""
    return set(_ROMS_U_DIMS) <= set(u.dims) and set(_ROMS_V_DIMS) <= set(v.dims) and set(_ROMS_RHO_DIMS) <= set(ds.dims)


def _latlon_on(ds, dims: tuple) -> tuple[Any, Any] | tuple[None, None]:
    """The file's latitude and longitude variables on exactly ``dims`` (2-D), or ``(None, None)``."""
    lat = next((ds[k] for k in ds.variables if ds[k].dims == dims and _is_lat(str(k), ds[k])), None)
    lon = next((ds[k] for k in ds.variables if ds[k].dims == dims and _is_lon(str(k), ds[k])), None)
    return (lat, lon) if lat is not None and lon is not None else (None, None)


def _node_grid(ds, u, cgrid: bool, where: str) -> _NodeGrid:
    """The node positions and angle sources of a non-rectilinear file (see :class:`_NodeGrid`)."""
    import cf_xarray  # noqa: F401 - registers the .cf accessors

    if cgrid:
        lat, lon = _latlon_on(ds, _ROMS_RHO_DIMS)
        if lat is None:
            raise FieldError(f"{where}: a ROMS C grid without lat_rho/lon_rho on {'/'.join(_ROMS_RHO_DIMS)}")
        ydim, xdim = _ROMS_RHO_DIMS
        desc = f"ROMS C grid: {u.name} at xi_u/eta_u and v at xi_v/eta_v averaged to rho points ({lat.name}/{lon.name})"
    else:
        lat = lon = None
        for k in list(u.coords) + list(ds.variables):
            var = ds[k]
            if var.ndim == 2 and set(var.dims) <= set(u.dims) and _is_lat(str(k), var):
                lat, lon = _latlon_on(ds, var.dims)
                if lat is not None:
                    break
        ydim = xdim = None
        desc = ""
        if lat is not None:
            ydim, xdim = (str(d) for d in lat.dims)
            desc = f"curvilinear 2-D latitude/longitude ({lat.name}/{lon.name})"
    gm = _grid_mapping(ds, u, where)
    crs = px = py = None
    crs_name = ""
    if gm is not None:
        crs, crs_name = gm.crs, str(gm.name)
        px, py, pdims = _projection_xy(ds, u, crs, where)
        if px is not None:
            if ydim is None or {ydim, xdim} == set(pdims):
                ydim, xdim = pdims
            else:
                px = py = None  # projection axes that are not the lat/lon's: angles from lat/lon
        desc = (desc + "; " if desc else "") + f"CF grid_mapping {crs_name} ({gm.array.name})"
    if ydim is None:
        raise FieldError(
            f"{where}: cannot find the positions of {u.name!r} (dims {u.dims}): no 1-D or 2-D latitude/longitude "
            "and no CF grid_mapping with projection_x/y_coordinate axes"
        )
    if lat is None:
        from pyproj import Transformer

        lon_v, lat_v = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(px, py)
        lat_a, lon_a = np.asarray(lat_v, float), np.asarray(lon_v, float)
        desc += ": latitude/longitude computed from the projection"
    else:
        # the projection axes say which dimension is x; 2-D latitude/longitude alone are taken as
        # (y, x), the order ROMS and NEMO write
        lat_a = lat.transpose(ydim, xdim).values.astype(float)
        lon_a = lon.transpose(ydim, xdim).values.astype(float)
    angle = None
    if "angle" in ds.variables and ds["angle"].dims == (ydim, xdim):
        a = ds["angle"]
        angle = a.values.astype(float)
        if "deg" in str(a.attrs.get("units", "radians")).lower():
            angle = np.deg2rad(angle)
    return _NodeGrid(str(ydim), str(xdim), lat_a, lon_a, desc, angle, crs, crs_name, px, py)


def _grid_mapping(ds, u, where: str):
    """The cf-xarray ``GridMapping`` (``.crs`` a pyproj CRS, ``.name``, ``.array``) of ``u``, or None;
    a grid mapping pyproj cannot read is a :class:`FieldError`."""
    if "grid_mapping" not in u.attrs and "grid_mapping" not in u.encoding:
        return None
    try:
        gms = ds.cf[str(u.name)].cf.grid_mappings
    except Exception as exc:  # noqa: BLE001 - cf-xarray/pyproj reading the grid mapping: a bad mapping in the file
        raise FieldError(f"{where}: cannot read the grid_mapping of {u.name!r}: {str(exc).splitlines()[0]}") from None
    if not gms:
        return None
    if len(gms) > 1:
        raise FieldError(f"{where}: {u.name!r} has {len(gms)} grid mappings; expected one")
    if gms[0].crs is None:
        raise FieldError(f"{where}: pyproj cannot read the grid_mapping {gms[0].name!r} of {u.name!r}")
    return gms[0]


def _projection_xy(ds, u, crs, where: str):
    """``(px, py, (ydim, xdim))``: the 2-D projection coordinates of ``u``'s nodes in ``crs``'s units
    (metres for a projected CRS, converted from the file's ``km``; degrees for a rotated pole), from
    its 1-D CF X/Y axes; ``(None, None, None)`` when it has none."""
    da = ds.cf[str(u.name)]
    axes = da.cf.axes
    xs = [k for k in axes.get("X", []) if ds[k].ndim == 1 and ds[k].dims[0] in u.dims]
    ys = [k for k in axes.get("Y", []) if ds[k].ndim == 1 and ds[k].dims[0] in u.dims]
    if not xs or not ys:
        return None, None, None
    x, y = ds[xs[0]], ds[ys[0]]
    f = 1.0
    if crs.is_projected:
        unit = str(x.attrs.get("units", "m")).strip().lower()
        if unit not in _LENGTH_UNITS:
            raise FieldError(f"{where}: projection coordinate {x.name!r} has units {unit!r} (expected m or km)")
        f = _LENGTH_UNITS[unit] / float(crs.axis_info[0].unit_conversion_factor or 1.0)
    PX, PY = np.meshgrid(x.values.astype(float) * f, y.values.astype(float) * f)
    return PX, PY, (str(y.dims[0]), str(x.dims[0]))


def _node_window(lat: np.ndarray, lon: np.ndarray, grid, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, cols)``: the index box of the file's nodes that covers ``grid``'s cell centres with a
    margin of two source cells (positions in the target's local metric frame); a region that no
    node reaches is a :class:`FieldError`."""
    X, Y = grid.latlon_to_xy(lat, lon)
    X, Y = np.asarray(X, float), np.asarray(Y, float)
    fin = np.isfinite(X) & np.isfinite(Y)
    gx, gy = grid.centres_xy()
    box = (float(np.min(gx)), float(np.max(gx)), float(np.min(gy)), float(np.max(gy)))

    def near(margin: float) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return (
                fin & (X >= box[0] - margin) & (X <= box[1] + margin) & (Y >= box[2] - margin) & (Y <= box[3] + margin)
            )

    steps = [np.hypot(np.diff(X, axis=a), np.diff(Y, axis=a)) for a in (0, 1)]
    typical = max(float(np.nanmedian(s)) if np.isfinite(s).any() else 0.0 for s in steps)
    cand = near(4.0 * typical)
    # the margin: two of the largest source steps among the nodes near the region
    local = [s[cand[1:] if a == 0 else cand[:, 1:]] for a, s in enumerate(steps)]
    local_max = max((float(np.nanmax(s)) for s in local if s.size and np.isfinite(s).any()), default=typical)
    sel = near(2.0 * local_max)
    if not sel.any():
        la, lo = lat[np.isfinite(lat)], ((lon[np.isfinite(lon)] + 180.0) % 360.0) - 180.0
        raise FieldError(
            f"{where}: region lat {grid.lats[0]:.3f}..{grid.lats[-1]:.3f}, lon {grid.lons[0]:.3f}..{grid.lons[-1]:.3f} "
            f"does not overlap the file (lat {la.min():.3f}..{la.max():.3f}, lon {lo.min():.3f}..{lo.max():.3f})"
        )
    ii, jj = np.nonzero(sel)
    ny, nx = lat.shape
    rows = np.arange(max(ii.min() - 1, 0), min(ii.max() + 2, ny))
    cols = np.arange(max(jj.min() - 1, 0), min(jj.max() + 2, nx))
    if rows.size < 2 or cols.size < 2:
        raise FieldError(f"{where}: the region covers fewer than 2x2 of the file's nodes")
    return rows, cols


def _read_box(var, isel: dict, tdim, ydim: str, xdim: str, rows, cols, scale: float) -> tuple[np.ndarray, int]:
    """``(a, n_fill)``: ``var`` on the index box ``rows`` x ``cols`` of its ``ydim``/``xdim`` as
    ``(T, len(rows), len(cols))`` m/s (see :func:`_read_velocity`); indices beyond the variable's
    extent (the outer faces of a C grid) are NaN."""
    ny, nx = var.sizes[ydim], var.sizes[xdim]
    rows, cols = np.asarray(rows), np.asarray(cols)
    ri, ci = np.clip(rows, 0, ny - 1), np.clip(cols, 0, nx - 1)
    # the box is read as one hyperslab (index arrays make netCDF read point by point)
    sel = dict(isel)
    sel[ydim] = slice(int(ri.min()), int(ri.max()) + 1)
    sel[xdim] = slice(int(ci.min()), int(ci.max()) + 1)
    order = [tdim, ydim, xdim] if tdim is not None else [ydim, xdim]
    a, n_fill = _read_velocity(var, sel, order, scale)
    a = a[:, ri - ri.min()][:, :, ci - ci.min()]
    a[:, (rows < 0) | (rows >= ny), :] = np.nan
    a[:, :, (cols < 0) | (cols >= nx)] = np.nan
    return a, n_fill


def _land_mask(ds, dims: tuple, rows, cols) -> np.ndarray | None:
    """True where the file's ``mask*`` variable on ``dims`` (ROMS mask_rho/mask_u/mask_v) is 0 (land),
    over the index box (indices beyond its extent are not land); None without one."""
    name = next((k for k in ds.variables if str(k).startswith("mask") and ds[k].dims == dims), None)
    if name is None:
        return None
    m = ds[name].values
    rows, cols = np.asarray(rows), np.asarray(cols)
    r = np.clip(rows, 0, m.shape[0] - 1)
    c = np.clip(cols, 0, m.shape[1] - 1)
    land = m[np.ix_(r, c)] == 0
    land[(rows < 0) | (rows >= m.shape[0]), :] = False
    land[:, (cols < 0) | (cols >= m.shape[1])] = False
    return land


def _read_curvilinear(ds, name: str, grid, start, hours, u, v, scales) -> _SurfaceCurrents:
    """:func:`_read_surface_currents` for a CF projected grid, a curvilinear 2-D latitude/longitude
    grid or a ROMS C grid: the surface currents on the file's nodes around ``grid``'s region,
    rotated to east/north (module docstring, step 5)."""
    from passt_mav.fields import curvilinear as cv

    where = f"{name} ({u.name}/{v.name})"
    cgrid = _roms_cgrid(ds, u, v)
    if u.dims != v.dims and not cgrid:
        raise FieldError(
            f"{u.name} and {v.name} have different dimensions {u.dims} vs {v.dims} (of staggered grids only "
            "ROMS's C grid, u on eta_u/xi_u and v on eta_v/xi_v, is read)"
        )
    nodes = _node_grid(ds, u, cgrid, where)
    frame = _velocity_frame(u, v)
    if frame is None and (cgrid or nodes.angle is not None):
        frame = "grid"  # ROMS's u/v are along its XI/ETA axes
    if frame is None:
        raise FieldError(
            f"{where}: velocities on a {'projected' if nodes.crs is not None else 'curvilinear'} grid whose direction the file "
            "does not give (no standard_name eastward_/northward_sea_water_velocity or sea_water_x/y_velocity, no ROMS "
            "angle): cannot rotate them to east/north"
        )
    udims = _ROMS_U_DIMS if cgrid else (nodes.ydim, nodes.xdim)
    vdims = _ROMS_V_DIMS if cgrid else (nodes.ydim, nodes.xdim)
    tdim = _time_dim(ds, u)
    isel_u, depth_used = _surface_selection(ds, u, str(u.name), (*udims, tdim))
    isel_v, _ = _surface_selection(ds, v, str(v.name), (*vdims, tdim))
    t64 = _source_times(ds, u, str(u.name), tdim)
    tsel, time_note = _select_times(t64, start, hours)
    if tdim is not None:
        isel_u[tdim] = isel_v[tdim] = tsel
    rows, cols = _node_window(nodes.lat, nodes.lon, grid, where)
    su, sv = scales
    if cgrid:
        # rho column j lies between u faces j-1 and j, rho row i between v faces i-1 and i
        ucols = np.arange(cols[0] - 1, cols[-1] + 1)
        vrows = np.arange(rows[0] - 1, rows[-1] + 1)
        a_u, fill_u = _read_box(u, isel_u, tdim, *udims, rows, ucols, su)
        a_v, fill_v = _read_box(v, isel_v, tdim, *vdims, vrows, cols, sv)
        for a, dims, r, c in ((a_u, udims, rows, ucols), (a_v, vdims, vrows, cols)):
            land = _land_mask(ds, dims, r, c)
            if land is not None:
                a[:, land] = np.nan
        a_u, a_v = cv.cgrid_to_rho(a_u, a_v)
    else:
        a_u, fill_u = _read_box(u, isel_u, tdim, *udims, rows, cols, su)
        a_v, fill_v = _read_box(v, isel_v, tdim, *vdims, rows, cols, sv)
    land = _land_mask(ds, (nodes.ydim, nodes.xdim), rows, cols)
    if land is not None:
        a_u[:, land] = np.nan
        a_v[:, land] = np.nan
    box = np.ix_(rows, cols)
    lat, lon = nodes.lat[box], nodes.lon[box]
    if frame == "geographic":
        rotation = "none (eastward/northward components)"
    else:
        if nodes.angle is not None:
            theta, how = nodes.angle[box], "the file's ROMS angle variable (XI axis from east)"
        elif nodes.px is not None:
            theta, worst = cv.angles_from_crs(nodes.crs, nodes.px[box], nodes.py[box], where=where)
            how = f"the grid x axis's direction from the {nodes.crs_name} projection (pyproj; axes within {worst:.2g} deg of perpendicular)"
        else:
            theta, worst = cv.angles_from_latlon(lat, lon, where=where)
            how = f"the grid x axis's direction from the 2-D latitude/longitude (axes within {worst:.2g} deg of perpendicular)"
        a_u, a_v = cv.rotate_to_east_north(a_u, a_v, theta)
        deg = np.rad2deg(theta[np.isfinite(theta)])
        span = f"{deg.min():.4g}..{deg.max():.4g}" if deg.size else "?"
        rotation = f"grid x/y components rotated to east/north by {how}: x axis {span} deg counter-clockwise from east"
    return _SurfaceCurrents(
        values=np.stack([a_u, a_v], axis=-1),
        window=_ScatteredWindow(rows, cols, lat, lon),
        times=t64[tsel],
        variables=(str(u.name), str(v.name)),
        scales=(su, sv),
        depth_m=depth_used,
        time_note=time_note,
        n_fill=fill_u + fill_v,
        attrs=_descriptive_attrs(ds),
        source_grid=nodes.description,
        rotation=rotation,
    )


def _valid_range(var) -> tuple[float, float]:
    """CF valid range of a variable in its stored (unpacked, since unscaled) units."""
    a = var.attrs
    enc = var.encoding
    if "scale_factor" in enc or "add_offset" in enc:
        # valid_* of packed variables are in packed units; xarray already masked _FillValue
        return -math.inf, math.inf
    lo, hi = -math.inf, math.inf
    if "valid_range" in a:
        lo, hi = (float(x) for x in np.asarray(a["valid_range"]).ravel()[:2])
    lo = float(a.get("valid_min", lo))
    hi = float(a.get("valid_max", hi))
    return lo, hi


def coverage_report(field: FlowField) -> dict[str, Any]:
    """How much of a field holds data.

    Returns a JSON-able dict: ``coverage`` (fraction of (time, cell) pairs with
    data), ``cells_any`` / ``cells_all`` (fraction of cells with data at some /
    every time), ``per_time_min`` / ``per_time_max`` (range of the per-snapshot
    coverage), ``n_times``, ``shape``.
    """
    m = field.mask
    per_t = 1.0 - m.reshape(m.shape[0], -1).mean(axis=1)
    return {
        "coverage": float(1.0 - m.mean()),
        "cells_any": float((~m).any(axis=0).mean()),
        "cells_all": float((~m).all(axis=0).mean()),
        "per_time_min": float(per_t.min()),
        "per_time_max": float(per_t.max()),
        "n_times": int(field.n_times),
        "shape": list(field.shape),
    }


def speed_check(field: FlowField) -> tuple[str, str | None] | None:
    """Speeds no surface current has, in a field whose units are m/s.

    Over the valid cells of every snapshot, a median speed above :data:`MAX_MEDIAN_SPEED` or any
    speed above :data:`MAX_SPEED` (m/s) is implausible. Returns None when the speeds are plausible
    (or the field is not in m/s, e.g. the non-dimensional cylinder, or holds no data), else
    ``(problem, units)``: ``problem`` one line naming the speeds (no hint), ``units`` the spelling
    (``"cm/s"``, ``"mm/s"``) whose factor makes them plausible when the median is too fast, None when
    neither does or only a few values are (bad values, not wrong units).
    """
    try:
        if velocity_scale(field.units) != 1.0:
            return None
    except FieldError:
        return None
    sp = field.speed()
    sp = sp[np.isfinite(sp)]
    if sp.size == 0:
        return None
    med, top = float(np.median(sp)), float(sp.max())
    if med <= MAX_MEDIAN_SPEED and top <= MAX_SPEED:
        return None
    problem = (
        f"speeds no surface current has: median {med:.3g} m/s, max {top:.3g} m/s over the valid cells "
        f"(a median above {MAX_MEDIAN_SPEED:g} m/s or any speed above {MAX_SPEED:g} m/s is implausible)"
    )
    units = None
    if med > MAX_MEDIAN_SPEED:  # a plausible median with a few wild values is bad data, not wrong units
        units = next((u for u, k in _HINT_UNITS if med * k <= MAX_MEDIAN_SPEED and top * k <= MAX_SPEED), None)
    return problem, units


def units_conflict(field: FlowField) -> str | None:
    """One line when an import was given velocity units (``units=``, ``--units``) other than the file's own
    ``units`` attribute of u or v: another factor to m/s (``"m/s"`` and ``"m s-1"`` agree), naming both and how
    many times faster or slower the currents are read than the file says; None without given units, without a
    readable attribute (what ``--units`` is for), or when they agree."""
    given = field.attrs.get("units_given")
    own = [str(x) for x in field.attrs.get("file_units") or () if x is not None]
    if given is None or not own:
        return None
    try:
        k_given, k_own = velocity_scale(given), {velocity_scale(x) for x in own}
    except FieldError:
        return None
    if len(k_own) != 1 or math.isclose(k_given, next(iter(k_own)), rel_tol=1e-9):
        return None
    ratio = k_given / next(iter(k_own))
    how = f"{ratio:.4g} times faster" if ratio > 1 else f"{1.0 / ratio:.4g} times slower"
    names = " and ".join(repr(x) for x in dict.fromkeys(own))
    return (
        f"--units {given} overrides the file's own units {names} of its currents: they are read {how} than "
        "the file says; leave --units out unless the file's units attribute is wrong"
    )


def coverage_check(field: FlowField) -> str | None:
    """One line when less than :data:`MIN_COVERAGE` of the field's (time, cell) pairs hold data
    (the percentage), else None."""
    cov = field.coverage
    if cov >= MIN_COVERAGE:
        return None
    return f"only {100.0 * cov:.1f} % of the region's cell-times hold data (below {100.0 * MIN_COVERAGE:g} %)"
