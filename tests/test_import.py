"""Importing model and radar current files: detection, units, surface, times, region, regridding."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import xarray as xr

import geo
from passt_mav.errors import FieldError
from passt_mav.fields.importers import coverage_report, import_currents, velocity_scale

# analytic linear field (bilinear interpolation reproduces it exactly)
A_U = (0.3, 0.05, -0.02, 0.01)  # u = a + b*lat + c*lon + d*hours  (m/s)
A_V = (-0.2, -0.03, 0.04, -0.005)


def _lin(coef, lat, lon, hours):
    a, b, c, d = coef
    return a + b * (lat - 40.0) + c * (lon + 63.0) + d * hours


def _source_grid(lon_convention="180", descending_lat=False):
    lat = np.round(np.arange(38.0, 42.0001, 0.08), 6)
    lon = np.round(np.arange(-66.0, -60.0001, 0.08), 6)
    if descending_lat:
        lat = lat[::-1]
    lon_file = lon % 360.0 if lon_convention == "360" else lon
    return lat, lon, lon_file


def _hycom_file(path, *, lon_convention="360", descending_lat=False, land=True, packed=True, step_h=1, n_t=12):
    """HYCOM/RTOFS-like: water_u/water_v (time, depth, lat, lon) in m/s, packed int16, land NaN."""
    lat, lon, lon_file = _source_grid(lon_convention, descending_lat)
    hours = np.arange(n_t) * step_h
    depth = np.array([0.0, 2.0, 4.0, 10.0])
    LA, LO = np.meshgrid(lat, lon, indexing="ij")
    u = np.empty((n_t, depth.size, lat.size, lon.size))
    v = np.empty_like(u)
    for k, h in enumerate(hours):
        for d in range(depth.size):
            # deeper levels differ by 0.5 m/s so picking the wrong level is visible
            u[k, d] = _lin(A_U, LA, LO, h) + 0.5 * d
            v[k, d] = _lin(A_V, LA, LO, h) - 0.5 * d
    if land:
        # a land block: nodes lat 40.00..40.16, lon -63.04..-62.88
        m = (LA >= 39.999) & (LA <= 40.161) & (LO >= -63.041) & (LO <= -62.879)
        u[:, :, m] = np.nan
        v[:, :, m] = np.nan
    times = pd.Timestamp("2018-03-01T00:00:00") + pd.to_timedelta(hours, unit="h")
    ds = xr.Dataset(
        {
            "water_u": (
                ("time", "depth", "lat", "lon"),
                u,
                {
                    "units": "m/s",
                    "long_name": "Eastward Water Velocity",
                    "standard_name": "eastward_sea_water_velocity",
                },
            ),
            "water_v": (
                ("time", "depth", "lat", "lon"),
                v,
                {
                    "units": "m/s",
                    "long_name": "Northward Water Velocity",
                    "standard_name": "northward_sea_water_velocity",
                },
            ),
        },
        coords={
            "time": ("time", times),
            "depth": ("depth", depth, {"units": "m", "positive": "down", "axis": "Z"}),
            "lat": ("lat", lat, {"units": "degrees_north", "standard_name": "latitude"}),
            "lon": ("lon", lon_file, {"units": "degrees_east", "standard_name": "longitude"}),
        },
    )
    enc = {"time": {"units": "hours since 2000-01-01 00:00:00", "calendar": "gregorian"}}
    if packed:
        for k in ("water_u", "water_v"):
            enc[k] = {"dtype": "int16", "scale_factor": 0.001, "add_offset": 0.0, "_FillValue": np.int16(-30000)}
    ds.to_netcdf(path, encoding=enc)
    return path


def _copernicus_file(path, *, n_days=4):
    """Copernicus Marine-like: uo/vo (time, depth, latitude, longitude), m s-1, daily means."""
    lat, lon, _ = _source_grid()
    depth = np.array([0.494025, 1.541375, 2.645669])
    hours = np.arange(n_days) * 24.0
    LA, LO = np.meshgrid(lat, lon, indexing="ij")
    uo = np.stack([np.stack([_lin(A_U, LA, LO, h) + 0.3 * d for d in range(3)]) for h in hours]).astype(np.float32)
    vo = np.stack([np.stack([_lin(A_V, LA, LO, h) + 0.3 * d for d in range(3)]) for h in hours]).astype(np.float32)
    times = pd.Timestamp("2018-03-01T12:00:00") + pd.to_timedelta(hours, unit="h")
    ds = xr.Dataset(
        {
            "uo": (
                ("time", "depth", "latitude", "longitude"),
                uo,
                {"units": "m s-1", "standard_name": "eastward_sea_water_velocity"},
            ),
            "vo": (
                ("time", "depth", "latitude", "longitude"),
                vo,
                {"units": "m s-1", "standard_name": "northward_sea_water_velocity"},
            ),
        },
        coords={
            "time": ("time", times),
            "depth": ("depth", depth, {"units": "m", "positive": "down", "standard_name": "depth"}),
            "latitude": ("latitude", lat.astype(np.float32), {"units": "degrees_north", "standard_name": "latitude"}),
            "longitude": ("longitude", lon.astype(np.float32), {"units": "degrees_east", "standard_name": "longitude"}),
        },
    )
    ds.to_netcdf(path, encoding={"time": {"units": "hours since 1950-01-01", "calendar": "standard"}})
    return path


# target grid: 11 x 16 cells well inside the source, centres between source nodes
TARGET = geo.RegionGrid(39.53, -64.57, 40.53, -62.07, 11, 16)


def _expected(grid, hours, coef):
    lat, lon = grid.centres_latlon()
    return np.stack([_lin(coef, lat, lon, h) for h in hours])


@pytest.mark.parametrize("lon_convention", ["360", "180"])
@pytest.mark.parametrize("descending_lat", [False, True])
def test_hycom_layout_linear_field_exact(tmp_path, lon_convention, descending_lat):
    p = _hycom_file(tmp_path / "hycom.nc", lon_convention=lon_convention, descending_lat=descending_lat, land=False)
    f = import_currents(p, TARGET)
    assert f.shape == (12, 2, 11, 16)
    assert f.attrs["variables"] == ["water_u", "water_v"]
    assert f.attrs["depth_m"] == 0.0
    assert f.time_origin == "2018-03-01T00:00:00Z"
    np.testing.assert_allclose(f.times, np.arange(12) * 3600.0)
    # packed int16 with scale 0.001: values are exact to half a count
    np.testing.assert_allclose(f.u, _expected(TARGET, range(12), A_U), atol=6e-4)
    np.testing.assert_allclose(f.v, _expected(TARGET, range(12), A_V), atol=6e-4)
    assert f.coverage == 1.0


def test_land_nan_stays_masked_and_stencil_rule(tmp_path):
    p = _hycom_file(tmp_path / "hycom.nc", land=True)
    grid = geo.RegionGrid(39.5, -64.0, 40.7, -62.0, 31, 26)  # spacing 0.04 / 0.08 deg
    f = import_currents(p, grid)
    lat, lon = grid.centres_latlon()
    # cells whose bracketing source nodes include a land node: lat in (39.92, 40.24), lon in (-63.12, -62.80)
    touches = (lat > 39.92 + 1e-6) & (lat < 40.24 - 1e-6) & (lon > -63.12 + 1e-6) & (lon < -62.80 - 1e-6)
    assert touches.sum() > 0
    np.testing.assert_array_equal(f.mask[0], touches)
    # everything else is the exact linear value (nothing was zero-filled)
    exp = _expected(grid, [0], A_U)[0]
    np.testing.assert_allclose(f.u[0][~touches], exp[~touches], atol=6e-4)
    assert np.isnan(f.data[:, :, touches]).all()
    rep = coverage_report(f)
    assert rep["coverage"] == pytest.approx(1 - touches.mean())
    assert rep["cells_all"] == pytest.approx(1 - touches.mean())
    assert f.attrs["coverage"] == pytest.approx(rep["coverage"], abs=1e-6)


def test_copernicus_surface_and_coarse_times(tmp_path):
    p = _copernicus_file(tmp_path / "cmems.nc")
    f = import_currents(p, TARGET, start="2018-03-02T00:00Z", hours=72)
    assert f.attrs["variables"] == ["uo", "vo"]
    assert f.attrs["depth_m"] == pytest.approx(0.494025)
    # daily file: its own times are kept (12Z on Mar 2, 3, 4), no interpolation
    assert f.n_times == 3
    assert f.time_origin == "2018-03-02T12:00:00Z"
    np.testing.assert_allclose(f.times, [0.0, 86400.0, 172800.0])
    assert "coarser than hourly" in f.attrs["time_selection"]
    # float32 lat/lon nodes in the file: bilinear of a linear field exact to float32 rounding
    np.testing.assert_allclose(f.u, _expected(TARGET, [24.0, 48.0, 72.0], A_U), atol=2e-5)
    np.testing.assert_allclose(f.v, _expected(TARGET, [24.0, 48.0, 72.0], A_V), atol=2e-5)


def test_time_window_hourly(tmp_path):
    p = _hycom_file(tmp_path / "hycom.nc", land=False)
    f = import_currents(p, TARGET, start="2018-03-01T03:00:00Z", hours=5)
    assert f.n_times == 5
    assert f.time_origin == "2018-03-01T03:00:00Z"
    np.testing.assert_allclose(f.u, _expected(TARGET, range(3, 8), A_U), atol=6e-4)
    # a window running past the end keeps what exists and says so
    g = import_currents(p, TARGET, start="2018-03-01T08:00Z", hours=10)
    assert g.n_times == 4 and "only 4 of the 10 hourly snapshots" in g.attrs["time_selection"]
    # past the end: FieldError naming the file's span
    with pytest.raises(FieldError, match="covers 2018-03-01T00:00:00Z..2018-03-01T11:00:00Z"):
        import_currents(p, TARGET, start="2018-04-01T00:00Z", hours=5)
    with pytest.raises(FieldError, match="ISO-8601"):
        import_currents(p, TARGET, start="yesterday", hours=5)


def test_finer_than_hourly_keeps_whole_hours(tmp_path):
    lat, lon, _ = _source_grid()
    minutes = np.arange(0, 180, 15)
    LA, LO = np.meshgrid(lat, lon, indexing="ij")
    u = np.stack([_lin(A_U, LA, LO, m / 60) for m in minutes])
    ds = xr.Dataset(
        {
            "u": (("time", "lat", "lon"), u * 100, {"units": "cm s-1"}),
            "v": (("time", "lat", "lon"), -u * 100, {"units": "cm s-1"}),
        },
        coords={
            "time": pd.Timestamp("2018-03-01") + pd.to_timedelta(minutes, unit="min"),
            "lat": ("lat", lat, {"units": "degrees_north"}),
            "lon": ("lon", lon, {"units": "degrees_east"}),
        },
    )
    p = tmp_path / "radar15.nc"
    ds.to_netcdf(p)
    f = import_currents(p, TARGET)
    np.testing.assert_allclose(f.times, [0.0, 3600.0, 7200.0])
    assert "finer than hourly" in f.attrs["time_selection"]
    np.testing.assert_allclose(f.u, _expected(TARGET, [0, 1, 2], A_U), atol=1e-5)


def test_region_partly_outside_is_nan_and_disjoint_is_error(tmp_path):
    p = _hycom_file(tmp_path / "hycom.nc", land=False, n_t=2)
    slat, slon, _ = _source_grid()
    assert slat[-1] == pytest.approx(42.0) and slon[-1] == pytest.approx(-60.08)
    grid = geo.RegionGrid(41.5, -61.0, 42.5, -59.0, 11, 21)  # the source ends inside it
    f = import_currents(p, grid)
    lat, lon = grid.centres_latlon()
    inside = (lat <= slat[-1] + 1e-9) & (lon <= slon[-1] + 1e-9)
    np.testing.assert_array_equal(~f.mask[0], inside)
    assert 0 < f.coverage < 1
    # a grid spanning exactly the source's outer nodes keeps its edge cells (no rounding loss)
    full = geo.RegionGrid(slat[0], slon[0], slat[-1], slon[-1], 13, 17)
    assert import_currents(p, full).coverage == 1.0
    with pytest.raises(FieldError, match="does not overlap"):
        import_currents(p, geo.north_atlantic_grid().__class__(10.0, 10.0, 11.0, 11.0, 5, 5))


def test_rtofs_like_2d_separable_coordinates(tmp_path):
    lat, lon, _ = _source_grid()
    LA, LO = np.meshgrid(lat, lon, indexing="ij")
    u = _lin(A_U, LA, LO, 0.0)[None, None]
    v = _lin(A_V, LA, LO, 0.0)[None, None]
    ds = xr.Dataset(
        {
            "u_velocity": (("MT", "Depth", "Y", "X"), u, {"units": "m/s"}),
            "v_velocity": (("MT", "Depth", "Y", "X"), v, {"units": "m/s"}),
        },
        coords={
            "MT": ("MT", [pd.Timestamp("2018-03-01T06:00")]),
            "Depth": ("Depth", [0.0], {"units": "m"}),
            "Latitude": (("Y", "X"), LA, {"units": "degrees_north"}),
            "Longitude": (("Y", "X"), LO % 360.0, {"units": "degrees_east"}),
        },
    )
    p = tmp_path / "rtofs.nc"
    ds.to_netcdf(p)
    f = import_currents(p, TARGET)
    assert f.n_times == 1 and f.time_origin == "2018-03-01T06:00:00Z"
    np.testing.assert_allclose(f.u[0], _expected(TARGET, [0], A_U)[0], atol=1e-9 + 1e-6)


@pytest.mark.parametrize(
    "units,factor",
    [
        ("m/s", 1.0),
        ("m s-1", 1.0),
        ("m s**-1", 1.0),
        ("m.s-1", 1.0),
        ("meters per second", 1.0),
        ("meter second-1", 1.0),
        ("cm/s", 0.01),
        ("cm s-1", 0.01),
        ("CM/S", 0.01),
        ("cm s^-1", 0.01),
        ("mm/s", 0.001),
        ("knots", 1852 / 3600),
    ],
)
def test_velocity_units(units, factor):
    assert velocity_scale(units) == pytest.approx(factor)


@pytest.mark.parametrize("units", ["furlongs/fortnight", "m", "degC", "", None, "m2 s-1"])
def test_unknown_units_rejected(units):
    with pytest.raises(FieldError):
        velocity_scale(units)


def test_file_errors(tmp_path):
    with pytest.raises(FieldError, match="not found"):
        import_currents(tmp_path / "nope.nc", TARGET)
    bad = tmp_path / "bad.nc"
    bad.write_text("not a netcdf file")
    with pytest.raises(FieldError, match="cannot read"):
        import_currents(bad, TARGET)
    ds = xr.Dataset({"temp": (("lat", "lon"), np.zeros((2, 2)))}, coords={"lat": [40.0, 41.0], "lon": [-63.0, -62.0]})
    ds.to_netcdf(tmp_path / "temp.nc")
    with pytest.raises(FieldError, match="no current variables found.*temp"):
        import_currents(tmp_path / "temp.nc", TARGET)
    p = _hycom_file(tmp_path / "h.nc", land=False, n_t=2)
    with pytest.raises(FieldError, match="'uu' not in file"):
        import_currents(p, TARGET, variables=("uu", "vv"))
    with pytest.raises(FieldError, match="unknown velocity units"):
        import_currents(p, TARGET, units="leagues")


# -- the real MARACOOS HF-radar file --------------------------------------------------
# raw nodes 95..124 (lat) x 70..99 (lon): a 30x30 window with 80 % of cells valid at every hour
I0, J0, N = 95, 70, 30


@pytest.fixture(scope="module")
def radar(hf_radar_path):
    with xr.open_dataset(hf_radar_path) as ds:
        raw_u = ds["u"].values[:, 0]  # (13, 187, 196) cm/s
        raw_v = ds["v"].values[:, 0]
        lat = ds["lat"].values.astype(float)
        lon = ds["lon"].values.astype(float)
        units = ds["u"].attrs["units"]
    return raw_u, raw_v, lat, lon, units


def test_hf_radar_aligned_grid_reproduces_raw_cells(hf_radar_path, radar):
    raw_u, raw_v, lat, lon, units = radar
    assert units == "cm/s"
    grid = geo.RegionGrid(lat[I0], lon[J0], lat[I0 + N - 1], lon[J0 + N - 1], N, N)
    f = import_currents(hf_radar_path, grid)
    assert f.n_times == 13 and f.time_origin == "2018-03-01T00:00:00Z"
    assert f.attrs["units_factor_to_m_s"] == [0.01, 0.01]
    assert f.attrs["depth_m"] == 0.0
    win = (slice(None), slice(I0, I0 + N), slice(J0, J0 + N))
    ru, rv = raw_u[win] * 0.01, raw_v[win] * 0.01
    # the NaN gaps of the radar are exactly the mask (no cell filled, none lost)
    np.testing.assert_array_equal(f.mask, ~(np.isfinite(ru) & np.isfinite(rv)))
    # cell centres coincide with raw nodes up to float32 rounding of the file's
    # coordinates (< 2e-3 of a cell): values equal raw x 0.01 to 1e-4 m/s
    np.testing.assert_allclose(f.u, ru, atol=1e-4, equal_nan=True)
    np.testing.assert_allclose(f.v, rv, atol=1e-4, equal_nan=True)
    # one known cell, read straight from the file
    k, r, c = 5, 12, 7
    assert np.isfinite(raw_u[k, I0 + r, J0 + c])
    assert f.u[k, r, c] == pytest.approx(raw_u[k, I0 + r, J0 + c] * 0.01, abs=1e-4)
    assert f.coverage == pytest.approx(np.isfinite(ru).mean())


def test_hf_radar_between_nodes_bilinear(hf_radar_path, radar):
    raw_u, _, lat, lon, _ = radar
    # centres half-way between raw nodes: value = mean of the 4 nodes where all exist, NaN otherwise
    grid = geo.RegionGrid(
        (lat[I0] + lat[I0 + 1]) / 2,
        (lon[J0] + lon[J0 + 1]) / 2,
        (lat[I0 + 19] + lat[I0 + 20]) / 2,
        (lon[J0 + 19] + lon[J0 + 20]) / 2,
        20,
        20,
    )
    f = import_currents(hf_radar_path, grid, start="2018-03-01T02:00:00Z", hours=3)
    assert f.n_times == 3
    w = raw_u[2:5, I0 : I0 + 21, J0 : J0 + 21] * 0.01
    mean4 = (w[:, :-1, :-1] + w[:, 1:, :-1] + w[:, :-1, 1:] + w[:, 1:, 1:]) / 4
    np.testing.assert_array_equal(np.isnan(f.u), np.isnan(mean4))
    np.testing.assert_allclose(f.u, mean4, atol=2e-3, equal_nan=True)
    assert np.isnan(f.u).any() and np.isfinite(f.u).any()


def test_non_standard_calendar_times(tmp_path):
    # model output in a 365-day calendar decodes to cftime objects; times still come out in UTC seconds
    lat, lon, _ = _source_grid()
    u = np.full((3, lat.size, lon.size), 0.1)
    ds = xr.Dataset(
        {"uo": (("time", "lat", "lon"), u, {"units": "m s-1"}), "vo": (("time", "lat", "lon"), -u, {"units": "m s-1"})},
        coords={
            "time": ("time", [0.0, 1.0, 2.0], {"units": "hours since 2018-03-01 06:00", "calendar": "noleap"}),
            "lat": ("lat", lat, {"units": "degrees_north"}),
            "lon": ("lon", lon, {"units": "degrees_east"}),
        },
    )
    ds.to_netcdf(tmp_path / "noleap.nc")
    f = import_currents(tmp_path / "noleap.nc", TARGET)
    assert f.time_origin == "2018-03-01T06:00:00Z"
    np.testing.assert_allclose(f.times, [0.0, 3600.0, 7200.0])
    np.testing.assert_allclose(f.v, -0.1, atol=1e-7)


# -- issue 13 item 6: a real 504-hour file already on the paper's grid imports without loss ------
def _paper_grid_file(path, *, units="1", lon_shift=1e-5, fill=None, lon_offset=0.0):
    """Like the file that lost 6.7 %: the 30x30 North Atlantic grid, velocity variables *named*
    eastward/northward_sea_water_velocity with no standard_name attribute, float32 coordinates
    whose edge longitudes lie ``lon_shift`` deg inside the grid's edges, hourly times."""
    na = geo.north_atlantic_grid()
    lat = na.lats.astype(np.float32)
    lon = na.lons.copy() + lon_offset
    lon[0] += lon_shift
    lon[-1] -= lon_shift
    lon = lon.astype(np.float32)
    rng = np.random.default_rng(3)
    u = rng.normal(0, 0.3, (6, 30, 30)).astype(np.float32)
    v = rng.normal(0, 0.3, (6, 30, 30)).astype(np.float32)
    if fill is not None:
        u[:, 0:3, 0:4] = fill
        v[:, 0:3, 0:4] = fill
    times = pd.Timestamp("2018-03-01T00:00:00") + pd.to_timedelta(np.arange(6), unit="h")
    attrs = {} if units is None else {"units": units}
    ds = xr.Dataset(
        {
            "eastward_sea_water_velocity": (("time", "lat", "lon"), u, dict(attrs)),
            "northward_sea_water_velocity": (("time", "lat", "lon"), v, dict(attrs)),
        },
        coords={"time": ("time", times), "lat": ("lat", lat), "lon": ("lon", lon)},
    )
    enc = {
        k: {"_FillValue": None} for k in ("eastward_sea_water_velocity", "northward_sea_water_velocity", "lat", "lon")
    }
    ds.to_netcdf(path, encoding=enc)
    return path, u, v


def test_cf_names_as_variable_names_float32_edges_keep_every_cell(tmp_path):
    p, u, v = _paper_grid_file(tmp_path / "paper.nc")
    na = geo.north_atlantic_grid()
    # units "1": the error names the real flag
    with pytest.raises(FieldError, match="--units"):
        import_currents(p, na)
    f = import_currents(p, na, units="m/s")  # no variables= needed: found by name
    assert f.attrs["variables"] == ["eastward_sea_water_velocity", "northward_sea_water_velocity"]
    assert f.coverage == 1.0  # was 0.933: columns 0 and 29 were NaN
    assert "the file's own grid" in f.attrs["edges"]
    # the file's own values, cell for cell (centres within float32 rounding of the nodes)
    np.testing.assert_allclose(f.u, u, atol=1e-5)
    np.testing.assert_allclose(f.v, v, atol=1e-5)


def test_half_cell_rule_and_no_extrapolation(tmp_path):
    na = geo.north_atlantic_grid()
    dlon = na.lons[1] - na.lons[0]
    # the file's nodes 0.3 cell east of the target's centres: the same grid within half a cell ->
    # column 0 (0.3 cell west of the file) keeps the file's edge values, the rest is interpolated
    p, u, _ = _paper_grid_file(tmp_path / "a.nc", units="m/s", lon_shift=0.0, lon_offset=0.3 * dlon)
    f = import_currents(p, na)
    assert f.coverage == 1.0 and "within half a cell" in f.attrs["edges"]
    np.testing.assert_allclose(f.u[:, :, 0], u[:, :, 0], atol=1e-5)
    np.testing.assert_allclose(f.u[:, :, 5], 0.3 * u[:, :, 4] + 0.7 * u[:, :, 5], atol=1e-4)
    # a target that is not the file's grid (other spacing) reaching 0.3 cell past the file: NaN there
    p, _, _ = _paper_grid_file(tmp_path / "b.nc", units="m/s", lon_shift=0.0)
    lons = na.lons.astype(np.float32).astype(float)
    wide = geo.RegionGrid(na.south, lons[0] - 0.3 * dlon, na.north, lons[-1], 30, 25)
    g = import_currents(p, wide)
    assert np.isnan(g.u[:, :, 0]).all() and np.isfinite(g.u[:, :, 1:]).all()
    assert "lon:" not in g.attrs["edges"]


def test_undeclared_fill_value_is_missing(tmp_path):
    p, u, _ = _paper_grid_file(tmp_path / "fill.nc", units="m s-1", fill=np.float32(1.26765e30))
    f = import_currents(p, geo.north_atlantic_grid())
    assert f.attrs["undeclared_fill_values"] == 2 * 6 * 12
    assert np.isnan(f.u[:, 0:3, 0:4]).all()
    assert np.nanmax(np.abs(f.data)) < 2.0
    # cells next to the fill block are not contaminated (their stencils hold no fill node)
    np.testing.assert_allclose(f.u[:, 5:, 5:], u[:, 5:, 5:], atol=1e-5)


def _shared(name):
    from conftest import SHARED_DATA

    p = SHARED_DATA / name
    if not p.exists():
        pytest.skip(f"real data file not found at {p} (../shared/data is not beside the checkout)")
    return p


def test_real_rtofs_without_units_attribute(tmp_path, capsys):
    """NOAA Global RTOFS off Washington: water_u/water_v with no units attribute, float32 lat/lon, land NaN."""
    p = _shared("wa_RTOFS_global.nc")
    with xr.open_dataset(p) as ds:
        lat = ds["lat"].values.astype(float)
        lon = ds["lon"].values.astype(float)
        raw_u = ds["water_u"].values
    own = geo.RegionGrid(lat[0], lon[0], lat[-1], lon[-1], lat.size, lon.size)
    with pytest.raises(FieldError, match="no 'units' attribute: give them with --units"):
        import_currents(p, own)
    from passt_mav.cli import main

    code = main(
        [
            "data",
            "import",
            str(p),
            f"--region={lat[0]},{lon[0]},{lat[-1]},{lon[-1]}",
            "--grid",
            "38x34",
            "--out",
            str(tmp_path / "x.nc"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "--units" in err and len(err.strip().splitlines()) == 1
    f = import_currents(p, own, units="m/s")
    assert f.n_times == 64 and f.time_origin == "2024-10-28T03:00:00Z"
    np.testing.assert_allclose(f.times[:3], [0.0, 10800.0, 21600.0])
    # the file's own grid (spacing uniform to 4e-6 deg): every sea node kept, land exactly the file's NaN
    np.testing.assert_array_equal(f.mask, np.isnan(raw_u))
    np.testing.assert_allclose(f.u, raw_u, atol=2e-4, equal_nan=True)
    assert 0.64 < f.coverage < 0.66  # ~35 % land
    assert np.nanmax(np.abs(f.data)) < 1.5


def test_real_gridded_current_fill_on_land(tmp_path):
    """HYCOM-like file (fill value on land): land cells are NaN, never a huge or zero current."""
    p = _shared("gridded_current.nc")
    with xr.open_dataset(p) as ds:
        lat = ds["lat"].values.astype(float)
        lon = ds["lon"].values.astype(float)
        raw_u = ds["water_u"].values
        n_raw = int(np.isnan(raw_u).sum())
    assert n_raw > 0
    own = geo.RegionGrid(lat[0], lon[0], lat[-1], lon[-1], lat.size, lon.size)
    f = import_currents(p, own)
    assert f.n_times == 17 and f.coverage == pytest.approx(1 - np.isnan(raw_u).mean())
    np.testing.assert_array_equal(f.mask, np.isnan(raw_u))
    np.testing.assert_allclose(f.u, raw_u, atol=1e-4, equal_nan=True)
    assert np.nanmax(np.abs(f.data)) < 1.0
