"""Region grids on the Earth: cell <-> lat/lon <-> local metres.

Frames and conventions (DESIGN.md data contract):

* ``row`` grows northward (row 0 is the southern edge), ``col`` grows eastward.
* A *fractional cell* coordinate ``(r, c)`` is continuous; integer values are cell
  centres and the region covers ``-0.5 <= r <= rows - 0.5`` (same for ``c``).
* Latitudes/longitudes are WGS84 degrees.
* The *local frame* is east/north metres in an azimuthal-equidistant projection
  about the region's origin (its centre for geographic grids, the anchor for
  metric grids), built with pyproj and ``always_xy=True``.

Two kinds of grid share one interface:

* :class:`RegionGrid` - regular in latitude/longitude, defined by the centres of
  its corner cells (south, west, north, east) and ``(rows, cols)``; this is how
  ocean-model and radar products are laid out.
* :class:`MetricRegionGrid` - regular in a metric data frame (x, y in metres, e.g.
  the cylinder CFD crop), placed on Earth by an anchor lat/lon, a rotation and a
  scale factor.

All conversion methods are vectorised: they take scalars or arrays and return
numpy arrays of the broadcast shape (0-d for scalar input).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

__all__ = ["GeoError", "RegionGrid", "MetricRegionGrid", "geodesic_distance_m"]


class GeoError(ValueError):
    """Invalid region, grid or position (message names the problem)."""


@functools.cache
def _geod():
    from pyproj import Geod

    return Geod(ellps="WGS84")


def geodesic_distance_m(lat1, lon1, lat2, lon2) -> np.ndarray:
    """WGS84 geodesic distance in metres between points (degrees), vectorised."""
    lat1, lon1, lat2, lon2 = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (lat1, lon1, lat2, lon2)))
    _, _, dist = _geod().inv(lon1.ravel(), lat1.ravel(), lon2.ravel(), lat2.ravel())
    return np.asarray(dist, dtype=float).reshape(lat1.shape)


class _GridBase:
    """Shared machinery: pyproj transformers and derived conversions."""

    rows: int
    cols: int
    _origin_lat: float
    _origin_lon: float

    # -- set up -------------------------------------------------------------
    def _init_projection(self, lat0: float, lon0: float) -> None:
        self._origin_lat = float(lat0)
        self._origin_lon = float(lon0)
        self._fwd = None
        self._inv = None

    def _transformers(self):
        if self._fwd is None:
            from pyproj import CRS, Transformer

            local = CRS.from_proj4(
                f"+proj=aeqd +lat_0={self._origin_lat:.10f} +lon_0={self._origin_lon:.10f} "
                "+datum=WGS84 +units=m +no_defs"
            )
            self._fwd = Transformer.from_crs("EPSG:4326", local, always_xy=True)
            self._inv = Transformer.from_crs(local, "EPSG:4326", always_xy=True)
        return self._fwd, self._inv

    @property
    def origin(self) -> tuple[float, float]:
        """(lat, lon) in degrees of the local frame's origin."""
        return (self._origin_lat, self._origin_lon)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    # -- lat/lon <-> local metres --------------------------------------------
    def latlon_to_xy(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:
        """Degrees -> local (east, north) metres."""
        fwd, _ = self._transformers()
        lat, lon = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
        x, y = fwd.transform(lon, lat)
        return np.asarray(x, float), np.asarray(y, float)

    def xy_to_latlon(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Local (east, north) metres -> degrees (lat, lon)."""
        _, inv = self._transformers()
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        lon, lat = inv.transform(x, y)
        return np.asarray(lat, float), np.asarray(lon, float)

    # -- cells ----------------------------------------------------------------
    def fcell_to_latlon(self, r, c) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
        raise NotImplementedError

    def latlon_to_fcell(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
        raise NotImplementedError

    def cell_to_latlon(self, row, col) -> tuple[np.ndarray, np.ndarray]:
        """Cell centre(s) (integer row, col) -> (lat, lon) degrees."""
        return self.fcell_to_latlon(np.asarray(row, float), np.asarray(col, float))

    def latlon_to_cell(self, lat, lon, *, clip: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(lat, lon) -> the (row, col) of the cell containing it (int64).

        Points outside the grid raise :class:`GeoError` unless ``clip`` is true,
        in which case they map to the nearest edge cell.
        """
        r, c = self.latlon_to_fcell(lat, lon)
        ri = np.floor(np.asarray(r) + 0.5).astype(np.int64)
        ci = np.floor(np.asarray(c) + 0.5).astype(np.int64)
        if clip:
            return np.clip(ri, 0, self.rows - 1), np.clip(ci, 0, self.cols - 1)
        bad = (ri < 0) | (ri >= self.rows) | (ci < 0) | (ci >= self.cols)
        if np.any(bad):
            raise GeoError(f"{int(np.count_nonzero(bad))} position(s) lie outside the {self.rows}x{self.cols} grid")
        return ri, ci

    def cell_to_xy(self, row, col) -> tuple[np.ndarray, np.ndarray]:
        """Cell centre(s) -> local (east, north) metres."""
        return self.latlon_to_xy(*self.cell_to_latlon(row, col))

    def xy_to_fcell(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        return self.latlon_to_fcell(*self.xy_to_latlon(x, y))

    def centres_latlon(self) -> tuple[np.ndarray, np.ndarray]:
        """(lat, lon) of every cell centre, each of shape (rows, cols)."""
        rr, cc = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        return self.cell_to_latlon(rr, cc)

    def centres_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """Local (east, north) metres of every cell centre, each (rows, cols)."""
        return self.latlon_to_xy(*self.centres_latlon())

    @property
    def cell_size_m(self) -> tuple[float, float]:
        """(north-south, east-west) centre-to-centre spacing in metres at the grid centre.

        Measured as WGS84 geodesic distances between neighbouring centres.
        """
        r0, c0 = (self.rows - 1) / 2.0, (self.cols - 1) / 2.0
        la, lo = self.fcell_to_latlon(np.array([r0 - 0.5, r0 + 0.5, r0, r0]), np.array([c0, c0, c0 - 0.5, c0 + 0.5]))
        dy = float(geodesic_distance_m(la[0], lo[0], la[1], lo[1]))
        dx = float(geodesic_distance_m(la[2], lo[2], la[3], lo[3]))
        return dy, dx

    @property
    def mean_cell_size_m(self) -> float:
        dy, dx = self.cell_size_m
        return math.sqrt(dy * dx)

    # -- geofence -------------------------------------------------------------
    def _margin_cells(self, margin_m: float) -> tuple[float, float]:
        dy, dx = self.cell_size_m
        return margin_m / dy, margin_m / dx

    def contains(self, lat, lon, margin_m: float = 0.0) -> np.ndarray:
        """True where (lat, lon) lies inside the region grown by ``margin_m`` metres.

        The region is the union of its cells (edges half a cell beyond the outer
        centres); a negative margin shrinks it.
        """
        r, c = self.latlon_to_fcell(lat, lon)
        mr, mc = self._margin_cells(margin_m)
        return (r >= -0.5 - mr) & (r <= self.rows - 0.5 + mr) & (c >= -0.5 - mc) & (c <= self.cols - 0.5 + mc)

    def geofence(self, margin_m: float = 0.0, points_per_side: int = 4) -> np.ndarray:
        """Inclusion polygon (N, 2) of (lat, lon) degrees, counter-clockwise, not closed.

        The region's outer cell edges grown by ``margin_m`` metres, each side
        densified to ``points_per_side`` segments so it follows the grid's shape in
        any projection.
        """
        mr, mc = self._margin_cells(margin_m)
        r0, r1 = -0.5 - mr, self.rows - 0.5 + mr
        c0, c1 = -0.5 - mc, self.cols - 0.5 + mc
        t = np.linspace(0.0, 1.0, points_per_side, endpoint=False)
        rs = np.concatenate([np.full_like(t, r0), r0 + (r1 - r0) * t, np.full_like(t, r1), r1 - (r1 - r0) * t])
        cs = np.concatenate([c0 + (c1 - c0) * t, np.full_like(t, c1), c1 - (c1 - c0) * t, np.full_like(t, c0)])
        lat, lon = self.fcell_to_latlon(rs, cs)
        return np.column_stack([lat, lon])

    def describe(self) -> dict[str, Any]:  # pragma: no cover - overridden
        raise NotImplementedError


class RegionGrid(_GridBase):
    """A grid regular in latitude/longitude (WGS84 degrees).

    Parameters are the latitudes/longitudes of the *centres* of the corner cells:
    ``south``/``north`` are the centre latitudes of rows 0 and ``rows-1``,
    ``west``/``east`` the centre longitudes of columns 0 and ``cols-1``.
    Longitudes are in -180..180 and the region may not cross the antimeridian.
    """

    kind = "geographic"

    def __init__(self, south: float, west: float, north: float, east: float, rows: int, cols: int):
        vals = dict(south=south, west=west, north=north, east=east)
        for k, v in vals.items():
            if not np.isfinite(v):
                raise GeoError(f"region {k} must be a finite number, got {v!r}")
        if not (-90 <= south < north <= 90):
            raise GeoError(f"region needs -90 <= south < north <= 90, got south={south}, north={north}")
        if not (-180 <= west < east <= 180):
            raise GeoError(f"region needs -180 <= west < east <= 180, got west={west}, east={east}")
        if int(rows) != rows or int(cols) != cols or rows < 2 or cols < 2:
            raise GeoError(f"grid needs integer rows, cols >= 2, got {rows}x{cols}")
        self.south, self.west, self.north, self.east = float(south), float(west), float(north), float(east)
        self.rows, self.cols = int(rows), int(cols)
        self.dlat = (self.north - self.south) / (self.rows - 1)
        self.dlon = (self.east - self.west) / (self.cols - 1)
        self._init_projection((self.south + self.north) / 2.0, (self.west + self.east) / 2.0)

    @property
    def lats(self) -> np.ndarray:
        """Cell-centre latitudes, (rows,), south to north."""
        return self.south + self.dlat * np.arange(self.rows)

    @property
    def lons(self) -> np.ndarray:
        """Cell-centre longitudes, (cols,), west to east."""
        return self.west + self.dlon * np.arange(self.cols)

    def fcell_to_latlon(self, r, c):
        r, c = np.broadcast_arrays(np.asarray(r, float), np.asarray(c, float))
        return self.south + self.dlat * r, self.west + self.dlon * c

    def latlon_to_fcell(self, lat, lon):
        lat, lon = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
        return (lat - self.south) / self.dlat, (lon - self.west) / self.dlon

    def describe(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "south": self.south,
            "west": self.west,
            "north": self.north,
            "east": self.east,
            "rows": self.rows,
            "cols": self.cols,
        }

    def __repr__(self) -> str:
        return (
            f"RegionGrid(south={self.south}, west={self.west}, north={self.north}, "
            f"east={self.east}, rows={self.rows}, cols={self.cols})"
        )

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, RegionGrid)
            and not isinstance(other, MetricRegionGrid)
            and self.describe() == other.describe()
        )

    def __hash__(self) -> int:
        return hash(tuple(self.describe().items()))


class MetricRegionGrid(_GridBase):
    """A grid regular in a metric data frame, placed on Earth.

    ``x0, x1`` / ``y0, y1`` are the data-frame coordinates (metres) of the first
    and last cell centres along x (columns, eastward before rotation) and y (rows,
    northward before rotation). The data frame's point ``(xc, yc)`` - the grid's
    centre - is put at ``anchor_lat, anchor_lon``; data metres are multiplied by
    ``scale`` (a 10 m CFD crop with scale 500 covers 5 km of sea) and rotated
    counter-clockwise by ``rotation_deg`` (0: data +x = east, +y = north).
    """

    kind = "metric"

    def __init__(
        self,
        x0: float,
        x1: float,
        y0: float,
        y1: float,
        rows: int,
        cols: int,
        *,
        anchor_lat: float,
        anchor_lon: float,
        rotation_deg: float = 0.0,
        scale: float = 1.0,
    ):
        if not (x1 > x0 and y1 > y0):
            raise GeoError(f"metric grid needs x0 < x1 and y0 < y1, got x {x0}..{x1}, y {y0}..{y1}")
        if int(rows) != rows or int(cols) != cols or rows < 2 or cols < 2:
            raise GeoError(f"grid needs integer rows, cols >= 2, got {rows}x{cols}")
        if not (np.isfinite(scale) and scale > 0):
            raise GeoError(f"scale must be a positive number, got {scale!r}")
        if not (-90 < anchor_lat < 90 and -180 <= anchor_lon <= 180):
            raise GeoError(f"anchor lat/lon out of range: {anchor_lat}, {anchor_lon}")
        self.x0, self.x1, self.y0, self.y1 = float(x0), float(x1), float(y0), float(y1)
        self.rows, self.cols = int(rows), int(cols)
        self.dx = (self.x1 - self.x0) / (self.cols - 1)
        self.dy = (self.y1 - self.y0) / (self.rows - 1)
        self.xc, self.yc = (self.x0 + self.x1) / 2.0, (self.y0 + self.y1) / 2.0
        self.anchor_lat, self.anchor_lon = float(anchor_lat), float(anchor_lon)
        self.rotation_deg, self.scale = float(rotation_deg), float(scale)
        th = math.radians(self.rotation_deg)
        self._cos, self._sin = math.cos(th), math.sin(th)
        self._init_projection(self.anchor_lat, self.anchor_lon)

    @property
    def xs(self) -> np.ndarray:
        """Data-frame x of the cell centres (cols,), metres."""
        return self.x0 + self.dx * np.arange(self.cols)

    @property
    def ys(self) -> np.ndarray:
        """Data-frame y of the cell centres (rows,), metres."""
        return self.y0 + self.dy * np.arange(self.rows)

    def data_to_local(self, xd, yd) -> tuple[np.ndarray, np.ndarray]:
        """Data-frame metres -> local (east, north) Earth metres (scaled, rotated)."""
        a = (np.asarray(xd, float) - self.xc) * self.scale
        b = (np.asarray(yd, float) - self.yc) * self.scale
        return a * self._cos - b * self._sin, a * self._sin + b * self._cos

    def local_to_data(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        x, y = np.asarray(x, float), np.asarray(y, float)
        a = x * self._cos + y * self._sin
        b = -x * self._sin + y * self._cos
        return a / self.scale + self.xc, b / self.scale + self.yc

    def velocity_to_local(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Rotate data-frame velocity components to east/north (no scaling)."""
        u, v = np.asarray(u, float), np.asarray(v, float)
        return u * self._cos - v * self._sin, u * self._sin + v * self._cos

    def fcell_to_latlon(self, r, c):
        r, c = np.broadcast_arrays(np.asarray(r, float), np.asarray(c, float))
        x, y = self.data_to_local(self.x0 + self.dx * c, self.y0 + self.dy * r)
        return self.xy_to_latlon(x, y)

    def latlon_to_fcell(self, lat, lon):
        x, y = self.latlon_to_xy(lat, lon)
        xd, yd = self.local_to_data(x, y)
        return (yd - self.y0) / self.dy, (xd - self.x0) / self.dx

    def describe(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "x0": self.x0,
            "x1": self.x1,
            "y0": self.y0,
            "y1": self.y1,
            "rows": self.rows,
            "cols": self.cols,
            "anchor_lat": self.anchor_lat,
            "anchor_lon": self.anchor_lon,
            "rotation_deg": self.rotation_deg,
            "scale": self.scale,
        }

    def __repr__(self) -> str:
        d = self.describe()
        d.pop("kind")
        return "MetricRegionGrid(" + ", ".join(f"{k}={v}" for k, v in d.items()) + ")"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, MetricRegionGrid) and self.describe() == other.describe()

    def __hash__(self) -> int:
        return hash(tuple(self.describe().items()))


def grid_from_dict(d: dict[str, Any]) -> RegionGrid | MetricRegionGrid:
    """Inverse of ``describe()``."""
    d = dict(d)
    kind = d.pop("kind", "geographic")
    if kind == "geographic":
        return RegionGrid(**d)
    if kind == "metric":
        return MetricRegionGrid(**d)
    raise GeoError(f"unknown grid kind {kind!r} (expected 'geographic' or 'metric')")
