"""Geometry of non-rectilinear ocean-model grids: grid-axis angles, C-grid averaging, regridding.

Pure numpy/scipy/pyproj (no file I/O); :mod:`passt_mav.fields.importers` reads the files and
calls these. Conventions used throughout:

* A node's **grid angle** ``theta`` (radians) is the angle of the grid's x axis (increasing
  x index / x coordinate) measured counter-clockwise from east on the ground, i.e. ROMS's
  ``angle`` ("angle between XI-axis and EAST"). The grid's y axis points ``theta + pi/2``
  (orthogonal grids: conformal projections, ROMS, NEMO).
* Grid-relative velocity components ``(ux, uy)`` (m/s along the grid's x and y axes) become
  east/north components by the rotation ``u_east = ux cos(theta) - uy sin(theta)``,
  ``v_north = ux sin(theta) + uy cos(theta)``.
* Geographic positions are WGS84 degrees; azimuths are degrees clockwise from north.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import FieldError

__all__ = [
    "MAX_NON_ORTHOGONALITY_DEG",
    "angles_from_crs",
    "angles_from_latlon",
    "cgrid_to_rho",
    "regrid_scattered",
    "rotate_to_east_north",
]

#: degrees: grid x/y axes whose ground directions are farther from perpendicular than this leave
#: "the component along x" ambiguous (covariant vs contravariant); such grids are refused
MAX_NON_ORTHOGONALITY_DEG = 1.0
#: fraction of a barycentric stencil's weight that may fall on missing nodes (renormalised below it;
#: the same rule as the rectilinear importer's bilinear stencils)
MISSING_WEIGHT_TOL = 1e-3


def _sphere():
    """A spherical ``pyproj.Geod`` (azimuths on a sphere do not depend on its radius)."""
    from pyproj import Geod

    return Geod(a=6371000.0, b=6371000.0)


def _theta_from_azimuth(az_deg: np.ndarray) -> np.ndarray:
    """Azimuth (degrees clockwise from north) -> angle (radians counter-clockwise from east)."""
    return np.deg2rad(90.0 - np.asarray(az_deg, float))


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a, float) + 180.0) % 360.0 - 180.0


def _axis_azimuths(geod, lon_a, lat_a, lon_b, lat_b) -> np.ndarray:
    """Azimuth (degrees from north) of the direction a -> b at their midpoint, from the geodesic on
    ``geod`` (a ``pyproj.Geod``): the mean of the forward azimuth at ``a`` and the reversed back
    azimuth at ``b`` (exact for a short segment, whose azimuth turns linearly along it)."""
    az12, az21, _ = geod.inv(lon_a, lat_a, lon_b, lat_b)
    az12 = np.asarray(az12, float)
    fwd_b = np.asarray(az21, float) + 180.0
    return az12 + 0.5 * _wrap_deg(fwd_b - az12)


def _check_orthogonal(theta_x: np.ndarray, theta_y: np.ndarray, where: str) -> float:
    """Largest departure (degrees) of the y axis from ``theta_x + 90 deg`` over finite nodes; a
    :class:`FieldError` naming ``where`` above :data:`MAX_NON_ORTHOGONALITY_DEG`."""
    dev = np.abs(_wrap_deg(np.rad2deg(theta_y - theta_x) - 90.0))
    dev = dev[np.isfinite(dev)]
    worst = float(dev.max()) if dev.size else 0.0
    if worst > MAX_NON_ORTHOGONALITY_DEG:
        raise FieldError(
            f"{where}: the grid's x and y axes are up to {worst:.2g} deg from perpendicular on the ground "
            f"(above {MAX_NON_ORTHOGONALITY_DEG:g} deg), so grid-relative velocity components are ambiguous; "
            "only orthogonal grids (conformal projections, ROMS, NEMO) are rotated"
        )
    return worst


def angles_from_crs(crs, x: np.ndarray, y: np.ndarray, *, where: str = "grid_mapping") -> tuple[np.ndarray, float]:
    """Grid angles of a CF projected grid from its coordinate reference system.

    Args:
        crs: the ``pyproj.CRS`` of the grid mapping (projected in metres, or a rotated pole in degrees).
        x, y: 2-D projection coordinates of the nodes, in the CRS's units (metres or degrees), shape
            ``(ny, nx)``: x varies along the last axis, y along the first (either way round).
        where: names the file in messages.

    Returns:
        ``(theta, worst)``: ``theta`` ``(ny, nx)`` radians counter-clockwise from east of the
        grid's x axis at each node, and the largest departure (degrees) of the y axis from
        perpendicular. The x axis direction is measured by projecting two points a short step
        (1e-4 of the node spacing) either side of each node along x back to WGS84 and taking the
        geodesic azimuth between them, on the CRS's own ellipsoid for a projection (conformal on
        that ellipsoid) and on a sphere for a rotated pole (whose rotation treats latitude and
        longitude as spherical angles); the y axis likewise, and a non-orthogonal grid is a
        :class:`FieldError` (see :data:`MAX_NON_ORTHOGONALITY_DEG`).
    """
    from pyproj import Transformer

    x = np.asarray(x, float)
    y = np.asarray(y, float)
    to_geo = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    geod = _sphere() if crs.is_geographic else (crs.get_geod() or _sphere())
    dx = _step(x, axis=-1)
    dy = _step(y, axis=-2)

    def azimuth(x0, y0, x1, y1):
        lo0, la0 = to_geo.transform(x0, y0)
        lo1, la1 = to_geo.transform(x1, y1)
        return _axis_azimuths(geod, np.ravel(lo0), np.ravel(la0), np.ravel(lo1), np.ravel(la1)).reshape(x.shape)

    theta_x = _theta_from_azimuth(azimuth(x - dx, y, x + dx, y))
    theta_y = _theta_from_azimuth(azimuth(x, y - dy, x, y + dy))
    worst = _check_orthogonal(theta_x, theta_y, where)
    return theta_x, worst


def _step(c: np.ndarray, axis: int) -> float:
    """A small positive coordinate step along ``axis``: 1e-4 of the median node spacing. Positive
    whichever way the file stores the axis: a CF x/y velocity is positive toward increasing
    coordinate (not index), e.g. on a polar-stereographic file whose y runs top-down."""
    d = np.diff(c, axis=axis)
    d = d[np.isfinite(d) & (d != 0)]
    if d.size == 0:
        raise FieldError("projection coordinates do not vary along an axis")
    return 1e-4 * abs(float(np.median(d)))


def angles_from_latlon(lat: np.ndarray, lon: np.ndarray, *, where: str = "grid") -> tuple[np.ndarray, float]:
    """Grid angles of a curvilinear grid from its 2-D latitudes/longitudes alone (no ``angle``
    variable, no grid mapping: NEMO-like files).

    ``lat``, ``lon`` are ``(ny, nx)`` degrees with the x index along the last axis. The x axis
    at a node is the direction, on a sphere, from its x neighbour before it to the one after it
    (one-sided at the edges), the y axis likewise (ocean models' curvilinear grids are spherical:
    NEMO computes its own rotation angles on the sphere the same way); returns ``(theta, worst)`` as
    :func:`angles_from_crs` (radians counter-clockwise from east; degrees from perpendicular),
    refusing non-orthogonal grids (checked at the inner nodes). The centred difference's error
    is second order in the node spacing (about 1e-3 deg on a 10 km polar-stereographic grid at
    71 deg N, where the grid turns 1 deg per node); the one-sided edge nodes lie outside the
    target region's cells by the importer's window margin.
    """
    lat = np.asarray(lat, float)
    lon = np.asarray(lon, float)
    if lat.shape[0] < 2 or lat.shape[1] < 2:
        raise FieldError(f"{where}: a curvilinear grid needs at least 2x2 nodes")
    geod = _sphere()

    def along(axis: int) -> np.ndarray:
        n = lat.shape[axis]
        i0 = np.clip(np.arange(n) - 1, 0, n - 1)
        i1 = np.clip(np.arange(n) + 1, 0, n - 1)
        la0, lo0 = np.take(lat, i0, axis=axis), np.take(lon, i0, axis=axis)
        la1, lo1 = np.take(lat, i1, axis=axis), np.take(lon, i1, axis=axis)
        return _theta_from_azimuth(
            _axis_azimuths(geod, lo0.ravel(), la0.ravel(), lo1.ravel(), la1.ravel()).reshape(lat.shape)
        )

    theta_x, theta_y = along(1), along(0)
    # checked where both differences are centred: a one-sided edge difference is first order only
    inner = (slice(1, -1) if lat.shape[0] > 2 else slice(None), slice(1, -1) if lat.shape[1] > 2 else slice(None))
    worst = _check_orthogonal(theta_x[inner], theta_y[inner], where)
    return theta_x, worst


def rotate_to_east_north(ux: np.ndarray, uy: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grid-relative components (m/s along the grid's x and y axes) -> (east, north) m/s, with
    ``theta`` the x axis's angle counter-clockwise from east (radians, broadcast over leading time
    axes). NaN stays NaN."""
    c, s = np.cos(theta), np.sin(theta)
    return ux * c - uy * s, ux * s + uy * c


def cgrid_to_rho(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arakawa C-grid velocities averaged to the cell centres (ROMS rho points).

    Args:
        u: ``(..., ny, nx + 1)``: the x component at the faces either side of each of ``nx`` centres
            (face ``k`` is between centres ``k - 1`` and ``k``; missing faces NaN).
        v: ``(..., ny + 1, nx)``: the y component at the faces below/above each centre.

    Returns:
        ``(u_c, v_c)`` ``(..., ny, nx)``: the mean of the two faces of each centre; a centre with a
        missing face (land, or beyond the file's edge) is NaN, never a one-sided value.
    """
    return 0.5 * (u[..., :, :-1] + u[..., :, 1:]), 0.5 * (v[..., :-1, :] + v[..., 1:, :])


def regrid_scattered(lat: np.ndarray, lon: np.ndarray, values: np.ndarray, grid) -> tuple[np.ndarray, int]:
    """Values on a curvilinear source grid's nodes, interpolated linearly onto ``grid``'s cells.

    Args:
        lat, lon: ``(ny, nx)`` node positions (degrees; nodes with non-finite positions are dropped).
        values: ``(T, ny, nx, 2)`` east/north m/s at the nodes, NaN where missing.
        grid: the target :class:`geo.RegionGrid`.

    Returns:
        ``(data, n_dropped)``: ``(T, 2, rows, cols)`` float32 and the count of Delaunay triangles
        dropped as longer than the source grid's cells. Nodes and cell centres are projected to
        the target grid's local metric frame (azimuthal equidistant about its centre) and
        triangulated (Delaunay); each cell takes the barycentric (linear) mean of its triangle's
        three nodes. Like the rectilinear importer's bilinear stencils, a cell whose triangle puts
        more than :data:`MISSING_WEIGHT_TOL` of its weight on missing nodes is NaN (below that the
        valid weights are renormalised), and cells outside the source nodes' hull, or inside a
        triangle with an edge longer than 1.5 source cell diagonals (spanning a gap or a concave
        grid boundary), are NaN: nothing is extrapolated.
    """
    from threadpoolctl import threadpool_limits

    T = values.shape[0]
    X, Y = grid.latlon_to_xy(lat, lon)
    X = np.asarray(X, float)
    Y = np.asarray(Y, float)
    ok_pos = np.isfinite(X) & np.isfinite(Y)
    pts = np.column_stack([X[ok_pos], Y[ok_pos]])
    vals = values[:, ok_pos, :]  # (T, n, 2)
    valid = np.isfinite(vals).all(axis=-1)  # (T, n)
    num = np.where(valid[..., None], vals, 0.0).transpose(1, 0, 2).reshape(pts.shape[0], T * 2)
    cols = np.concatenate([num, valid.T.astype(np.float64)], axis=1)  # (n, 3T)
    # one BLAS thread: locating the cells computes a tiny LAPACK solve per triangle, which a threaded
    # BLAS turns into seconds of thread start-up (1.5 s vs 0.05 s for 14 000 nodes on a busy machine)
    with threadpool_limits(1):
        return _regrid_on_triangles(pts, cols, X, Y, T, grid)


def _regrid_on_triangles(pts, cols, X, Y, T: int, grid) -> tuple[np.ndarray, int]:
    """:func:`regrid_scattered` after the nodes are projected: ``pts`` ``(n, 2)`` metres, ``cols``
    ``(n, 3T)`` (T*2 zero-filled values, then T valid-node weights), ``X``/``Y`` the structured node
    positions (for the longest cell diagonal)."""
    # scipy's LinearNDInterpolator on one Delaunay triangulation interpolates the values and the
    # valid-node weights together (extra columns), which is how the missing-node rule is applied;
    # griddata would hide the triangulation, whose over-long triangles are dropped here
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import Delaunay

    max_edge = 1.5 * _max_cell_diagonal(X, Y)
    try:
        tri = Delaunay(pts)
    except Exception as exc:  # noqa: BLE001 - qhull's errors (too few / collinear nodes) mean an unusable window
        raise FieldError(f"cannot triangulate the source nodes in the region: {str(exc).splitlines()[0]}") from None
    edges = np.stack(
        [
            np.linalg.norm(tri.points[tri.simplices[:, a]] - tri.points[tri.simplices[:, b]], axis=1)
            for a, b in ((0, 1), (1, 2), (2, 0))
        ],
        axis=1,
    ).max(axis=1)
    long_tri = edges > max_edge
    gx, gy = grid.centres_xy()
    q = np.column_stack([np.ravel(gx), np.ravel(gy)])
    out = LinearNDInterpolator(tri, cols, fill_value=np.nan)(q)  # (cells, 3T)
    simplex = tri.find_simplex(q)
    inside = (simplex >= 0) & ~long_tri[np.clip(simplex, 0, None)]
    wv = out[:, 2 * T :]  # (cells, T): weight on valid nodes
    ok = inside[:, None] & np.isfinite(wv) & (wv >= 1.0 - MISSING_WEIGHT_TOL)
    with np.errstate(invalid="ignore", divide="ignore"):
        res = out[:, : 2 * T].reshape(-1, T, 2) / wv[..., None]
    res = np.where(ok[..., None], res, np.nan)
    data = res.reshape(grid.rows, grid.cols, T, 2).transpose(2, 3, 0, 1).astype(np.float32)
    return data, int(np.count_nonzero(long_tri))


def _max_cell_diagonal(X: np.ndarray, Y: np.ndarray) -> float:
    """The longest diagonal (metres) of the structured grid's cells whose four corners are finite."""
    d1 = np.hypot(X[1:, 1:] - X[:-1, :-1], Y[1:, 1:] - Y[:-1, :-1])
    d2 = np.hypot(X[1:, :-1] - X[:-1, 1:], Y[1:, :-1] - Y[:-1, 1:])
    d = np.concatenate([d1[np.isfinite(d1)], d2[np.isfinite(d2)]])
    if d.size == 0:
        raise FieldError("the source grid has no cell with four positioned corners in the region")
    return float(d.max())
