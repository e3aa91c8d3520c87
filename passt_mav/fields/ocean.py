"""The embedded synthetic North Atlantic surface-current field (the "ocean" scenario).

A physically plausible stand-in for the paper's HYCOM/RTOFS crop, generated in
well under a second from a seed, so that the product works without downloading
ocean-model data. It is built from a streamfunction ``psi`` (m^2/s):

* a meandering Gulf-Stream-like jet, ``psi_jet = -U0 W tanh(n / W)`` with
  ``n = (y - Y(x, t)) / sqrt(1 + Y'^2)`` the distance across the jet axis
  ``Y(x, t)``; the along-axis speed profile is ``U0 sech^2(n / W)`` (core ``U0``
  1.45-1.6 m/s, ``W`` 30-38 km, so the full width at half maximum is 53-67 km),
  kept where the meanders steepen. The axis carries two meander waves
  (wavelengths 300-420 and 220-300 km, amplitudes 22-32 and 10-18 km) travelling
  east at 5-10 km/day;
* three to five Gaussian rings ``psi = G exp(-r^2 / R^2)`` (radius 35-55 km, peak
  swirl 0.25-0.45 m/s, centres 70-110 km off the jet): warm-core (anticyclonic,
  clockwise) rings north of the jet, cold-core (cyclonic) rings south of it,
  drifting south-west at 2-6 km/day;
* a spatially uniform M2 tidal ellipse (period 12.42 h, semi-axes 2-5 cm/s),
  which is both divergence- and vorticity-free.

Velocities come from the streamfunction on the sphere,
``u = -(1/R) dpsi/dphi`` and ``v = 1/(R cos phi) dpsi/dlambda``, evaluated by
central differences with a step of 1e-5 degrees (1 m) around each cell centre, so
the field is non-divergent on the sphere up to rounding; a coarse grid's own
centred-difference divergence is only its truncation error (RMS 0.5-0.7 % of
the vorticity's on the 30x30 grid, see tests/test_ocean.py).

The maximum speed over the 504 h of a seed lies in about 1.5-2.0 m/s (the jet
core plus the tide, or a ring brushing the jet; measured 1.52-1.98 m/s for seeds
0-11). Over the 504 h the jet-axis latitude at a fixed longitude swings by
roughly 25-80 km (measured 27-81 km at the middle column, seeds 0-11), since
the meanders travel 100-210 km, a quarter to two thirds of a wavelength.
Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from passt_mav.errors import FieldError
from passt_mav.fields.field import FlowField

__all__ = ["make_ocean_default", "OCEAN_TIME_ORIGIN", "M2_PERIOD_S", "EARTH_RADIUS_M"]

#: time of the first snapshot (the paper's data start in March 2018)
OCEAN_TIME_ORIGIN = "2018-03-01T00:00:00Z"
#: principal lunar semi-diurnal tide period, seconds
M2_PERIOD_S = 12.4206012 * 3600.0
#: mean Earth radius (IUGG), metres; the field lives on this sphere
EARTH_RADIUS_M = 6371008.8
_DAY = 86400.0
_H_DEG = 1e-5  # finite-difference step for the streamfunction, degrees (~1 m)


def _draw_parameters(rng: np.random.Generator) -> dict[str, Any]:
    """All random choices of one realisation, in SI units (m, s, m/s)."""
    jet = {
        "U0": float(rng.uniform(1.45, 1.6)),
        "W": float(rng.uniform(30e3, 38e3)),
        "y0": float(rng.uniform(-15e3, 15e3)),
        "waves": [],
    }
    for lam_rng, amp_rng in (((300e3, 420e3), (22e3, 32e3)), ((220e3, 300e3), (10e3, 18e3))):
        jet["waves"].append(
            {
                "wavelength": float(rng.uniform(*lam_rng)),
                "amplitude": float(rng.uniform(*amp_rng)),
                "speed": float(rng.uniform(5e3, 10e3)) / _DAY,  # eastward phase speed
                "phase": float(rng.uniform(0, 2 * math.pi)),
            }
        )
    rings = []
    n_rings = int(rng.integers(3, 6))
    for i in range(n_rings):
        warm = bool(i % 2 == 0) if i < 2 else bool(rng.integers(0, 2))
        radius = float(rng.uniform(35e3, 55e3))
        vmax = float(rng.uniform(0.25, 0.45))
        # peak swirl of G exp(-r^2/R^2) is sqrt(2) |G| e^-1/2 / R
        gamma = vmax * radius / (math.sqrt(2.0) * math.exp(-0.5))
        side = 1.0 if warm else -1.0  # warm rings pinch off north of the stream
        rings.append(
            {
                "warm": warm,
                "radius": radius,
                "vmax": vmax,
                # positive G is anticyclonic (clockwise) in this sign convention
                "G": gamma if warm else -gamma,
                "x0": float(rng.uniform(-90e3, 130e3)),
                "y0": float(side * rng.uniform(70e3, 110e3)),
                "drift_speed": float(rng.uniform(2e3, 6e3)) / _DAY,
                "drift_dir_deg": float(rng.uniform(200.0, 250.0)),  # towards SW, math angle from east
            }
        )
    tide = {
        "period_s": M2_PERIOD_S,
        "major": float(rng.uniform(0.03, 0.05)),
        "minor": float(rng.uniform(0.02, 0.03)),
        "orientation_deg": float(rng.uniform(0, 180)),
        "phase": float(rng.uniform(0, 2 * math.pi)),
    }
    return {"jet": jet, "rings": rings, "tide": tide}


def _psi(x: np.ndarray, y: np.ndarray, t: float, p: dict[str, Any]) -> np.ndarray:
    """Streamfunction (m^2/s) at local equirectangular metres (x east, y north), time t (s)."""
    jet = p["jet"]
    axis = np.full_like(x, jet["y0"])
    slope = np.zeros_like(x)
    for w in jet["waves"]:
        k = 2 * math.pi / w["wavelength"]
        arg = k * (x - w["speed"] * t) + w["phase"]
        axis = axis + w["amplitude"] * np.sin(arg)
        slope = slope + w["amplitude"] * k * np.cos(arg)
    # dividing by sqrt(1 + Y'^2) measures the distance normal to the axis, so the
    # core speed stays U0 (and the width W) where the meanders steepen
    stretch = np.sqrt(1.0 + slope**2)
    psi = -jet["U0"] * jet["W"] * np.tanh((y - axis) / (jet["W"] * stretch))
    for r in p["rings"]:
        th = math.radians(r["drift_dir_deg"])
        xc = r["x0"] + r["drift_speed"] * t * math.cos(th)
        yc = r["y0"] + r["drift_speed"] * t * math.sin(th)
        psi = psi + r["G"] * np.exp(-((x - xc) ** 2 + (y - yc) ** 2) / r["radius"] ** 2)
    return psi


def _tide(t: np.ndarray, p: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Uniform M2 ellipse (u, v) in m/s at times t (s)."""
    td = p["tide"]
    ph = 2 * math.pi * t / td["period_s"] + td["phase"]
    a, b = td["major"] * np.cos(ph), td["minor"] * np.sin(ph)
    th = math.radians(td["orientation_deg"])
    return a * math.cos(th) - b * math.sin(th), a * math.sin(th) + b * math.cos(th)


@dataclass(frozen=True)
class _Stencil:
    """The centred-difference stencil of every cell centre: the local plane coordinates ``(x, y)``
    (m, east/north of the grid's centre) of its four neighbours ``_H_DEG`` north, south, east and
    west, the cosine of its latitude and the stencil's full width ``dphi`` (radians)."""

    north: tuple[np.ndarray, np.ndarray]
    south: tuple[np.ndarray, np.ndarray]
    east: tuple[np.ndarray, np.ndarray]
    west: tuple[np.ndarray, np.ndarray]
    coslat: np.ndarray
    dphi: float

    @classmethod
    def of(cls, grid, lat0: float, lon0: float) -> _Stencil:
        """The stencil of ``grid``'s cell centres, plane coordinates about ``(lat0, lon0)`` (degrees)."""
        lat, lon = np.meshgrid(grid.lats, grid.lons, indexing="ij")  # (rows, cols) degrees
        R, h = EARTH_RADIUS_M, _H_DEG
        coslat0 = math.cos(math.radians(lat0))

        def xy(la, lo):
            return R * coslat0 * np.radians(lo - lon0), R * np.radians(la - lat0)

        # the four stencil points are fixed in space; only psi's time argument changes
        return cls(
            xy(lat + h, lon),
            xy(lat - h, lon),
            xy(lat, lon + h),
            xy(lat, lon - h),
            np.cos(np.radians(lat)),
            math.radians(2 * h),
        )

    def velocity(self, t: float, p: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """``(u, v)`` (m/s, east/north) of the streamfunction at time ``t`` (s): exactly solenoidal on the sphere."""
        R = EARTH_RADIUS_M
        u = -(_psi(*self.north, t, p) - _psi(*self.south, t, p)) / (R * self.dphi)
        v = (_psi(*self.east, t, p) - _psi(*self.west, t, p)) / (R * self.coslat * self.dphi)
        return u, v


def _check_ocean_args(grid, hours, seed) -> tuple[Any, int, int]:
    """``(grid, hours, seed)`` checked: a geographic grid (default ``geo.north_atlantic_grid()``),
    a positive whole number of hours and a non-negative seed."""
    import geo

    if grid is None:
        grid = geo.north_atlantic_grid()
    if not isinstance(grid, geo.RegionGrid) or isinstance(grid, geo.MetricRegionGrid):
        raise FieldError("the synthetic ocean field needs a geographic RegionGrid (lat/lon)")
    if int(hours) != hours or hours < 1:
        raise FieldError(f"hours must be a positive integer, got {hours!r}")
    hours = int(hours)
    seed = int(seed)
    if seed < 0:
        raise FieldError(f"seed must be >= 0, got {seed}")
    return grid, hours, seed


def make_ocean_default(*, seed: int = 0, hours: int = 504, grid=None) -> FlowField:
    """Synthetic North Atlantic surface currents (see module docstring).

    Args:
        seed: selects the realisation (meander phases, rings, tide); the same seed
            gives byte-identical data.
        hours: number of hourly snapshots (the paper uses 504 = 21 days).
        grid: a :class:`geo.RegionGrid`; default ``geo.north_atlantic_grid()``. The
            jet runs through the grid's centre; lengths are absolute (km), so a
            finer grid over the same region samples the same field.

    Returns:
        A :class:`FlowField`, data ``(hours, 2, rows, cols)`` float32 in m/s
        (u east, v north, row 0 south), times in seconds since 2018-03-01T00Z.
    """
    grid, hours, seed = _check_ocean_args(grid, hours, seed)
    p = _draw_parameters(np.random.default_rng(seed))
    lat0 = (grid.south + grid.north) / 2.0
    lon0 = (grid.west + grid.east) / 2.0
    stencil = _Stencil.of(grid, lat0, lon0)
    times = np.arange(hours, dtype=np.float64) * 3600.0
    tu, tv = _tide(times, p)
    out = np.empty((hours, 2, grid.rows, grid.cols), dtype=np.float32)
    for i, t in enumerate(times):
        u, v = stencil.velocity(t, p)
        out[i, 0] = u + tu[i]
        out[i, 1] = v + tv[i]
    attrs = {
        "title": "passt_mav synthetic North Atlantic surface currents",
        "generator": "passt_mav.fields.ocean.make_ocean_default",
        "seed": seed,
        "hours": hours,
        "parameters": p,
        "anchor_lat": lat0,
        "anchor_lon": lon0,
        "source": "synthetic: meandering jet + drifting rings + uniform M2 tide from a streamfunction",
    }
    return FlowField(out, grid, times, OCEAN_TIME_ORIGIN, "m s-1", attrs)
