"""FlowField NetCDF round trips, CF readability without passt_mav, sampling, bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

import geo
from passt_mav.cli import main
from passt_mav.fields.field import FlowField, load_field

ATTRS = {
    "title": "test field",
    "generator": "tests",
    "seed": 7,
    "nu": 0.005,
    "parameters": {"jet": {"U0": 1.5, "waves": [1, 2, 3]}, "flag": True},
}


def _geo_field(rng) -> FlowField:
    grid = geo.RegionGrid(39.0, -64.0, 40.5, -62.0, 7, 9)
    data = rng.normal(size=(5, 2, 7, 9)).astype(np.float32)
    data[:, :, 2, 3] = np.nan  # land cell
    data[3, :, 5, 1] = np.nan  # a gap at one time
    return FlowField(data, grid, np.arange(5) * 3600.0, "2018-03-01T00:00:00Z", "m s-1", ATTRS)


def _metric_field(rng) -> FlowField:
    grid = geo.MetricRegionGrid(
        1.0, 8.0, -3.0, 3.0, 6, 8, anchor_lat=40.1, anchor_lon=-63.2, rotation_deg=30.0, scale=250.0
    )
    data = rng.normal(size=(4, 2, 6, 8)).astype(np.float32)
    data[:, :, 2:4, 0:2] = np.nan  # the cylinder body
    return FlowField(data, grid, 0.1 + np.arange(4) * 0.25, None, "1", {"generator": "tests", "strouhal": 0.2})


@pytest.mark.parametrize("make", [_geo_field, _metric_field], ids=["geographic", "metric"])
def test_round_trip(tmp_path, make):
    f = make(np.random.default_rng(0))
    p = f.to_netcdf(tmp_path / "f.nc")
    g = load_field(p)
    np.testing.assert_array_equal(g.data, f.data)  # NaN == NaN for assert_array_equal
    assert g.data.dtype == np.float32
    np.testing.assert_array_equal(g.mask, f.mask)
    np.testing.assert_array_equal(g.times, f.times)
    assert g.grid == f.grid and type(g.grid) is type(f.grid)
    assert g.time_origin == f.time_origin
    assert g.units == f.units
    assert g.attrs == json.loads(json.dumps(f.attrs))
    assert g.data_hash() == f.data_hash()


def test_plain_xarray_reads_cf_geographic(tmp_path):
    f = _geo_field(np.random.default_rng(1))
    p = f.to_netcdf(tmp_path / "f.nc")
    with xr.open_dataset(p) as ds:  # no passt_mav code involved
        assert ds["u"].attrs["standard_name"] == "eastward_sea_water_velocity"
        assert ds["v"].attrs["standard_name"] == "northward_sea_water_velocity"
        assert ds["u"].attrs["units"] == "m s-1"
        assert ds["u"].dims == ("time", "lat", "lon")
        assert ds["lat"].attrs["standard_name"] == "latitude" and ds["lon"].attrs["units"] == "degrees_east"
        np.testing.assert_allclose(ds["lat"].values, f.grid.lats)
        np.testing.assert_allclose(ds["lon"].values, f.grid.lons)
        # CF time decodes to real datetimes
        exp = np.datetime64("2018-03-01T00:00") + np.arange(5) * np.timedelta64(1, "h")
        np.testing.assert_array_equal(ds["time"].values.astype("datetime64[s]"), exp.astype("datetime64[s]"))
        np.testing.assert_array_equal(ds["u"].values, f.u)
        assert np.isnan(ds["v"].values[:, 2, 3]).all()
        assert ds.attrs["Conventions"].startswith("CF")


def test_plain_xarray_reads_metric(tmp_path):
    f = _metric_field(np.random.default_rng(2))
    p = f.to_netcdf(tmp_path / "m.nc")
    with xr.open_dataset(p) as ds:
        assert ds["u"].dims == ("time", "y", "x")
        np.testing.assert_allclose(ds["x"].values, f.grid.xs)
        np.testing.assert_allclose(ds["time"].values, f.times)
        assert ds["x"].attrs["units"] == "m"


def _linear_field(grid, coef_u=(0.2, 0.03, -0.05, 0.01), coef_v=(-0.1, 0.02, 0.04, -0.02)):
    """u, v linear in (row, col, snapshot index): bilinear + linear-time interp is exact."""
    T = 6
    r, c = np.meshgrid(np.arange(grid.rows), np.arange(grid.cols), indexing="ij")
    data = np.stack([np.stack([a + b * r + d * c + e * k for (a, b, d, e) in (coef_u, coef_v)]) for k in range(T)])
    return data.astype(np.float32), coef_u, coef_v


def test_interp_exact_for_linear_fields():
    grid = geo.RegionGrid(39.0, -64.0, 40.5, -62.0, 7, 9)
    data, cu, cv = _linear_field(grid)
    f = FlowField(data, grid, np.arange(6) * 600.0, "2018-03-01T00:00:00Z")
    rng = np.random.default_rng(3)
    t = rng.uniform(0, 3000, 200)
    r = rng.uniform(0, 6, 200)
    c = rng.uniform(0, 8, 200)
    out = f.interp(t, r, c)
    k = t / 600.0
    np.testing.assert_allclose(out[:, 0], cu[0] + cu[1] * r + cu[2] * c + cu[3] * k, atol=1e-5)
    np.testing.assert_allclose(out[:, 1], cv[0] + cv[1] * r + cv[2] * c + cv[3] * k, atol=1e-5)
    # scalars, edges and outside
    assert f.interp(0.0, 6.0, 8.0).shape == (2,)
    np.testing.assert_allclose(
        f.interp(3000.0, 6.0, 8.0),
        [cu[0] + 6 * cu[1] + 8 * cu[2] + 5 * cu[3], cv[0] + 6 * cv[1] + 8 * cv[2] + 5 * cv[3]],
        atol=1e-5,
    )
    assert np.isnan(f.interp(0.0, -0.1, 3.0)).all()
    assert np.isnan(f.interp(3001.0, 3.0, 3.0)).all()


def test_sample_latlon_exact_for_linear_in_latlon():
    grid = geo.RegionGrid(39.0, -64.0, 40.5, -62.0, 7, 9)
    lat, lon = grid.centres_latlon()
    u = 0.5 + 0.8 * (lat - 39.0) - 0.3 * (lon + 64.0)
    v = -0.2 + 0.1 * (lat - 39.0) + 0.6 * (lon + 64.0)
    data = np.broadcast_to(np.stack([u, v])[None], (2, 2, 7, 9)).astype(np.float32)
    f = FlowField(data, grid, [0.0, 3600.0], "2018-03-01T00:00:00Z")
    rng = np.random.default_rng(4)
    la, lo = rng.uniform(39.0, 40.5, 100), rng.uniform(-64.0, -62.0, 100)
    out = f.sample_latlon(1800.0, la, lo)
    np.testing.assert_allclose(out[:, 0], 0.5 + 0.8 * (la - 39.0) - 0.3 * (lo + 64.0), atol=1e-5)
    np.testing.assert_allclose(out[:, 1], -0.2 + 0.1 * (la - 39.0) + 0.6 * (lo + 64.0), atol=1e-5)


def test_interp_nan_near_missing_only():
    grid = geo.RegionGrid(39.0, -64.0, 40.5, -62.0, 7, 9)
    data, cu, _ = _linear_field(grid)
    data[:, :, 3, 4] = np.nan
    f = FlowField(data, grid, np.arange(6) * 600.0, "2018-03-01T00:00:00Z")
    assert np.isnan(f.interp(0.0, 3.5, 4.5)).all()  # stencil includes (3, 4)
    assert np.isnan(f.interp(0.0, 2.5, 3.5)).all()
    ok = f.interp(0.0, 3.0, 5.0)  # on a valid node next to the gap: zero weight on the gap
    assert ok[0] == pytest.approx(cu[0] + 3 * cu[1] + 5 * cu[2], abs=1e-5)
    ok = f.interp(0.0, 1.5, 1.5)
    assert np.isfinite(ok).all()


# -- bad files through the command line: exit 2, one line ----------------------------------
def _run_info(path, capsys):
    code = main(["data", "info", str(path)])
    err = capsys.readouterr().err.strip()
    return code, err


def test_bad_files_exit_2_one_line(tmp_path, capsys):
    code, err = _run_info(tmp_path / "missing.nc", capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "not found" in err

    junk = tmp_path / "junk.nc"
    junk.write_bytes(b"this is not netcdf\n" * 10)
    code, err = _run_info(junk, capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "cannot read" in err

    f = _geo_field(np.random.default_rng(5))
    ds = f.to_dataset().drop_vars("v")
    nov = tmp_path / "nov.nc"
    ds.to_netcdf(nov)
    code, err = _run_info(nov, capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "lacks the variable(s) v" in err

    foreign = tmp_path / "foreign.nc"
    xr.Dataset({"u": (("lat", "lon"), np.zeros((2, 2)))}, coords={"lat": [1.0, 2.0], "lon": [1.0, 2.0]}).to_netcdf(
        foreign
    )
    code, err = _run_info(foreign, capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "passt-mav data import" in err
