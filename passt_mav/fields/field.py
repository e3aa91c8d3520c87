"""The ``FlowField`` container: current snapshots on a region grid, with NetCDF I/O.

Data contract (DESIGN.md):

* ``data``: float32, shape ``(time, 2, rows, cols)``; channel 0 = u (eastward,
  +x), channel 1 = v (northward, +y); row 0 is the southern edge. Geographic
  fields are in m/s; the cylinder is non-dimensional (inflow speed = 1, lengths in
  metres, so time is in "seconds at 1 m/s").
* Missing or land cells are NaN in ``data`` and ``True`` in ``mask``
  (``(time, rows, cols)``). Nothing here fills NaN silently; :meth:`filled` does
  it on request.
* ``times``: float64 seconds since ``time_origin`` (ISO-8601 UTC string) for
  geographic data, or non-dimensional time for the cylinder (``time_origin`` is
  ``None``).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geo import MetricRegionGrid, RegionGrid
from passt_mav.errors import FieldError

__all__ = ["FieldError", "FlowField", "load_field", "load_std", "parse_iso"]

#: CF standard names for geographic current components.
CF_U = "eastward_sea_water_velocity"
CF_V = "northward_sea_water_velocity"


@dataclass(eq=False)
class FlowField:
    """Current snapshots on a grid.

    Attributes:
        data: ``(time, 2, rows, cols)`` float32, u/v east/north; NaN = missing.
        grid: the :class:`geo.RegionGrid` or :class:`geo.MetricRegionGrid`.
        times: ``(time,)`` float64; seconds since ``time_origin`` (geographic) or
            non-dimensional time (metric/cylinder).
        time_origin: ISO-8601 UTC string of time 0, or ``None`` for
            non-dimensional fields.
        units: velocity units, ``"m s-1"`` or ``"1"`` (non-dimensional).
        attrs: provenance (generator, parameters, seed, command, ...), JSON-able.
    """

    data: np.ndarray
    grid: RegionGrid | MetricRegionGrid
    times: np.ndarray
    time_origin: str | None = None
    units: str = "m s-1"
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if data.ndim != 4 or data.shape[1] != 2:
            raise FieldError(f"field data must have shape (time, 2, rows, cols), got {data.shape}")
        if data.shape[2:] != self.grid.shape:
            raise FieldError(f"field data grid {data.shape[2:]} does not match the region grid {self.grid.shape}")
        self.data = np.ascontiguousarray(data, dtype=np.float32)
        times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        if times.shape[0] != data.shape[0]:
            raise FieldError(f"{times.shape[0]} times for {data.shape[0]} snapshots")
        if times.size > 1 and not np.all(np.diff(times) > 0):
            raise FieldError("field times must increase strictly")
        self.times = times
        self.attrs = dict(self.attrs)

    # -- basic properties ---------------------------------------------------
    @property
    def n_times(self) -> int:
        return int(self.data.shape[0])

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def mask(self) -> np.ndarray:
        """``(time, rows, cols)`` bool, True where u or v is missing (NaN)."""
        return ~np.isfinite(self.data).all(axis=1)

    @property
    def land_mask(self) -> np.ndarray:
        """``(rows, cols)`` bool, True where a cell is missing at every time."""
        return self.mask.all(axis=0)

    @property
    def coverage(self) -> float:
        """Fraction of (time, cell) pairs holding data."""
        return float(1.0 - self.mask.mean())

    @property
    def dt(self) -> float:
        """Snapshot interval (seconds, or non-dimensional time); requires uniform spacing."""
        if self.n_times < 2:
            raise FieldError("a single snapshot has no time step")
        d = np.diff(self.times)
        if not np.allclose(d, d[0], rtol=1e-6, atol=1e-9):
            raise FieldError("snapshot times are not uniformly spaced")
        return float(d[0])

    def decorrelation_time(self, level: float = 0.5) -> float | None:
        """The lag (field time units) at which the current's autocorrelation in time falls to ``level``.

        The anomaly is each water cell's u and v minus its own time mean; the autocorrelation at lag
        ``k * dt`` is the mean product of anomalies ``k`` snapshots apart over all cells and both
        components, divided by their mean square. Linear between snapshots. None when the field has
        fewer than three snapshots, no variance, or stays above ``level`` over its whole span. A tidal
        current falls to 0.5 within about a sixth of its period (2 h for the 12.4 h tide).
        """
        if self.n_times < 3:
            return None
        water = ~self.land_mask & ~self.mask.any(axis=0)
        d = np.asarray(self.data[:, :, water], np.float64)
        if d.size == 0:
            return None
        d = d - d.mean(axis=0, keepdims=True)
        var = float(np.mean(d * d))
        if not var > 0:
            return None
        dt, prev = self.dt, 1.0
        for k in range(1, self.n_times - 1):
            rho = float(np.mean(d[k:] * d[:-k])) / var
            if rho < level:
                return dt * (k - 1 + (prev - level) / (prev - rho))
            prev = rho
        return None

    @property
    def is_geographic(self) -> bool:
        return isinstance(self.grid, RegionGrid) and not isinstance(self.grid, MetricRegionGrid)

    @property
    def u(self) -> np.ndarray:
        return self.data[:, 0]

    @property
    def v(self) -> np.ndarray:
        return self.data[:, 1]

    def speed(self) -> np.ndarray:
        """``(time, rows, cols)`` speed magnitude (NaN where missing)."""
        return np.hypot(self.data[:, 0], self.data[:, 1])

    def state_at(self, k: int) -> np.ndarray:
        """Snapshot ``k`` as a state to start from: ``(2, rows, cols)`` float32, field units.

        The one rule for gaps that come and go (HF radar, a model's wetting and drying): a cell missing
        at snapshot ``k`` that holds data at some other snapshot takes its value at the nearest
        snapshot in time with data (the earlier on a tie), never zero; a cell missing at every
        snapshot (``land_mask``) stays NaN. Every state taken from a field goes through here: the
        mission's start (``t0``), ``plan``'s state, the offline engines and the counterfactual.
        """
        miss = self.mask
        out = np.array(self.data[k], dtype=np.float32)
        gap = miss[k] & ~miss.all(axis=0)
        for j in sorted(range(self.n_times), key=lambda j: (abs(j - k), j))[1:]:
            if not gap.any():
                break
            take = gap & ~miss[j]
            out[:, take] = self.data[j][:, take]
            gap &= ~take
        return out

    def filled(self, value: float = 0.0) -> np.ndarray:
        """Copy of ``data`` with NaN replaced by ``value`` (explicit, never implicit)."""
        return np.where(np.isfinite(self.data), self.data, np.float32(value)).astype(np.float32)

    def datetimes(self) -> np.ndarray:
        """Snapshot times as ``datetime64[ms]`` UTC (geographic fields only)."""
        if self.time_origin is None:
            raise FieldError("this field has non-dimensional time (no time origin)")
        t0 = np.datetime64(parse_iso(self.time_origin).replace(tzinfo=None), "ms")
        return t0 + (self.times * 1000.0).round().astype("timedelta64[ms]")

    # -- slicing ------------------------------------------------------------
    def isel(
        self, time: slice | int | np.ndarray | None = None, rows: slice | None = None, cols: slice | None = None
    ) -> FlowField:
        """Subset by snapshot index and/or a contiguous cell window (step 1)."""
        t = slice(None) if time is None else time
        if isinstance(t, (int, np.integer)):
            t = slice(int(t), int(t) + 1)
        data = self.data[t]
        times = self.times[t]
        grid = self.grid
        if rows is not None or cols is not None:
            rs = range(self.grid.rows)[rows or slice(None)]
            cs = range(self.grid.cols)[cols or slice(None)]
            if rs.step != 1 or cs.step != 1 or len(rs) < 2 or len(cs) < 2:
                raise FieldError("region slices must be contiguous (step 1) and keep at least 2x2 cells")
            data = data[:, :, rs.start : rs.stop, cs.start : cs.stop]
            grid = _subgrid(self.grid, rs, cs)
        return FlowField(data, grid, times, self.time_origin, self.units, dict(self.attrs))

    # -- sampling -----------------------------------------------------------
    def interp(self, t, r, c) -> np.ndarray:
        """Bilinear-in-space, linear-in-time sample at fractional cell ``(r, c)``.

        ``t`` is in the units of ``times``; scalars or arrays broadcast together.
        Returns ``(..., 2)`` float64 (u, v). Outside the grid or time range, or
        where any of the surrounding values is missing, the result is NaN.
        """
        t, r, c = np.broadcast_arrays(np.asarray(t, float), np.asarray(r, float), np.asarray(c, float))
        out = np.full(t.shape + (2,), np.nan)
        R, C = self.grid.shape
        T = self.n_times
        ft = (
            np.interp(t, self.times, np.arange(T), left=np.nan, right=np.nan)
            if T > 1
            else np.where(t == self.times[0], 0.0, np.nan)
        )
        ok = np.isfinite(ft) & (r >= 0) & (r <= R - 1) & (c >= 0) & (c <= C - 1)
        if not np.any(ok):
            return out
        ft, rr, cc = ft[ok], r[ok], c[ok]
        t0 = np.minimum(np.floor(ft).astype(int), max(T - 2, 0))
        r0 = np.minimum(np.floor(rr).astype(int), R - 2)
        c0 = np.minimum(np.floor(cc).astype(int), C - 2)
        wt, wr, wc = ft - t0, rr - r0, cc - c0
        acc = np.zeros(ft.shape + (2,))
        for dt_, w_t in ((0, 1 - wt), (1, wt)):
            ti = np.minimum(t0 + dt_, T - 1)
            for dr, w_r in ((0, 1 - wr), (1, wr)):
                for dc, w_c in ((0, 1 - wc), (1, wc)):
                    vals = self.data[ti, :, r0 + dr, c0 + dc].astype(float)  # (n, 2)
                    w = (w_t * w_r * w_c)[:, None]
                    # a zero weight must not let a NaN neighbour poison the sample
                    acc += np.where(w > 0, vals * w, 0.0) + np.where((w > 0) & ~np.isfinite(vals), np.nan, 0.0)
        out[ok] = acc
        return out

    def sample_latlon(self, t, lat, lon) -> np.ndarray:
        """Sample (u, v) at geographic positions (degrees) and time ``t``; see :meth:`interp`."""
        r, c = self.grid.latlon_to_fcell(lat, lon)
        return self.interp(t, r, c)

    # -- identity -----------------------------------------------------------
    def data_hash(self) -> str:
        """SHA-256 (hex, first 16) of data bytes, times and grid: identifies a training set."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.data).tobytes())
        h.update(np.ascontiguousarray(self.times).tobytes())
        h.update(json.dumps(self.grid.describe(), sort_keys=True).encode())
        return h.hexdigest()[:16]

    # -- NetCDF -------------------------------------------------------------
    def to_dataset(self, std: np.ndarray | None = None):
        """An ``xarray.Dataset`` following CF conventions (see module docstring).

        ``std``: optional ``(time, 2, rows, cols)`` posterior standard deviation of u/v (the GP's,
        same units and frame as ``data``), written as ``u_std``/``v_std`` (CF standard-name
        modifier ``standard_error``) and named by u/v's ``ancillary_variables``.
        """
        import xarray as xr

        attrs = self._cf_global_attrs()
        dims, coords, u_attrs, v_attrs = self._cf_space()
        coords["time"] = ("time", self.times, self._cf_time_attrs())
        data_vars = {"u": (dims, self.data[:, 0], u_attrs), "v": (dims, self.data[:, 1], v_attrs)}
        if std is not None:
            data_vars.update(self._cf_std_vars(std, dims, u_attrs, v_attrs))
        ds = xr.Dataset(data_vars, coords=coords, attrs=attrs)
        return ds

    def _cf_global_attrs(self) -> dict[str, Any]:
        """The data set's global attributes: CF conventions, title, grid and provenance as JSON, and
        every scalar (str/number, not bool) entry of ``attrs``."""
        attrs: dict[str, Any] = {
            "Conventions": "CF-1.8",
            "title": str(self.attrs.get("title", "passt_mav flow field")),
            "passt_grid": json.dumps(self.grid.describe()),
            "passt_provenance": json.dumps(_jsonable(self.attrs), sort_keys=True),
        }
        for k, v in self.attrs.items():
            if isinstance(v, (str, int, float, np.integer, np.floating)) and not isinstance(v, bool):
                attrs.setdefault(k, v)
        return attrs

    def _cf_space(self) -> tuple[tuple[str, str, str], dict, dict, dict]:
        """``(dims, coords, u_attrs, v_attrs)`` of the spatial frame: lat/lon cell centres (degrees)
        and eastward/northward currents on a geographic grid, else x/y cell centres (m, data frame)."""
        g = self.grid
        if self.is_geographic:
            dims = ("time", "lat", "lon")
            coords = {
                "lat": (
                    "lat",
                    g.lats,
                    {"standard_name": "latitude", "units": "degrees_north", "long_name": "cell-centre latitude"},
                ),
                "lon": (
                    "lon",
                    g.lons,
                    {"standard_name": "longitude", "units": "degrees_east", "long_name": "cell-centre longitude"},
                ),
            }
            u_attrs = {"standard_name": CF_U, "units": self.units, "long_name": "eastward current"}
            v_attrs = {"standard_name": CF_V, "units": self.units, "long_name": "northward current"}
        else:
            dims = ("time", "y", "x")
            coords = {
                "y": (
                    "y",
                    g.ys,
                    {"units": "m", "long_name": "cross-stream coordinate of cell centre (data frame)", "axis": "Y"},
                ),
                "x": (
                    "x",
                    g.xs,
                    {"units": "m", "long_name": "stream-wise coordinate of cell centre (data frame)", "axis": "X"},
                ),
            }
            u_attrs = {"units": self.units, "long_name": "x velocity (inflow = 1)"}
            v_attrs = {"units": self.units, "long_name": "y velocity (inflow = 1)"}
        return dims, coords, u_attrs, v_attrs

    def _cf_time_attrs(self) -> dict[str, str]:
        """Attributes of the time coordinate: seconds since ``time_origin``, or non-dimensional time."""
        if self.time_origin is not None:
            origin = parse_iso(self.time_origin).strftime("%Y-%m-%d %H:%M:%S")
            return {"standard_name": "time", "units": f"seconds since {origin}", "calendar": "standard"}
        return {"units": "1", "long_name": "non-dimensional time (lengths in m, inflow speed 1)"}

    def _cf_std_vars(self, std, dims: tuple, u_attrs: dict, v_attrs: dict) -> dict:
        """``u_std``/``v_std`` data variables from the posterior std ``std`` (checked against the field's
        shape); names them in ``u_attrs``/``v_attrs``'s ``ancillary_variables``."""
        std = np.asarray(std, np.float32)
        if std.shape != self.data.shape:
            raise FieldError(f"posterior std must have the field's shape {self.data.shape}, got {std.shape}")
        out = {}
        for k, name, a in ((0, "u", u_attrs), (1, "v", v_attrs)):
            sa = {"units": self.units, "long_name": f"posterior standard deviation of {name} (GP)"}
            if "standard_name" in a:
                sa["standard_name"] = a["standard_name"] + " standard_error"
            out[f"{name}_std"] = (dims, std[:, k], sa)
            a["ancillary_variables"] = f"{name}_std"
        return out

    def to_netcdf(self, path: str | Path, std: np.ndarray | None = None) -> Path:
        """Write CF NetCDF-4 (NaN fill for missing); ``std`` as in :meth:`to_dataset`. Returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        ds = self.to_dataset(std)
        enc = {
            k: {"_FillValue": np.float32(np.nan), "dtype": "float32", "zlib": True, "complevel": 4}
            for k in ds.data_vars
        }
        # decode_times stays off on read: seconds are stored raw, never as datetime objects
        enc["time"] = {"dtype": "float64"}
        ds.to_netcdf(path, encoding=enc, engine="netcdf4")
        return path

    @classmethod
    def from_netcdf(cls, path: str | Path) -> FlowField:
        """Read a file written by :meth:`to_netcdf` (for other files use the importers).

        The project's attributes (``passt_grid``, ``passt_provenance``, the time axis' ``units``), the variables'
        shapes and the size are checked first (:mod:`passt_mav.fields.checks`): a damaged file is one
        :class:`FieldError` naming the file and what is wrong, never another exception."""
        import xarray as xr

        from passt_mav.fields import checks

        path = Path(path)
        if not path.exists():
            raise FieldError(f"field file not found: {path}")
        try:
            ds = xr.open_dataset(path, decode_times=False, engine="netcdf4")
        except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise FieldError(f"cannot read {path} as NetCDF: {msg}") from None
        with ds:
            if "passt_grid" not in ds.attrs:
                raise FieldError(
                    f"{path} is not a passt_mav field file (no passt_grid attribute); use 'passt-mav data import'"
                )
            missing = [k for k in ("u", "v", "time") if k not in ds.variables]
            if missing:
                raise FieldError(f"{path} lacks the variable(s) {', '.join(missing)} of a passt_mav field file")
            grid = checks.grid_attr(ds.attrs["passt_grid"], path)
            attrs = checks.provenance_attr(ds.attrs.get("passt_provenance"), path)
            origin = checks.time_origin_attr(ds["time"].attrs.get("units"), path)
            units = ds["u"].attrs.get("units", "m s-1")
            if not isinstance(units, str):
                raise FieldError(f"{path}: attribute u:units is damaged (a {type(units).__name__}, not text)")
            u, v, t = ds["u"], ds["v"], ds["time"]
            if u.ndim != 3 or u.shape != v.shape or t.ndim != 1 or t.shape[0] != u.shape[0]:
                raise FieldError(
                    f"{path}: u {u.shape}, v {v.shape} and time {t.shape} are not the (time, rows, cols) and (time,) "
                    "of a passt_mav field file"
                )
            checks.check_size(u.shape, str(path))
            u, v, times = _values(u, path), _values(v, path), _values(t, path, np.float64)
        if not np.all(np.isfinite(times)):
            raise FieldError(f"{path}: the time axis has missing (NaN) or infinite values")
        try:
            return cls(np.stack([u, v], axis=1), grid, times, origin, units, attrs)
        except FieldError as exc:
            raise FieldError(f"{path}: {exc}") from None


def _values(var, path, dtype=np.float32) -> np.ndarray:
    """The values of the file variable ``var`` as ``dtype`` (a truncated file, a text or a complex variable, values
    beyond the dtype: a :class:`FieldError` naming the variable and ``path``)."""
    try:
        a = var.values
        if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
            raise FieldError(f"{path}: variable {var.name} holds {a.dtype} values, not numbers")
        with np.errstate(over="ignore", invalid="ignore"):
            return a.astype(dtype)
    except FieldError:
        raise
    except (OSError, RuntimeError, ValueError, TypeError, OverflowError) as exc:  # a damaged file's data
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FieldError(f"{path}: cannot read variable {var.name}: {msg}") from None


def load_field(path: str | Path) -> FlowField:
    """Load a passt_mav field file (``.nc``)."""
    return FlowField.from_netcdf(path)


def load_std(path: str | Path) -> np.ndarray | None:
    """The posterior std ``(time, 2, rows, cols)`` float32 stored beside a field by
    :meth:`FlowField.to_netcdf` (``u_std``/``v_std``, field units), or None if the file has none
    (estimates written before the std was recorded, or forecasts)."""
    import xarray as xr

    with xr.open_dataset(Path(path), decode_times=False, engine="netcdf4") as ds:
        if "u_std" not in ds.variables or "v_std" not in ds.variables:
            return None
        return np.stack([ds["u_std"].values, ds["v_std"].values], axis=1).astype(np.float32)


def _subgrid(grid, rs: range, cs: range):
    if isinstance(grid, MetricRegionGrid):
        xs, ys = grid.xs, grid.ys
        # the anchor stays where it is: the sub-grid keeps its absolute placement
        sub = MetricRegionGrid(
            xs[cs.start],
            xs[cs.stop - 1],
            ys[rs.start],
            ys[rs.stop - 1],
            len(rs),
            len(cs),
            anchor_lat=grid.anchor_lat,
            anchor_lon=grid.anchor_lon,
            rotation_deg=grid.rotation_deg,
            scale=grid.scale,
        )
        # re-anchor so the sub-grid's centre lands where it was in the parent
        lat, lon = grid.fcell_to_latlon((rs.start + rs.stop - 1) / 2, (cs.start + cs.stop - 1) / 2)
        return MetricRegionGrid(
            sub.x0,
            sub.x1,
            sub.y0,
            sub.y1,
            sub.rows,
            sub.cols,
            anchor_lat=float(lat),
            anchor_lon=float(lon),
            rotation_deg=grid.rotation_deg,
            scale=grid.scale,
        )
    lats, lons = grid.lats, grid.lons
    return RegionGrid(lats[rs.start], lons[cs.start], lats[rs.stop - 1], lons[cs.stop - 1], len(rs), len(cs))


def parse_iso(s: str) -> _dt.datetime:
    """An ISO 8601 date-time (``Z``, an offset or none = UTC; a space may stand for ``T``) as an aware UTC datetime."""
    s = s.strip().replace("Z", "+00:00")
    if " " in s and "T" not in s:
        s = s.replace(" ", "T", 1)
    d = _dt.datetime.fromisoformat(s)
    if d.tzinfo is None:
        d = d.replace(tzinfo=_dt.UTC)
    return d.astimezone(_dt.UTC)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)
