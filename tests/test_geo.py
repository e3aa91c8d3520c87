"""geo: cell <-> lat/lon <-> metres on the paper's grids, and grid paths -> waypoints.

Known answers come from pyproj's WGS84 ``Geod`` (independent of the aeqd
projection geo uses) and from the closed-form parallel-arc length N(phi) cos(phi) dlon.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import geo

WGS84_A = 6378137.0
WGS84_F = 1 / 298.257223563


@pytest.fixture(scope="module")
def geod():
    from pyproj import Geod

    return Geod(ellps="WGS84")


@pytest.fixture(scope="module")
def cyl_grid():
    """The cylinder crop placed on the sea, rotated so that every axis mixes lat and lon."""
    return geo.MetricRegionGrid(
        2.6, 11.4, -4.7, 4.7, 30, 30, anchor_lat=40.2, anchor_lon=-63.1, rotation_deg=30.0, scale=100.0
    )


# -- cells <-> lat/lon ----------------------------------------------------------------


def test_latlon_cell_round_trip_returns_cell_centres_exactly(na_grid):
    lat, lon = na_grid.centres_latlon()
    r, c = na_grid.latlon_to_cell(lat, lon)
    rr, cc = np.meshgrid(np.arange(30), np.arange(30), indexing="ij")
    np.testing.assert_array_equal(r, rr)
    np.testing.assert_array_equal(c, cc)
    # points anywhere inside a cell (up to 0.45 cell from the centre) map to it, and back to its centre
    rng = np.random.default_rng(0)
    jr, jc = rng.uniform(-0.45, 0.45, (2, 30, 30))
    r2, c2 = na_grid.latlon_to_cell(lat + jr * na_grid.dlat, lon + jc * na_grid.dlon)
    lat2, lon2 = na_grid.cell_to_latlon(r2, c2)
    np.testing.assert_array_equal(lat2, lat)
    np.testing.assert_array_equal(lon2, lon)
    assert lat[0, 0] == 39.360065 and lon[0, 0] == -64.24
    assert lat[-1, -1] == pytest.approx(41.130714, abs=1e-12) and lon[-1, -1] == pytest.approx(-61.92004, abs=1e-12)


def test_cell_size_matches_geodesic_distances_and_the_paper(na_grid, geod):
    lat, lon = na_grid.centres_latlon()
    # north-south neighbours, every column
    _, _, d_ns = geod.inv(lon[:-1].ravel(), lat[:-1].ravel(), lon[1:].ravel(), lat[1:].ravel())
    # east-west neighbours: closed form on the parallel, N(phi) cos(phi) dlon (geodesic shorter by ~1e-7)
    _, _, d_ew = geod.inv(lon[:, :-1].ravel(), lat[:, :-1].ravel(), lon[:, 1:].ravel(), lat[:, 1:].ravel())
    phi = np.radians(lat[:, :-1].ravel())
    e2 = WGS84_F * (2 - WGS84_F)
    arc = WGS84_A / np.sqrt(1 - e2 * np.sin(phi) ** 2) * np.cos(phi) * math.radians(na_grid.dlon)
    np.testing.assert_allclose(d_ew, arc, rtol=1e-5)
    dy, dx = na_grid.cell_size_m
    # geo's figure is the geodesic spacing at the grid centre
    mid = 14
    assert dy == pytest.approx(np.median(d_ns), rel=1e-3)
    assert dx == pytest.approx(
        0.5 * (d_ew.reshape(30, 29)[mid].mean() + d_ew.reshape(30, 29)[mid + 1].mean()), rel=1e-3
    )
    # every neighbour spacing within 1 % (north-south) / 1.5 % (east-west: cos(lat) varies 2.6 % over 1.8 deg)
    assert np.abs(d_ns / dy - 1).max() < 0.01
    assert np.abs(d_ew / dx - 1).max() < 0.015
    # The paper calls this a 6.6 km grid. Its own corner coordinates give 6.78 km (N-S) x 6.81 km
    # (E-W) at the centre, 2.9 % more: the paper's figure is rounded/approximate.
    assert dy == pytest.approx(6780.0, rel=0.01) and dx == pytest.approx(6807.0, rel=0.01)
    assert na_grid.mean_cell_size_m == pytest.approx(6600.0, rel=0.05)


@pytest.mark.parametrize("grid_name", ["na", "cyl"])
def test_metres_latlon_round_trip_below_1mm_and_distances_are_geodesic(grid_name, na_grid, cyl_grid, geod):
    g = na_grid if grid_name == "na" else cyl_grid
    rng = np.random.default_rng(1)
    r = rng.uniform(-0.5, g.rows - 0.5, 500)
    c = rng.uniform(-0.5, g.cols - 0.5, 500)
    lat, lon = g.fcell_to_latlon(r, c)
    x, y = g.latlon_to_xy(lat, lon)
    lat2, lon2 = g.xy_to_latlon(x, y)
    _, _, err = geod.inv(lon, lat, lon2, lat2)
    assert np.max(err) < 1e-3
    # azimuthal equidistant about the origin: |(x, y)| is the geodesic distance from the origin
    lat0, lon0 = g.origin
    _, _, d0 = geod.inv(np.full_like(lon, lon0), np.full_like(lat, lat0), lon, lat)
    np.testing.assert_allclose(np.hypot(x, y), d0, rtol=1e-7, atol=1e-4)
    # fractional cells survive lat/lon and metres
    r2, c2 = g.xy_to_fcell(x, y)
    np.testing.assert_allclose(r2, r, atol=1e-7)
    np.testing.assert_allclose(c2, c, atol=1e-7)


def test_metric_grid_cell_size_is_scaled_cfd_spacing(cyl_grid, geod):
    dy, dx = cyl_grid.cell_size_m
    assert dx == pytest.approx(8.8 / 29 * 100, rel=1e-4)
    assert dy == pytest.approx(9.4 / 29 * 100, rel=1e-4)
    la, lo = cyl_grid.cell_to_latlon([0, 0], [0, 29])  # one row: 29 cells along the rotated x axis
    _, _, d = geod.inv(lo[0], la[0], lo[1], la[1])
    assert d == pytest.approx(8.8 * 100, rel=1e-4)


@pytest.fixture(params=["scalar", "array"])
def scalar_and_array(request):
    """Wrap inputs as Python scalars or as 1-element arrays (pyproj's conftest idiom)."""
    if request.param == "scalar":
        return lambda v: v
    return lambda v: np.array([v])


def test_scalar_and_array_inputs_share_one_path(scalar_and_array, na_grid, cyl_grid):
    for g in (na_grid, cyl_grid):
        lat, lon = g.cell_to_latlon(scalar_and_array(7), scalar_and_array(11))
        lat_ref, lon_ref = g.centres_latlon()
        assert float(np.ravel(lat)[0]) == pytest.approx(lat_ref[7, 11], abs=1e-12)
        assert float(np.ravel(lon)[0]) == pytest.approx(lon_ref[7, 11], abs=1e-12)
        r, c = g.latlon_to_cell(lat, lon)
        assert np.shape(r) == np.shape(scalar_and_array(0)) and int(np.ravel(r)[0]) == 7 and int(np.ravel(c)[0]) == 11
        x, _y = g.latlon_to_xy(lat, lon)
        assert np.shape(x) == np.shape(scalar_and_array(0.0))


def test_outside_position_raises(na_grid):
    with pytest.raises(geo.GeoError, match="outside"):
        na_grid.latlon_to_cell(45.0, -63.0)


# -- grid paths -> waypoints -------------------------------------------------------------


def test_diagonal_and_two_straight_runs_merge_to_turn_points(na_grid):
    # diagonal NE run (0,0)->(2,2), east run ->(2,5), north run ->(4,5)
    path = [(0, 0), (1, 1), (2, 2), (2, 3), (2, 4), (2, 5), (3, 5), (4, 5)]
    cells = geo.waypoint_cells(na_grid, path)
    np.testing.assert_array_equal(cells, [(0, 0), (2, 2), (2, 5), (4, 5)])
    wps = geo.path_to_waypoints(na_grid, np.array(path))
    assert wps.shape == (4, 2) and wps.dtype == np.float64
    np.testing.assert_allclose(wps[:, 0], na_grid.lats[[0, 2, 2, 4]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(wps[:, 1], na_grid.lons[[0, 2, 5, 5]], rtol=0, atol=1e-12)


def test_metric_grid_waypoints_are_cell_centres(cyl_grid):
    path = [(5, 5), (5, 6), (5, 7), (6, 8), (7, 9), (7, 8)]
    wps = geo.path_to_waypoints(cyl_grid, path)
    lat, lon = cyl_grid.cell_to_latlon([5, 5, 7, 7], [5, 7, 9, 8])
    np.testing.assert_allclose(wps, np.column_stack([lat, lon]), rtol=0, atol=1e-12)


def test_single_cell_and_two_cell_paths(na_grid):
    np.testing.assert_array_equal(geo.waypoint_cells(na_grid, [(3, 4)]), [(3, 4)])
    np.testing.assert_array_equal(geo.waypoint_cells(na_grid, [(3, 4), (4, 4)]), [(3, 4), (4, 4)])


def test_repeated_cells_are_dropped_and_do_not_split_a_run(na_grid):
    p = geo.validate_path(na_grid, [(1, 1), (1, 2), (1, 2), (1, 3)])
    np.testing.assert_array_equal(p, [(1, 1), (1, 2), (1, 3)])
    np.testing.assert_array_equal(geo.waypoint_cells(na_grid, [(1, 1), (1, 2), (1, 2), (1, 3)]), [(1, 1), (1, 3)])
    # integral floats (e.g. from JSON) are accepted
    assert geo.validate_path(na_grid, np.array([[0.0, 0.0], [1.0, 1.0]])).dtype == np.int64


@pytest.mark.parametrize(
    "path, match",
    [
        ([(0, 0), (0, 1), (0, 3)], "not an 8-neighbour"),
        ([(0, 0), (2, 2)], "not an 8-neighbour"),
        ([(29, 29), (30, 30)], "outside the 30x30 grid"),
        ([(-1, 0), (0, 0)], "outside the 30x30 grid"),
        ([(0, 0, 0), (1, 1, 1)], "shape"),
        ([1, 2, 3], "shape"),
        (np.zeros((0, 2), int), "empty"),
        ([(0.0, 0.5), (1.0, 1.0)], "not an integer"),
        ([(0.0, np.nan), (1.0, 1.0)], "not an integer"),
        (np.array([[True, False]]), "integer"),
        ([("a", "b")], "integer"),
    ],
)
def test_invalid_paths_raise_geo_error(na_grid, path, match):
    with pytest.raises(geo.GeoError, match=match):
        geo.path_to_waypoints(na_grid, path)
