"""Boat kinematics in a current field (pure math: no I/O, no MAVLink).

Frames and units:

* Positions are local **east/north metres** in an azimuthal-equidistant
  projection about the vehicle's home (:class:`LocalFrame`, pyproj); lat/lon are
  WGS84 degrees.
* Headings are **compass radians**: 0 = north, +pi/2 = east, clockwise positive.
  A velocity ``(ve, vn)`` has heading ``atan2(ve, vn)``.
* Currents are ``(u, v)`` = (east, north) in m/s.

Motion model (first order, one step :func:`step_boat`): the hull moves through the
water at ``speed`` along ``heading``; the ground velocity is that plus the local
current. The commanded heading is reached with a turn-rate limit and the
commanded water speed through a first-order lag (``speed_tau_s``) and an
acceleration limit. With the motor off (``motor_off``: HOLD, disarmed, no RC input) only the
hull's drag slows it through the water, quadratic in speed (``coast_drag_per_m``): fitted to
Rover 4.7 SITL's motorboat, which coasted from 5 m/s to 1.54, 0.83 and 0.37 m/s after 2, 4 and
10 s and 18.7 m in 60 s, and which, stopped in a 0.5 m/s current, took ~20 s to pick the
current up (120 s of drift from a standstill: 49-50 m, not 60). The hull has no sideways
water speed: across the bow it always moves with the current. This is deliberately simple: it
is enough to make the timing and the drift of a surveying boat realistic, not to model a hull.

Navigation (:func:`guidance`):

* ``"pursuit"`` (default): the bow points at the waypoint; the crab angle a
  cross-current needs is NOT compensated, so the boat is set down-current and
  follows a curved (pursuit) track. With a uniform current ``w`` perpendicular to
  the leg and water speed ``V`` the track is the classic river-crossing curve
  ``y = a/2 [(x/a)^(1-k) - (x/a)^(1+k)]``, ``k = w/V``, and the leg takes
  ``a V / (V^2 - w^2)`` seconds (tests check both).
* ``"crosstrack"``: like ArduPilot's L1/S-curve controllers, it steers back to the
  straight line between the previous and the next waypoint and holds the crab
  angle the current needs (velocity-triangle solution), so the track stays on the
  line and the ground speed along it is ``sqrt(V^2 - w_perp^2) + w_par``.

Current sampling (:class:`CurrentModel`): bilinear in space and linear in time
through :meth:`FlowField.sample_latlon`. Outside the field's spatial coverage, on
land/missing cells, the current moving the boat is **zero** and the current sensor
(:meth:`CurrentModel.measure`) reads nothing; in time the field is held at its
first/last snapshot (clamped), so a simulation may outlast the data.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "LocalFrame",
    "CurrentModel",
    "BoatParams",
    "BoatState",
    "guidance",
    "step_boat",
    "wrap_pi",
]


def wrap_pi(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class LocalFrame:
    """Azimuthal-equidistant east/north metres about ``(lat0, lon0)`` (pyproj)."""

    def __init__(self, lat0: float, lon0: float):
        from pyproj import CRS, Transformer

        self.lat0, self.lon0 = float(lat0), float(lon0)
        crs = CRS.from_proj4(
            f"+proj=aeqd +lat_0={self.lat0:.10f} +lon_0={self.lon0:.10f} +datum=WGS84 +units=m +no_defs"
        )
        self._fwd = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        self._inv = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)

    def to_xy(self, lat: float, lon: float) -> tuple[float, float]:
        """Degrees -> (east, north) metres."""
        x, y = self._fwd.transform(lon, lat)
        return float(x), float(y)

    def to_latlon(self, x: float, y: float) -> tuple[float, float]:
        """(east, north) metres -> (lat, lon) degrees."""
        lon, lat = self._inv.transform(x, y)
        return float(lat), float(lon)


class CurrentModel:
    """The current (east, north m/s) at a position and simulated time.

    Args:
        field: a :class:`passt_mav.fields.FlowField`, or ``None`` for still water.
        start_time: field time (the field's own units: seconds since its
            ``time_origin``, or non-dimensional time for metric fields) at
            simulated time 0 (boot).
        velocity_scale: m/s per field velocity unit (1 for geographic fields in
            m/s; e.g. 0.5 to make the cylinder's inflow 0.5 m/s).
        time_scale: simulated seconds per field time unit (1 for fields in
            seconds; for the non-dimensional cylinder, how many seconds one unit
            lasts).
        uniform: a constant ``(u, v)`` m/s added everywhere (tests, or a field-less
            drift).
    """

    def __init__(
        self,
        field=None,
        *,
        start_time: float | None = None,
        velocity_scale: float = 1.0,
        time_scale: float = 1.0,
        uniform: tuple[float, float] = (0.0, 0.0),
    ):
        if not (velocity_scale > 0 and time_scale > 0):
            raise ValueError("velocity_scale and time_scale must be positive")
        self.field = field
        self.velocity_scale = float(velocity_scale)
        self.time_scale = float(time_scale)
        self.uniform = (float(uniform[0]), float(uniform[1]))
        self.start_time = (
            float(field.times[0]) if (start_time is None and field is not None) else float(start_time or 0.0)
        )
        self._times = field.times.tolist() if field is not None else []
        self._rotate = getattr(field.grid, "velocity_to_local", None) if field is not None else None
        if field is not None and field.is_geographic:
            self._rotate = None  # lat/lon grids are already east/north

    def _interp1(self, t: float, r: float, c: float) -> tuple[float, float]:
        """One-point :meth:`FlowField.interp` (same weights, same NaN rule).

        Written out for a single point because the vectorised version costs
        ~0.2 ms per call in array set-up, which made it 60 % of a simulation
        step; tests check both agree to float precision.
        """
        f = self.field
        R, C = f.grid.shape
        T = f.n_times
        nan = (math.nan, math.nan)
        if not (0.0 <= r <= R - 1 and 0.0 <= c <= C - 1):
            return nan
        times = self._times
        if T > 1:
            if not times[0] <= t <= times[-1]:
                return nan
            k = min(bisect.bisect_right(times, t) - 1, T - 2)
            ft = k + (t - times[k]) / (times[k + 1] - times[k])
        elif t == times[0]:
            ft = 0.0
        else:
            return nan
        t0 = min(int(math.floor(ft)), max(T - 2, 0))
        r0 = min(int(math.floor(r)), R - 2)
        c0 = min(int(math.floor(c)), C - 2)
        wt, wr, wc = ft - t0, r - r0, c - c0
        acc_u = acc_v = 0.0
        for dt_, w_t in ((0, 1.0 - wt), (1, wt)):
            if w_t <= 0.0:
                continue
            blk = f.data[min(t0 + dt_, T - 1), :, r0 : r0 + 2, c0 : c0 + 2].tolist()  # [2][2][2] floats
            for dr, w_r in ((0, 1.0 - wr), (1, wr)):
                for dc, w_c in ((0, 1.0 - wc), (1, wc)):
                    w = w_t * w_r * w_c
                    if w > 0.0:
                        acc_u += blk[0][dr][dc] * w
                        acc_v += blk[1][dr][dc] * w
        return acc_u, acc_v

    def field_time(self, t_sim: float) -> float:
        """Field time at simulated time ``t_sim`` (s since boot), clamped to the data."""
        ft = self.start_time + t_sim / self.time_scale
        return float(np.clip(ft, self.field.times[0], self.field.times[-1])) if self.field is not None else ft

    def measure(self, t_sim: float, lat: float, lon: float) -> tuple[float, float] | None:
        """What a current sensor reads at ``(lat, lon)``: ``(u_east, v_north)`` m/s, or None
        where the field has no data (land, a missing cell, outside its coverage): a sensor on
        land or off the map measures nothing, it does not measure still water."""
        if self.field is not None:
            r, c = self.field.grid.latlon_to_fcell(lat, lon)
            fu, _ = self._interp1(self.field_time(t_sim), float(r), float(c))
            if not math.isfinite(fu):
                return None
        return self.at(t_sim, lat, lon)

    def at(self, t_sim: float, lat: float, lon: float) -> tuple[float, float]:
        """``(u_east, v_north)`` m/s at ``(lat, lon)`` and simulated time ``t_sim``."""
        u, v = self.uniform
        if self.field is None:
            return u, v
        r, c = self.field.grid.latlon_to_fcell(lat, lon)
        fu, fv = self._interp1(self.field_time(t_sim), float(r), float(c))
        if not (math.isfinite(fu) and math.isfinite(fv)):
            return u, v  # outside coverage or a missing cell: still water (documented)
        if self._rotate is not None:
            fu, fv = (float(a) for a in self._rotate(fu, fv))
        return u + fu * self.velocity_scale, v + fv * self.velocity_scale


@dataclass(frozen=True)
class BoatParams:
    """Hull and controller limits.

    Attributes:
        max_turn_rate_dps: turn-rate limit, degrees per second.
        speed_tau_s: first-order time constant of water speed, seconds.
        max_accel: acceleration limit, m/s^2.
        max_speed: hull speed limit through the water, m/s.
        nav: ``"pursuit"`` (crab not compensated, default) or ``"crosstrack"``.
        l1_lookahead_m: look-ahead distance of the cross-track controller, metres.
        coast_drag_per_m: with the motor off, dv/dt = -k v^2 through the water (k in 1/m; Rover
            SITL's motorboat: 0.25); 0 stops the hull with the powered lag instead.
    """

    max_turn_rate_dps: float = 60.0
    speed_tau_s: float = 0.5
    max_accel: float = 2.0
    max_speed: float = 10.0
    nav: str = "pursuit"
    l1_lookahead_m: float = 10.0
    coast_drag_per_m: float = 0.25


@dataclass
class BoatState:
    """Kinematic state: position (east, north m), compass heading (rad), water speed (m/s).

    ``ground_ve, ground_vn`` (m/s) and ``current`` (u, v m/s) are from the last step.
    """

    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0
    speed: float = 0.0
    ground_ve: float = 0.0
    ground_vn: float = 0.0
    turn_rate: float = 0.0
    current: tuple[float, float] = (0.0, 0.0)


def guidance(
    state: BoatState,
    target: tuple[float, float],
    speed: float,
    current: tuple[float, float],
    params: BoatParams,
    origin: tuple[float, float] | None = None,
) -> tuple[float, float]:
    """Commanded ``(heading rad, water speed m/s)`` to reach ``target`` (east, north m).

    ``origin`` is the previous waypoint (start of the leg) used by the
    ``"crosstrack"`` controller; ``"pursuit"`` ignores it and the current.
    """
    dx, dy = target[0] - state.x, target[1] - state.y
    if params.nav == "pursuit" or origin is None:
        return math.atan2(dx, dy), speed
    if params.nav != "crosstrack":
        raise ValueError(f"unknown nav {params.nav!r}; choose 'pursuit' or 'crosstrack'")
    ox, oy = origin
    lx, ly = target[0] - ox, target[1] - oy
    leg = math.hypot(lx, ly)
    if leg < 1e-6:
        return math.atan2(dx, dy), speed
    ux, uy = lx / leg, ly / leg
    # along-track position of the boat, then a carrot point L ahead on the line
    s = (state.x - ox) * ux + (state.y - oy) * uy
    s_c = min(max(s, 0.0) + params.l1_lookahead_m, leg)
    cx, cy = ox + ux * s_c, oy + uy * s_c
    gx, gy = cx - state.x, cy - state.y
    g = math.hypot(gx, gy)
    if g < 1e-9:
        return math.atan2(dx, dy), speed
    gx, gy = gx / g, gy / g
    # velocity triangle: water velocity w such that w + current is parallel to (gx, gy)
    cu, cv = current
    c_perp = -cu * gy + cv * gx  # current across the desired track (left +)
    c_par = cu * gx + cv * gy
    if abs(c_perp) >= speed:
        # too strong to cancel: push straight against it
        wx, wy = gy * math.copysign(speed, c_perp), -(gx) * math.copysign(speed, c_perp)
        return math.atan2(wx, wy), speed
    along = math.sqrt(speed * speed - c_perp * c_perp)
    wx = gx * along - (-gy) * c_perp
    wy = gy * along - gx * c_perp
    del c_par
    return math.atan2(wx, wy), speed


def step_boat(
    state: BoatState,
    cmd_heading: float,
    cmd_speed: float,
    current: tuple[float, float],
    dt: float,
    params: BoatParams,
    motor_off: bool = False,
) -> BoatState:
    """Advance ``state`` by ``dt`` seconds (in place; also returned).

    The heading turns toward ``cmd_heading`` at most ``max_turn_rate_dps``; the
    water speed follows ``cmd_speed`` with a first-order lag and the acceleration
    limit; the position integrates water velocity plus ``current``. ``motor_off``: no thrust, the
    water speed decays by the hull's quadratic drag alone (``coast_drag_per_m``; ``cmd_speed`` ignored).
    """
    max_turn = math.radians(params.max_turn_rate_dps) * dt
    err = wrap_pi(cmd_heading - state.heading)
    turn = max(-max_turn, min(max_turn, err))
    state.heading = wrap_pi(state.heading + turn)
    state.turn_rate = turn / dt if dt > 0 else 0.0
    if motor_off and params.coast_drag_per_m > 0:
        # dv/dt = -k v^2, solved exactly over the step (speed >= 0)
        state.speed = state.speed / (1.0 + params.coast_drag_per_m * state.speed * dt)
    else:
        target = 0.0 if motor_off else max(0.0, min(params.max_speed, cmd_speed))
        dv = (
            (target - state.speed) * (1.0 - math.exp(-dt / params.speed_tau_s))
            if params.speed_tau_s > 0
            else target - state.speed
        )
        dv = max(-params.max_accel * dt, min(params.max_accel * dt, dv))
        state.speed += dv
    ve = state.speed * math.sin(state.heading) + current[0]
    vn = state.speed * math.cos(state.heading) + current[1]
    state.x += ve * dt
    state.y += vn * dt
    state.ground_ve, state.ground_vn = ve, vn
    state.current = (float(current[0]), float(current[1]))
    return state
