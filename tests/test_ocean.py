"""The synthetic North Atlantic default field: physics and determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

import geo
from passt_mav.errors import FieldError
from passt_mav.fields.ocean import EARTH_RADIUS_M, M2_PERIOD_S, make_ocean_default


@pytest.fixture(scope="module")
def ocean():
    return make_ocean_default(seed=0)


def _div_vort(u: np.ndarray, v: np.ndarray, grid) -> tuple[np.ndarray, np.ndarray]:
    """Centred-difference divergence and vorticity (1/s) on interior cells.

    Metres per degree on the sphere: dx = R cos(lat) dlon, dy = R dlat; the
    spherical divergence is (du/dlon + d(v cos lat)/dlat) / (R cos lat).
    """
    lat = np.radians(grid.lats)[:, None]
    dlon, dlat = np.radians(grid.dlon), np.radians(grid.dlat)
    c = np.cos(lat)
    u = u.astype(np.float64)
    v = v.astype(np.float64)

    def ddlon(a):
        return (a[..., 1:-1, 2:] - a[..., 1:-1, :-2]) / (2 * dlon)

    def ddlat(a):
        return (a[..., 2:, 1:-1] - a[..., :-2, 1:-1]) / (2 * dlat)

    ci = c[1:-1]
    div = (ddlon(u) + ddlat(v * c)) / (EARTH_RADIUS_M * ci)
    vort = (ddlon(v) - ddlat(u * c)) / (EARTH_RADIUS_M * ci)
    return div, vort


def _rms(a):
    return float(np.sqrt(np.mean(a**2)))


def test_shape_dtype_units_times(ocean):
    assert ocean.shape == (504, 2, 30, 30)
    assert ocean.data.dtype == np.float32
    assert ocean.grid == geo.north_atlantic_grid()
    assert ocean.units == "m s-1"
    assert ocean.time_origin == "2018-03-01T00:00:00Z"
    assert ocean.dt == pytest.approx(3600.0)
    assert not ocean.mask.any()
    assert ocean.attrs["seed"] == 0 and ocean.attrs["generator"].endswith("make_ocean_default")
    assert {"jet", "rings", "tide"} <= set(ocean.attrs["parameters"])


def test_nearly_divergence_free(ocean):
    # measured: RMS(div)/RMS(vort) = 0.005-0.0065 for seeds 0-11 (truncation error of
    # the centred differences on 6.8 km cells); a gradient field gives >> 1
    div, vort = _div_vort(ocean.u, ocean.v, ocean.grid)
    ratio = _rms(div) / _rms(vort)
    assert ratio < 0.02
    # the same test on the curl-free twin (u, v) -> (v, -u) must fail loudly
    div2, vort2 = _div_vort(ocean.v, -ocean.u, ocean.grid)
    assert _rms(div2) / _rms(vort2) > 10.0


def test_vorticity_scale_is_oceanic(ocean):
    # a 1.5 m/s jet of ~35 km half-width: |zeta| / f up to O(1) (Gulf Stream Rossby numbers)
    _, vort = _div_vort(ocean.u, ocean.v, ocean.grid)
    f = 2 * 7.2921e-5 * math.sin(math.radians(40.2))
    assert 0.3 < np.max(np.abs(vort)) / f < 3.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_max_speed_in_documented_range(seed):
    f = make_ocean_default(seed=seed)
    assert 1.5 <= float(f.speed().max()) <= 2.0


def test_jet_core_width(ocean):
    # eastward-speed profile across the jet at the middle column, first snapshot:
    # full width at half maximum 50-100 km (W 30-38 km -> FWHM 53-67 km, widened by meander tilt)
    u = ocean.u[0, :, 15].astype(float)
    half = u >= 0.5 * u.max()
    dy = ocean.grid.cell_size_m[0]
    assert 45e3 <= half.sum() * dy <= 110e3
    assert 1.3 <= u.max() <= 2.0


def _axis_lat(f, col: int) -> np.ndarray:
    """Jet-axis latitude at column ``col`` per snapshot, tracked through time.

    The axis starts at the eastward-velocity maximum of the first snapshot and
    is then followed within +-3 cells of its previous row, so a ring's eastward
    flank elsewhere in the column is not mistaken for the jet.
    """
    u = f.u[:, :, col]
    r = int(np.argmax(u[0]))
    rows = [r]
    for k in range(1, f.n_times):
        lo, hi = max(r - 3, 0), min(r + 4, f.grid.rows)
        r = lo + int(np.argmax(u[k, lo:hi]))
        rows.append(r)
    return f.grid.lats[np.array(rows)]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_meanders_move(seed):
    # documented: the axis at a fixed longitude swings by roughly 25-80 km over 504 h
    f = make_ocean_default(seed=seed)
    lat = _axis_lat(f, 15)
    swing_km = (lat.max() - lat.min()) * 111.2
    assert 20.0 <= swing_km <= 110.0
    # what is tracked is the jet: (nearly) the fastest cell of the column at every time
    rows = np.round((lat - f.grid.south) / f.grid.dlat).astype(int)
    sp = f.speed()[:, :, 15]
    assert np.min(sp[np.arange(f.n_times), rows] / sp.max(axis=1)) > 0.9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_meanders_propagate_east(seed):
    # the axis curve Y(lon) 96 h later best matches Y(lon) shifted east by the
    # documented phase speeds (5-10 km/day -> 20-40 km = 3-6 columns of 6.8 km)
    f = make_ocean_default(seed=seed, hours=97)
    y0 = np.array([_axis_lat(f, c)[0] for c in range(30)])
    y1 = np.array([_axis_lat(f, c)[-1] for c in range(30)])
    errs = {
        s: np.mean((y1[s:] - y0[: 30 - s]) ** 2) if s >= 0 else np.mean((y1[:s] - y0[-s:]) ** 2) for s in range(-8, 9)
    }
    best = min(errs, key=errs.get)
    waves = f.attrs["parameters"]["jet"]["waves"]
    expected = np.mean([w["speed"] for w in waves]) * 96 * 3600 / f.grid.cell_size_m[1]
    assert 2 <= best <= 7
    assert abs(best - expected) <= 1.5


def test_tide_is_uniform_m2(ocean):
    # the spatial mean minus its 25 h running mean is dominated by a 12.42 h oscillation of a few cm/s
    um = ocean.u.mean(axis=(1, 2)).astype(float)
    spec = np.abs(np.fft.rfft(um - um.mean()))
    freqs = np.fft.rfftfreq(um.size, d=3600.0)
    band = (freqs > 1 / (14 * 3600)) & (freqs < 1 / (11 * 3600))
    k = np.argmax(np.where(band, spec, 0))
    assert abs(1 / freqs[k] - M2_PERIOD_S) < 0.5 * 3600
    t = ocean.attrs["parameters"]["tide"]
    assert 0.02 <= t["major"] <= 0.05 and 0.02 <= t["minor"] <= t["major"] + 0.01


def test_same_seed_identical_bytes_different_seed_differs():
    a = make_ocean_default(seed=3, hours=48)
    b = make_ocean_default(seed=3, hours=48)
    c = make_ocean_default(seed=4, hours=48)
    assert a.data.tobytes() == b.data.tobytes()
    assert a.data_hash() == b.data_hash()
    assert a.data_hash() != c.data_hash()
    assert np.sqrt(np.mean((a.data - c.data) ** 2)) > 0.1


def test_hours_prefix_consistent():
    # a shorter run is the prefix of the longer one (time is not rescaled)
    a = make_ocean_default(seed=1, hours=24)
    b = make_ocean_default(seed=1, hours=504)
    np.testing.assert_array_equal(a.data, b.data[:24])


def test_finer_grid_samples_same_field():
    # lengths are absolute: a 59x59 grid over the same region hits the 30x30 centres at even indices
    g = geo.north_atlantic_grid()
    fine = geo.RegionGrid(g.south, g.west, g.north, g.east, 59, 59)
    a = make_ocean_default(seed=2, hours=3)
    b = make_ocean_default(seed=2, hours=3, grid=fine)
    np.testing.assert_allclose(b.data[:, :, ::2, ::2], a.data, atol=1e-5)


def test_bad_arguments():
    with pytest.raises(FieldError):
        make_ocean_default(hours=0)
    with pytest.raises(FieldError):
        make_ocean_default(seed=-1)
    metric = geo.MetricRegionGrid(0, 10, 0, 10, 5, 5, anchor_lat=40, anchor_lon=-63)
    with pytest.raises(FieldError):
        make_ocean_default(grid=metric)
