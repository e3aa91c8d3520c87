"""Importing currents from projected and curvilinear ocean-model grids (issue 54, item 2).

Every file is built here with a known rotation between the grid's axes and east/north, worked
out analytically (not with the importer's pyproj/geodesic machinery): the importer must give the
east/north current back. Conventions: ``theta`` is the angle of the grid's x axis counter-clockwise
from east (radians); a current (east ``ue``, north ``vn``, m/s) has grid components
``ux = ue cos(theta) + vn sin(theta)`` and ``uy = -ue sin(theta) + vn cos(theta)``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from pyproj import CRS, Transformer

import geo
from passt_mav.cli import main
from passt_mav.errors import FieldError
from passt_mav.fields.importers import import_currents

UE, VN = 0.3, -0.2  # m/s: the uniform east/north current at hour 0
DU_DT = 0.01  # m/s per hour added to the east component (the time axis is read in order)
TIMES = pd.Timestamp("2021-06-01T00:00") + pd.to_timedelta(np.arange(3), unit="h")
WGS84 = {"semi_major_axis": 6378137.0, "inverse_flattening": 298.257223563}


def _to_grid(ue, vn, theta):
    """East/north components -> components along the grid's x and y axes (theta: x axis from east)."""
    c, s = np.cos(theta), np.sin(theta)
    return ue * c + vn * s, -ue * s + vn * c


def _current(hour):
    return UE + DU_DT * hour, VN


def _projected_file(path, gm_attrs, proj4, theta_of, region, *, step, units="m", latlon=True, land=None, rotated=False):
    """A CF file on a projected grid: 1-D projection x/y (``step`` metres apart, in ``units``) covering
    ``region`` (S, W, N, E degrees) with a margin, a ``crs`` grid-mapping variable with ``gm_attrs``,
    grid-relative ``ux``/``uy`` (standard names sea_water_x/y_velocity) of the uniform current rotated
    by ``theta_of(lat, lon)``, optional 2-D lat/lon auxiliary coordinates and an optional land block
    (``land(lat, lon)`` True -> NaN). ``rotated``: the axes are a rotated pole's rlon/rlat (degrees)."""
    to_xy = Transformer.from_crs("EPSG:4326", CRS(proj4), always_xy=True)
    s, w, n, e = region
    la, lo = np.meshgrid(np.linspace(s - 0.5, n + 0.5, 20), np.linspace(w - 1.5, e + 1.5, 20))
    px, py = to_xy.transform(lo, la)
    x = np.arange(np.min(px), np.max(px) + step, step)
    y = np.arange(np.min(py), np.max(py) + step, step)
    X, Y = np.meshgrid(x, y)
    lon, lat = Transformer.from_crs(CRS(proj4), "EPSG:4326", always_xy=True).transform(X, Y)
    theta = theta_of(lat, lon)
    ux = np.empty((len(TIMES), *X.shape), np.float32)
    uy = np.empty_like(ux)
    for k in range(len(TIMES)):
        ux[k], uy[k] = _to_grid(*_current(k), theta)
    if land is not None:
        ux[:, land(lat, lon)] = np.nan
        uy[:, land(lat, lon)] = np.nan
    f = {"m": 1.0, "km": 1e-3, "degrees": 1.0}[units]
    xn, yn, xs, ys = (
        ("rlon", "rlat", "grid_longitude", "grid_latitude")
        if rotated
        else ("x", "y", "projection_x_coordinate", "projection_y_coordinate")
    )
    velo = {"units": "m s-1", "grid_mapping": "crs"}
    ds = xr.Dataset(
        {
            "ux": (("time", yn, xn), ux, {**velo, "standard_name": "sea_water_x_velocity"}),
            "uy": (("time", yn, xn), uy, {**velo, "standard_name": "sea_water_y_velocity"}),
            "crs": ((), np.int32(0), gm_attrs),
        },
        coords={
            "time": ("time", TIMES),
            xn: (xn, x * f, {"standard_name": xs, "units": units, "axis": "X"}),
            yn: (yn, y * f, {"standard_name": ys, "units": units, "axis": "Y"}),
        },
    )
    if latlon:
        ds = ds.assign_coords(
            lat=((yn, xn), lat, {"standard_name": "latitude", "units": "degrees_north"}),
            lon=((yn, xn), lon, {"standard_name": "longitude", "units": "degrees_east"}),
        )
        for k in ("ux", "uy"):
            ds[k].attrs["coordinates"] = "lat lon"
    ds.to_netcdf(path, encoding={"time": {"units": "hours since 2021-01-01"}})
    return path


# -- (a) polar stereographic -----------------------------------------------------------------
PS_ATTRS = {
    "grid_mapping_name": "polar_stereographic",
    "straight_vertical_longitude_from_pole": -45.0,
    "latitude_of_projection_origin": 90.0,
    "standard_parallel": 70.0,
    "false_easting": 0.0,
    "false_northing": 0.0,
    **WGS84,
}
PS_PROJ = "+proj=stere +lat_0=90 +lat_ts=70 +lon_0=-45 +datum=WGS84 +units=m"
# Barents Sea: 55-65 deg east of the projection's central meridian, so the grid is rotated ~60 deg
PS_REGION = (70.5, 12.0, 71.5, 18.0)
PS_GRID = geo.RegionGrid(*PS_REGION, 12, 16)


def _ps_theta(lat, lon):
    # north polar stereographic: x = rho sin(lon - lon0), y = -rho cos(lon - lon0); east at a node is
    # (lon - lon0) counter-clockwise from +x, so the x axis is -(lon - lon0) from east
    return -np.deg2rad(lon - PS_ATTRS["straight_vertical_longitude_from_pole"])


def _ps_land(lat, lon):
    return (lat > 70.9) & (lat < 71.1) & (lon > 14.5) & (lon < 15.5)


def _assert_current(f, tol):
    """Every valid cell holds the uniform current of its hour within ``tol`` m/s; returns the worst error."""
    worst = 0.0
    for k in range(f.n_times):
        ue, vn = _current(k)
        ok = ~f.mask[k]
        err = max(float(np.abs(f.u[k][ok] - ue).max()), float(np.abs(f.v[k][ok] - vn).max()))
        worst = max(worst, err)
    assert worst < tol, worst
    return worst


@pytest.mark.parametrize("latlon", [True, False], ids=["with-2d-latlon", "positions-from-crs"])
def test_polar_stereographic_grid_relative_current_comes_back_east_north(tmp_path, latlon):
    p = _projected_file(tmp_path / "ps.nc", PS_ATTRS, PS_PROJ, _ps_theta, PS_REGION, step=10_000.0, latlon=latlon)
    f = import_currents(p, PS_GRID)
    assert f.shape == (3, 2, 12, 16) and f.time_origin == "2021-06-01T00:00:00Z"
    assert f.attrs["variables"] == ["ux", "uy"]
    assert "polar_stereographic" in f.attrs["source_grid"]
    assert "polar_stereographic projection" in f.attrs["rotation"]
    assert f.coverage == 1.0
    # the grid is rotated by -54..-66 deg here: an unrotated import would be off by ~0.3 m/s.
    # Measured: 3e-8 m/s (float32 storage); the bound leaves room for the angle's finite step
    _assert_current(f, 1e-5)


def test_polar_stereographic_y_top_down_and_dims_transposed(tmp_path):
    # y stored north-to-south-of-the-pole order reversed (a top-down raster) and the arrays as
    # (time, x, y): the CF x/y components are along increasing x/y coordinates whatever the storage
    p = _projected_file(tmp_path / "ps.nc", PS_ATTRS, PS_PROJ, _ps_theta, PS_REGION, step=10_000.0)
    with xr.open_dataset(p) as ds:
        ds = ds.load()
    q = tmp_path / "ps_flipped.nc"
    ds.isel(y=slice(None, None, -1)).transpose("time", "x", "y").to_netcdf(q)
    f = import_currents(q, PS_GRID)
    assert f.coverage == 1.0
    _assert_current(f, 1e-5)


def test_polar_stereographic_land_stays_nan(tmp_path):
    p = _projected_file(tmp_path / "ps.nc", PS_ATTRS, PS_PROJ, _ps_theta, PS_REGION, step=10_000.0, land=_ps_land)
    f = import_currents(p, PS_GRID)
    lat, lon = PS_GRID.centres_latlon()
    # cells well inside the land block are NaN at every time, never a zero current
    inner = _ps_land(lat, lon)
    assert inner.any() and f.mask[:, inner].all()
    assert np.isnan(f.data[:, :, inner]).all()
    assert 0.5 < f.coverage < 1.0
    # the rest is the current, not diluted toward zero near the coast
    _assert_current(f, 1e-5)


def test_nemo_like_curvilinear_latlon_without_grid_mapping(tmp_path):
    # polar-stereographic nodes on a sphere (as an ocean model's grid is) with only 2-D nav_lat/nav_lon
    # (no grid mapping, no x/y axes): the grid's axes are found from the positions alone (centred
    # differences on the sphere); the analytic angle holds on the sphere too
    sphere = "+proj=stere +lat_0=90 +lat_ts=70 +lon_0=-45 +R=6371229 +units=m"
    p = _projected_file(tmp_path / "ps.nc", PS_ATTRS, sphere, _ps_theta, PS_REGION, step=10_000.0)
    with xr.open_dataset(p) as ds:
        ds = ds.load()
    ds = ds.drop_vars(["crs", "x", "y"]).rename({"lat": "nav_lat", "lon": "nav_lon"})
    for k in ("ux", "uy"):
        del ds[k].attrs["grid_mapping"]
        ds[k].encoding.pop("coordinates", None)  # xarray writes the renamed nav_lat/nav_lon
    q = tmp_path / "nemo.nc"
    ds.to_netcdf(q)
    f = import_currents(q, PS_GRID)
    assert "curvilinear 2-D latitude/longitude (nav_lat/nav_lon)" in f.attrs["source_grid"]
    assert "2-D latitude/longitude" in f.attrs["rotation"]
    # measured 3.6e-6 m/s: the centred difference's angle error (~6e-4 deg on a 10 km grid)
    _assert_current(f, 1e-4)


def test_eastward_northward_velocities_on_a_curvilinear_grid_are_not_rotated(tmp_path):
    # e.g. a model's output already rotated to east/north but kept on its native 2-D lat/lon grid
    p = _projected_file(tmp_path / "ps.nc", PS_ATTRS, PS_PROJ, lambda la, lo: 0.0 * la, PS_REGION, step=10_000.0)
    with xr.open_dataset(p) as ds:
        ds = ds.load()
    ds["ux"].attrs["standard_name"] = "eastward_sea_water_velocity"
    ds["uy"].attrs["standard_name"] = "northward_sea_water_velocity"
    q = tmp_path / "en.nc"
    ds.to_netcdf(q)
    f = import_currents(q, PS_GRID)
    assert f.attrs["rotation"] == "none (eastward/northward components)"
    _assert_current(f, 1e-5)


# -- (c) Lambert conformal conic, projection coordinates in km ----------------------------------
LCC_ATTRS = {
    "grid_mapping_name": "lambert_conformal_conic",
    "standard_parallel": 40.0,
    "longitude_of_central_meridian": -100.0,
    "latitude_of_projection_origin": 40.0,
    "false_easting": 0.0,
    "false_northing": 0.0,
    **WGS84,
}
LCC_PROJ = "+proj=lcc +lat_1=40 +lat_0=40 +lon_0=-100 +datum=WGS84 +units=m"
LCC_REGION = (39.5, -64.5, 40.5, -62.5)


def _lcc_theta(lat, lon):
    # tangent LCC: x = rho sin(n (lon - lon0)), cone constant n = sin(40 deg) (1SP, also on the ellipsoid)
    return -np.sin(np.deg2rad(40.0)) * np.deg2rad(lon - LCC_ATTRS["longitude_of_central_meridian"])


def test_lambert_conformal_km_coordinates(tmp_path):
    p = _projected_file(tmp_path / "lcc.nc", LCC_ATTRS, LCC_PROJ, _lcc_theta, LCC_REGION, step=8_000.0, units="km")
    f = import_currents(p, geo.RegionGrid(*LCC_REGION, 9, 14))
    assert "lambert_conformal_conic" in f.attrs["rotation"]
    assert f.coverage == 1.0
    _assert_current(f, 1e-5)  # x axis -22..-25 deg from east here; measured 3e-8 m/s


# -- (c) rotated pole (EURO-CORDEX's pole), over the North Sea -----------------------------------
RP_ATTRS = {
    "grid_mapping_name": "rotated_latitude_longitude",
    "grid_north_pole_latitude": 39.25,
    "grid_north_pole_longitude": -162.0,
}
RP_PROJ = "+proj=ob_tran +o_proj=longlat +o_lon_p=0 +o_lat_p=39.25 +lon_0=18 +datum=WGS84 +no_defs"
RP_REGION = (54.0, 3.0, 56.0, 7.0)


def _unit(lat, lon):
    la, lo = np.deg2rad(lat), np.deg2rad(lon)
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)


def _rp_theta(lat, lon):
    # on the sphere the rotated grid's x axis (rotated east) at r is along pole x r, true east along
    # z x r and north along r x east
    r = _unit(lat, lon)
    pole = _unit(np.array(RP_ATTRS["grid_north_pole_latitude"]), np.array(RP_ATTRS["grid_north_pole_longitude"]))
    ex = np.cross(np.broadcast_to(pole, r.shape), r)
    east = np.cross(np.broadcast_to([0.0, 0.0, 1.0], r.shape), r)
    north = np.cross(r, east)
    return np.arctan2((ex * north).sum(-1), (ex * east).sum(-1))


def test_rotated_pole_grid_relative_current(tmp_path):
    p = _projected_file(
        tmp_path / "rp.nc", RP_ATTRS, RP_PROJ, _rp_theta, RP_REGION, step=0.11, units="degrees", rotated=True
    )
    f = import_currents(p, geo.RegionGrid(*RP_REGION, 10, 12))
    assert "rotated_latitude_longitude" in f.attrs["rotation"]
    assert f.coverage == 1.0
    _assert_current(f, 1e-5)  # x axis 8..13 deg from east here; measured 3e-8 m/s


# -- (b) ROMS: curvilinear rho grid, staggered u/v, angle ---------------------------------------
ROMS_ANGLE = np.deg2rad(30.0)  # the XI axis, counter-clockwise from east
ROMS_C = (40.0, -63.0)  # the grid's centre (and the target's)
GRAD = (2e-6, -1.5e-6)  # d(ue)/dx_east, d(vn)/dy_north in s-1: the current varies across the grid


def _roms_current(x, y, hour):
    """East/north current (m/s) at local east/north metres ``x``, ``y`` from ROMS_C."""
    return UE + DU_DT * hour + GRAD[0] * x, VN + GRAD[1] * y


def _roms_file(path, *, std_names, land=True, dx=2000.0, nxi=60, neta=50):
    """A ROMS-like history file: rho points on a rectangular grid rotated by ROMS_ANGLE in the local
    azimuthal-equidistant plane about ROMS_C; u at the xi faces, v at the eta faces; 3 s-levels
    (deeper levels +0.5 m/s so the wrong level shows); land (mask_rho = 0) where u/v are written as 0."""
    aeqd = CRS(f"+proj=aeqd +lat_0={ROMS_C[0]} +lon_0={ROMS_C[1]} +datum=WGS84 +units=m")
    inv = Transformer.from_crs(aeqd, "EPSG:4326", always_xy=True)
    c, s = np.cos(ROMS_ANGLE), np.sin(ROMS_ANGLE)

    def plane(xi, eta):  # grid coordinates (metres along XI/ETA) -> local east/north metres
        return xi * c - eta * s, xi * s + eta * c

    xi_r = (np.arange(nxi) - (nxi - 1) / 2) * dx
    eta_r = (np.arange(neta) - (neta - 1) / 2) * dx
    xi_u = 0.5 * (xi_r[:-1] + xi_r[1:])
    eta_v = 0.5 * (eta_r[:-1] + eta_r[1:])

    def pos(xi, eta):
        XI, ETA = np.meshgrid(xi, eta)
        x, y = plane(XI, ETA)
        lon, lat = inv.transform(x, y)
        return x, y, lat, lon

    xr_, yr_, lat_r, lon_r = pos(xi_r, eta_r)
    xu, yu, lat_u, lon_u = pos(xi_u, eta_r)
    xv, yv, lat_v, lon_v = pos(xi_r, eta_v)
    mask_rho = np.ones((neta, nxi))
    if land:
        mask_rho[20:26, 28:34] = 0.0
    mask_u = mask_rho[:, :-1] * mask_rho[:, 1:]
    mask_v = mask_rho[:-1, :] * mask_rho[1:, :]
    s_rho = np.array([-0.8333, -0.5, -0.1667])
    u = np.empty((len(TIMES), 3, neta, nxi - 1))
    v = np.empty((len(TIMES), 3, neta - 1, nxi))
    for k in range(len(TIMES)):
        gu, _ = _to_grid(*_roms_current(xu, yu, k), ROMS_ANGLE)
        _, gv = _to_grid(*_roms_current(xv, yv, k), ROMS_ANGLE)
        for lev in range(3):
            u[k, lev] = np.where(mask_u > 0, gu + 0.5 * (2 - lev), 0.0)
            v[k, lev] = np.where(mask_v > 0, gv - 0.5 * (2 - lev), 0.0)
    uattrs = {"long_name": "u-momentum component", "units": "meter second-1"}
    vattrs = {"long_name": "v-momentum component", "units": "meter second-1"}
    if std_names:
        uattrs["standard_name"] = "sea_water_x_velocity_at_u_location"
        vattrs["standard_name"] = "sea_water_y_velocity_at_v_location"
    ds = xr.Dataset(
        {
            "u": (
                ("ocean_time", "s_rho", "eta_u", "xi_u"),
                u,
                {**uattrs, "coordinates": "lon_u lat_u s_rho ocean_time"},
            ),
            "v": (
                ("ocean_time", "s_rho", "eta_v", "xi_v"),
                v,
                {**vattrs, "coordinates": "lon_v lat_v s_rho ocean_time"},
            ),
            "angle": (("eta_rho", "xi_rho"), np.full((neta, nxi), ROMS_ANGLE), {"units": "radians"}),
            "mask_rho": (("eta_rho", "xi_rho"), mask_rho, {"flag_values": [0.0, 1.0]}),
            "mask_u": (("eta_u", "xi_u"), mask_u),
            "mask_v": (("eta_v", "xi_v"), mask_v),
            "lat_rho": (("eta_rho", "xi_rho"), lat_r, {"units": "degree_north", "standard_name": "latitude"}),
            "lon_rho": (("eta_rho", "xi_rho"), lon_r, {"units": "degree_east", "standard_name": "longitude"}),
            "lat_u": (("eta_u", "xi_u"), lat_u, {"units": "degree_north"}),
            "lon_u": (("eta_u", "xi_u"), lon_u, {"units": "degree_east"}),
            "lat_v": (("eta_v", "xi_v"), lat_v, {"units": "degree_north"}),
            "lon_v": (("eta_v", "xi_v"), lon_v, {"units": "degree_east"}),
        },
        coords={"ocean_time": ("ocean_time", TIMES), "s_rho": ("s_rho", s_rho, {"positive": "up"})},
    )
    ds.to_netcdf(path, encoding={"ocean_time": {"units": "seconds since 2021-01-01"}})
    return path, (xr_, yr_, mask_rho)


ROMS_GRID = geo.RegionGrid(39.8, -63.3, 40.2, -62.7, 11, 13)  # centred on ROMS_C


def _roms_expected(grid, hour):
    aeqd = CRS(f"+proj=aeqd +lat_0={ROMS_C[0]} +lon_0={ROMS_C[1]} +datum=WGS84 +units=m")
    lat, lon = grid.centres_latlon()
    x, y = Transformer.from_crs("EPSG:4326", aeqd, always_xy=True).transform(lon, lat)
    return _roms_current(np.asarray(x), np.asarray(y), hour)


@pytest.mark.parametrize("std_names", [True, False], ids=["cf-standard-names", "roms-names-only"])
def test_roms_c_grid_with_angle_comes_back_east_north(tmp_path, std_names):
    p, _ = _roms_file(tmp_path / "roms_his.nc", std_names=std_names, land=False)
    f = import_currents(p, ROMS_GRID)
    assert f.attrs["variables"] == ["u", "v"]
    assert f.attrs["depth_m"] == pytest.approx(-0.1667)  # the top s-level
    assert "ROMS C grid" in f.attrs["source_grid"] and "ROMS angle" in f.attrs["rotation"]
    assert f.coverage == 1.0
    worst = 0.0
    for k in range(3):
        eu, ev = _roms_expected(ROMS_GRID, k)
        worst = max(worst, float(np.abs(f.u[k] - eu).max()), float(np.abs(f.v[k] - ev).max()))
    # the current is linear in the plane, so averaging faces to rho points and linear interpolation on
    # triangles reproduce it; a face off by one would be off by GRAD * 2 km = 4e-3 m/s.
    # Measured 1.5e-8 m/s (float32 of the result)
    assert worst < 1e-5, worst


def test_roms_land_mask_zero_velocities_are_nan_not_zero(tmp_path):
    p, (x, y, mask_rho) = _roms_file(tmp_path / "roms_his.nc", std_names=True, land=True)
    grid = geo.RegionGrid(39.9, -63.1, 40.1, -62.9, 21, 21)
    f = import_currents(p, grid)
    assert 0.0 < f.coverage < 1.0
    # a cell whose triangle touches a land rho point (or a rho point with a land face) is NaN; the land
    # u/v are written as 0 in the file, and no zero current appears anywhere
    sp = np.hypot(f.u, f.v)
    assert np.nanmin(sp) > 0.1
    eu, ev = _roms_expected(grid, 0)
    ok = ~f.mask[0]
    np.testing.assert_allclose(f.u[0][ok], eu[ok], atol=1e-5)
    np.testing.assert_allclose(f.v[0][ok], ev[ok], atol=1e-5)
    # the cells nearest the middle of the land block are masked
    aeqd = CRS(f"+proj=aeqd +lat_0={ROMS_C[0]} +lon_0={ROMS_C[1]} +datum=WGS84 +units=m")
    lat, lon = grid.centres_latlon()
    cx, cy = Transformer.from_crs("EPSG:4326", aeqd, always_xy=True).transform(lon, lat)
    land_x, land_y = x[mask_rho == 0], y[mask_rho == 0]
    d = np.hypot(np.asarray(cx)[..., None] - land_x, np.asarray(cy)[..., None] - land_y).min(axis=-1)
    assert f.mask[:, d < 500.0].all() and (d < 500.0).any()


# -- (d) what is refused --------------------------------------------------------------------------
def _curvilinear_unknown_direction(path):
    p = _projected_file(path.with_suffix(".ps.nc"), PS_ATTRS, PS_PROJ, _ps_theta, PS_REGION, step=20_000.0)
    with xr.open_dataset(p) as ds:
        ds = ds.load()
    ds = ds.drop_vars(["crs", "x", "y"]).rename({"ux": "u", "uy": "v"})
    for k in ("u", "v"):
        ds[k].attrs = {"units": "m/s"}
    ds.to_netcdf(path)
    return path


def test_unknown_velocity_direction_on_a_curvilinear_grid_is_refused(tmp_path):
    p = _curvilinear_unknown_direction(tmp_path / "curv.nc")
    with pytest.raises(FieldError, match="cannot rotate them to east/north"):
        import_currents(p, PS_GRID)


def _one_line_exit_2(capsys, argv, *needles):
    """As tests/test_cli_errors.py: exit 2, one ``passt-mav: error:`` line naming ``needles``, no traceback."""
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert rc == 2, (out, err)
    lines = err.strip().splitlines()
    assert lines == [lines[-1]] and lines[-1].startswith("passt-mav: error: "), err
    for n in needles:
        assert n in lines[-1], (n, lines[-1])
    assert "Traceback" not in out + err


def test_refusals_through_the_cli_are_one_line_exit_2(tmp_path, capsys):
    p = _curvilinear_unknown_direction(tmp_path / "curv.nc")
    region = "--region=" + ",".join(str(x) for x in PS_REGION)
    _one_line_exit_2(
        capsys, ["data", "import", p, region, "--grid", "6x8", "--out", tmp_path / "o.nc"], "curv.nc", "east/north"
    )
    assert not (tmp_path / "o.nc").exists()
    # a non-orthogonal projection (sinusoidal, 60 deg from its central meridian): x/y components are ambiguous
    sinu = {
        "grid_mapping_name": "sinusoidal",
        "longitude_of_central_meridian": -45.0,
        "false_easting": 0.0,
        "false_northing": 0.0,
        **WGS84,
    }
    q = _projected_file(
        tmp_path / "sinu.nc",
        sinu,
        "+proj=sinu +lon_0=-45 +datum=WGS84 +units=m",
        lambda la, lo: 0 * la,
        PS_REGION,
        step=20_000.0,
    )
    _one_line_exit_2(
        capsys, ["data", "import", q, region, "--grid", "6x8", "--out", tmp_path / "o.nc"], "perpendicular"
    )
    # u and v on different staggered grids that are not ROMS's
    ds = xr.Dataset(
        {
            "u": (("time", "yu", "xu"), np.zeros((1, 3, 4)), {"units": "m/s"}),
            "v": (("time", "yv", "xv"), np.zeros((1, 4, 3)), {"units": "m/s"}),
        },
        coords={"time": TIMES[:1]},
    )
    ds.to_netcdf(tmp_path / "stag.nc")
    _one_line_exit_2(
        capsys,
        ["data", "import", tmp_path / "stag.nc", region, "--out", tmp_path / "o.nc"],
        "different dimensions",
        "ROMS",
    )
    # an unstructured mesh (FVCOM-like: nodes listed along one dimension)
    node = np.arange(50)
    std = ("eastward_sea_water_velocity", "northward_sea_water_velocity")
    ds = xr.Dataset(
        {k: (("time", "node"), np.full((1, 50), 0.1), {"units": "m/s", "standard_name": s}) for k, s in zip("uv", std)},
        coords={
            "time": TIMES[:1],
            "lat": ("node", 70.0 + 0.05 * node, {"units": "degrees_north"}),
            "lon": ("node", 12.0 + 0.1 * node, {"units": "degrees_east"}),
        },
    )
    ds.to_netcdf(tmp_path / "fvcom.nc")
    _one_line_exit_2(
        capsys, ["data", "import", tmp_path / "fvcom.nc", region, "--out", tmp_path / "o.nc"], "unstructured mesh"
    )
    assert not (tmp_path / "o.nc").exists()


def test_cli_import_of_a_roms_file_and_info_say_how_it_was_read(tmp_path, capsys):
    p, _ = _roms_file(tmp_path / "roms_his.nc", std_names=False, land=False)
    out = tmp_path / "roms.nc"
    assert main(["data", "import", str(p), "--region=39.9,-63.1,40.1,-62.9", "--grid", "6x6", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["data", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "source_grid ROMS C grid" in text and "rotation    grid x/y components rotated" in text
