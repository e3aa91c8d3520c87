"""The between-leg step of PASST on a vehicle: one implementation for the controller and the replay.

Pure: no MAVLink, no vehicle, no files. :class:`LegStep` takes the loop
(:class:`~passt_mav.loop.passt.PasstLoop`), the state, the vehicle's position and clock
reading, and the leg's samples, and returns the plan and the new state with every
figure the controller records. :class:`passt_mav.vehicle.controller.MissionController` calls it
between the legs it flies; :func:`passt_mav.analysis.replay.replay` calls it on legs
rebuilt from a log, so a replay repeats the controller's decisions exactly.

One leg::

    position (lat, lon deg) -> start cell (region + margin and land checked)
    clock reading (time_boot_ms, boot) -> field time t_now -> forecast the state
        k = round((t_now - t_state) / dt) snapshots forward        [LegStep.plan]
    -> PasstLoop.plan_leg (only the moves the boat can make in the forecast current)
    -> the path timed in that current -> the snapshots it spans -> PlannedLeg
    ... the vehicle flies it ...
    samples (time_boot_ms, boot, lat, lon, u, v m/s east/north)
    -> field units and frame, field time, thinning per (cell, snapshot bin)
    -> the leg stretched to its last sample -> GP update -> state at the leg's end
    -> RMSE vs the truth (PASST, and the model alone from t0)           [LegStep.absorb]

Units: positions in degrees (WGS84), velocities in m/s east/north on the vehicle side
and in the field's units and grid frame on the model side; field time in the field's
units (s for geographic fields; scaled units for the cylinder, ``field.time_scale``
vehicle seconds per unit).
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from dataclasses import field as _dcfield
from typing import Any

import numpy as np

from passt_mav.errors import ReconstructionError, UserError
from passt_mav.loop.measurement import rmse, truth_at  # noqa: F401 - the measurement rules, re-exported
from passt_mav.loop.measurement import sample_columns as _columns
from passt_mav.loop.threads import single_threaded

__all__ = [
    "THINNING",
    "FieldClock",
    "LegStep",
    "PlannedLeg",
    "AbsorbedLeg",
    "utc_epoch",
    "to_field_units",
    "thin_samples",
    "leg_steps",
    "extend_leg_to_end",
    "pure_model_at",
    "rmse",
    "truth_at",
    "build_predictor",
    "build_loop",
    "FleetStep",
    "in_field_time",
    "FIELD_TIME",
]

log = logging.getLogger(__name__)

THINNING = (
    "samples averaged per (nearest grid cell, snapshot bin round((t - t_start)/dt)); "
    "position, time and velocity averaged in each group"
)


# -- clock and sample preparation -------------------------------------------------------------
@dataclass(frozen=True)
class FieldClock:
    """Vehicle time since boot -> field time: ``t_boot0 + time_boot_ms / 1000 / time_scale``.

    ``source``: how ``t_boot0`` was found (``utc``: the vehicle's UTC at boot; ``boot``: given
    or snapshot t0). ``later_boots``: ``t_boot0`` of each boot after a reboot (boot 1, 2, ...).
    """

    t_boot0: float
    time_scale: float = 1.0
    source: str = "boot"
    later_boots: tuple[float, ...] = ()

    def field_time(self, time_boot_ms, boot=0):
        """Field time of ``time_boot_ms`` (ms) of boot ``boot`` (0 = the first; scalar or array)."""
        tb = np.asarray(time_boot_ms, dtype=np.float64)
        anchors = np.array((self.t_boot0,) + tuple(self.later_boots), dtype=np.float64)
        b = np.clip(np.asarray(boot, dtype=np.int64), 0, len(anchors) - 1)
        return anchors[b] + tb / 1000.0 / self.time_scale

    def describe(self) -> dict[str, Any]:
        d = {
            "rule": "t_field = t_boot0 + time_boot_ms / 1000 / time_scale",
            "t_boot0": self.t_boot0,
            "time_scale": self.time_scale,
            "source": self.source,
        }
        if self.later_boots:
            d["later_boots"] = list(self.later_boots)
        return d


def utc_epoch(iso: str) -> float:
    """Epoch seconds of an ISO-8601 UTC time (a field's ``time_origin``)."""
    t = _dt.datetime.fromisoformat(iso)  # Python 3.11 reads a trailing "Z"
    return (t if t.tzinfo else t.replace(tzinfo=_dt.UTC)).timestamp()


def to_field_units(grid, u, v, velocity_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """East/north m/s -> the field's velocity units and frame (inverse of the simulator's mapping)."""
    u = np.asarray(u, float) / velocity_scale
    v = np.asarray(v, float) / velocity_scale
    rot = float(getattr(grid, "rotation_deg", 0.0) or 0.0)
    if rot:
        th = math.radians(rot)
        u, v = u * math.cos(th) + v * math.sin(th), -u * math.sin(th) + v * math.cos(th)
    return u, v


def thin_samples(grid, t, lat, lon, u, v, *, t_start: float, dt: float):
    """:class:`~passt_mav.loop.passt.Samples` averaged per (nearest cell, snapshot bin); see module doc.

    t: field time of each sample; lat/lon degrees; u/v in field units. Samples off
    the grid are dropped. Returns Samples with fractional cells (mean position).
    """
    from passt_mav.loop.passt import Samples

    t, lat, lon, u, v = (np.asarray(a, float).reshape(-1) for a in (t, lat, lon, u, v))
    if t.size == 0:
        return Samples(t, t, t, t, t)
    r, c = grid.latlon_to_fcell(lat, lon)
    r, c = np.asarray(r, float), np.asarray(c, float)
    inside = (r >= 0) & (r <= grid.rows - 1) & (c >= 0) & (c <= grid.cols - 1) & np.isfinite(u) & np.isfinite(v)
    t, r, c, u, v = t[inside], r[inside], c[inside], u[inside], v[inside]
    key = np.stack([np.floor(r + 0.5), np.floor(c + 0.5), np.round((t - t_start) / dt)], axis=1).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = np.bincount(inv)

    def mean(a):
        return np.bincount(inv, weights=a) / n

    return Samples(mean(t), mean(r), mean(c), mean(u), mean(v))


def leg_steps(config, grid, speed: float, dt: float, time_scale: float) -> int:
    """Snapshots a leg is planned to span in still water: L moves x mean cell size / speed (see
    passt.steps_for_leg; a current-aware mission times the planned path instead, :meth:`LegStep.timing`).

    speed in m/s, dt in field time units, time_scale in vehicle seconds per field time unit.
    """
    from passt_mav.loop.passt import steps_for_leg

    return steps_for_leg(config.planner.path_length, grid.mean_cell_size_m, speed, dt * time_scale)


def extend_leg_to_end(loop, plan, t_samples, dt: float) -> int:
    """Stretch ``plan`` (a :class:`~passt_mav.loop.passt.LegPlan`) to the time the leg really ended.

    The leg was sized before it flew (L x mean cell / speed); diagonal moves, turns and the
    current make the real leg longer. Reconstructing at the planned end would compare late
    samples with a forecast clipped to that end (stale residuals), so the forecast is
    extended to the last sample's field time ``t_samples`` (field units). Returns the
    leg's steps. Shared by the controller and replay, which must agree exactly.
    """
    t = np.asarray(t_samples, float)
    if t.size:
        steps_actual = max(1, int(round((float(np.max(t)) - plan.t_start) / dt)))
        if steps_actual > plan.steps:
            plan.forecast = loop.forecast(plan.forecast[0], steps_actual)
            plan.steps = steps_actual
    return int(plan.steps)


def pure_model_at(loop, field, t0_index: int, dt: float, t: float, cache: dict) -> np.ndarray | None:
    """The model alone from the truth at snapshot ``t0_index`` (no re-initialisation), at field time ``t``.

    Linear between the model's steps; (2, R, C) float64, or None before t0 or without a model.
    ``cache`` (a dict the caller keeps) holds the trajectory so later calls only extend it.
    Shared by the controller and replay, whose RMSE figures must agree to 1e-6.
    """
    if loop.predictor is None:
        return None
    t0 = float(field.times[t0_index])
    x = (t - t0) / dt
    if x < 0:
        return None
    need = int(math.ceil(x)) + 1
    pure = cache.get("pure")
    if pure is None or len(pure) <= need:
        s = field.state_at(t0_index)  # gaps that come and go: FlowField.state_at
        pure = cache["pure"] = loop.model_alone(s, max(need, 2 * (need // 2 + 1)))
    k = int(math.floor(x))
    w = x - k
    return (1 - w) * pure[k].astype(float) + w * pure[min(k + 1, len(pure) - 1)].astype(float)


# -- building blocks from a mission config --------------------------------------------------------
def build_predictor(spec: str, field, *, echo: Callable[[str], None] = print) -> tuple[object | None, dict]:
    """The predictor named by a mission's ``model`` and what was used.

    ``builtin:*`` / ``.pt``: loaded; if that fails, a warning is printed and DMD is
    fitted on ``field`` instead (recorded as ``fallback``). Registry names are fitted on
    ``field``. Returns ``(predictor, info)`` with info keys ``requested``, ``used``, ``fallback``.
    """
    from passt_mav.models.base import PREDICTORS, load_predictor, make_predictor

    info: dict[str, Any] = {"requested": spec, "used": spec, "fallback": None}
    if spec in PREDICTORS:
        return make_predictor(spec).fit(field), info
    try:
        pred = load_predictor(spec)
        shape = getattr(pred, "grid_shape_", None)
        if shape is not None and tuple(shape)[-2:] != tuple(field.grid.shape):
            raise UserError(f"model {spec} is for a {tuple(shape)[-2:]} grid, the mission's is {field.grid.shape}")
        from passt_mav.models.evaluate import echo_skill

        echo_skill(spec, getattr(pred, "metadata_", None), echo)
        return pred, info
    except (UserError, OSError, RuntimeError, KeyError, ValueError) as exc:
        msg = f"WARNING: model {spec} could not be loaded ({exc}); falling back to DMD fitted on the mission's field"
        echo(msg)
        log.warning(msg)
        info.update(used="dmd", fallback=str(exc))
        return make_predictor("dmd").fit(field), info


def build_loop(config, predictor, grid, land=None):
    """:class:`PasstLoop` from a mission config (planner, reward, L, GP prior/options, seeds)."""
    from passt_mav.loop.online import ModelUpdate
    from passt_mav.loop.passt import LoopOptions

    preset = config.loop_preset()
    gp_kw = {"seed": config.seeds.gp}
    if config.sensors.noise_std > 0:
        gp_kw["noise_std"] = config.sensors.noise_std
    gp_kw.update(preset.gp_kwargs())  # the mission's bias and nugget, explicitly: the API's defaults may differ
    gp_kw.update(config.gp.options)
    options = LoopOptions(
        **preset.loop_kwargs(),
        planner_kw=dict(config.planner.options),
        path_length=config.planner.path_length,
        steps_per_leg=config.steps_per_leg or 1,
        gp_kw=gp_kw,
        hyper=config.gp.hyper,
        model_update=ModelUpdate(**config.model_update.model_dump()),
        # planner.current_aware: moves the boat cannot make in the forecast current are not offered (the speed
        # in the field's velocity units; a fleet's boat plans at its own, LegStep.plan)
        vehicle_speed=float(config.vehicle.speed_mps) / float(config.field.velocity_scale)
        if getattr(config.planner, "current_aware", False)
        else None,
        transit_kw=_hold_kw(
            config.vehicle.speed_mps,
            config.vehicle.max_water_speed_mps,
            1.0 / float(config.field.velocity_scale),
        ),
    )
    loop = options.loop(predictor, grid, land=land, seed=config.seeds.planner)
    # a mission's estimate is written with its posterior std (estimate.nc u_std/v_std; exports read it):
    # one more triangular solve per leg, nothing next to a leg's minutes on the water
    loop.keep_std = True
    return loop


def _hold_kw(speed: float, max_water_speed: float | None, scale: float = 1.0) -> dict:
    """How an ArduPilot boat holds its speed (:func:`passt_mav.planning.transit.ground_speed`): over ground
    along the bow, up to the hull's top speed through the water (``max_water_speed`` m/s; None: ``speed``),
    both times ``scale`` (1 / ``field.velocity_scale``: the field's velocity units)."""
    mws = float(speed) if max_water_speed is None else float(max_water_speed)
    return {"hold": "ground", "max_water_speed": mws * float(scale)}


# -- the step -------------------------------------------------------------------------------------
@dataclass
class PlannedLeg:
    """A leg as planned: where from, when, and the plan (:class:`~passt_mav.loop.passt.LegPlan`).

    ``start_cell`` (row, col); ``start_latlon`` deg or None; ``t_now`` field time of the
    clock reading (None when ``k`` was given); ``k`` snapshots forecast before planning;
    ``steps`` snapshots the leg is planned to span (stretched by :meth:`LegStep.absorb`
    when the leg really took longer); ``planning_s`` wall seconds of ``plan_leg``.
    """

    index: int
    start_cell: tuple[int, int]
    start_latlon: tuple[float, float] | None
    t_now: float | None
    k: int
    plan: Any
    steps: int
    planning_s: float
    clock_reading: tuple[int, int] | None = None  # (time_boot_ms, boot) the vehicle's clock said at t_now
    #: the path timed in the forecast current (:class:`passt_mav.planning.transit.LegTiming`, vehicle s
    #: from the leg's start; None when the mission's planner is not current-aware)
    timing: Any = None
    #: vehicle seconds the leg is expected to take (:meth:`LegStep.expected_vehicle_s`; None before)
    planned_duration_vehicle_s: float | None = None
    #: the boat's commanded speed the leg was planned for (m/s) and its hull's top speed through the water
    speed_mps: float | None = None
    max_water_speed_mps: float | None = None

    @property
    def t_start(self) -> float:
        return float(self.plan.t_start)

    def record(self, dt: float) -> dict[str, Any]:
        """The leg record's planning fields (``leg.json``)."""
        return {
            "index": self.index,
            "start_cell": list(self.start_cell),
            "start_latlon": None if self.start_latlon is None else list(self.start_latlon),
            "path": self.plan.path.tolist(),
            "t_start": self.t_start,
            "t_end": self.t_start + self.steps * dt,
            "steps": self.steps,
            "forecast_steps_before": self.k,
            "planning_s": self.planning_s,
            "planning_timings": dict(self.plan.timings),
            # the map the path was planned on ((R, C), row 0 south; 0 = land or nothing to gain),
            # for the report: why the boat goes where it goes
            "reward_map": np.round(np.nan_to_num(np.asarray(self.plan.reward, float)), 4).tolist(),
            "clock_reading": None
            if self.clock_reading is None
            else {"time_boot_ms": self.clock_reading[0], "boot": self.clock_reading[1]},
            # vehicle s from the leg's start at which the boat should reach each path cell in the forecast
            # current, and the ground speed of each move (m/s); None: timed in still water
            "planned_arrival_vehicle_s": None
            if self.timing is None
            else [round(float(x), 1) for x in np.nan_to_num(self.timing.arrival, posinf=-1.0)],
            "planned_ground_speed_m_s": None
            if self.timing is None
            else [round(float(x), 3) for x in np.nan_to_num(self.timing.ground_speed, nan=0.0)],
        }


@dataclass
class AbsorbedLeg:
    """What a leg's samples made of the state.

    ``samples``: the thinned :class:`~passt_mav.loop.passt.Samples` the GP got (field units);
    ``state`` (2, R, C) float32 at field time ``t_state`` (the leg's end); ``steps`` the
    leg's snapshots after stretching to its last sample; ``gp_s`` wall seconds of the
    update; RMSE in field units over water cells vs the truth at ``t_state`` (None when
    unknown); ``note`` says why the state is the forecast (no usable samples).
    """

    samples: Any
    state: np.ndarray
    t_state: float
    steps: int
    n_samples: int
    gp_s: float = 0.0
    rmse_passt: float | None = None
    rmse_model: float | None = None
    note: str | None = None
    gp: dict | None = None
    #: GP posterior std (2, R, C) float32 of ``state`` (field units; None when the state is the forecast)
    std: np.ndarray | None = None
    #: the guard's record (:func:`passt_mav.loop.guard.guard_record`) with its RMSE in m/s and its
    #: one-line ``message`` (None when the loop's forecast fitted the samples at least as well)
    guard: dict | None = None
    #: the map's std against the truth (:func:`passt_mav.loop.scoring.leg_scores`; None when unknown)
    calibration: dict | None = None
    #: the trivial maps' RMSE beside the map's (``zero``, ``forecast_mean``, ``map``, ``beaten_by``)
    baselines: dict | None = None

    def record(self) -> dict[str, Any]:
        return {
            "t_state": self.t_state,
            "steps": self.steps,
            "gp_s": self.gp_s,
            "n_samples": self.n_samples,
            "n_gp_points": len(self.samples),
            "rmse_passt": self.rmse_passt,
            "rmse_model": self.rmse_model,
            "gp": self.gp,
            "guard": self.guard,
            "calibration": self.calibration,
            "baselines": self.baselines,
        }


@dataclass
class LegStep:
    """The between-leg step (module docstring) for one mission.

    Args:
        config: :class:`~passt_mav.mission.MissionConfig` (planner, vehicle speed, margins, units).
        field: the mission's field (dt, land, and the truth for RMSE).
        loop: the :class:`~passt_mav.loop.passt.PasstLoop` (:func:`build_loop`); its GP
            hyper-parameters and planner seeds carry from leg to leg.
        truth_known: compute RMSE vs ``field`` (the field is what the vehicle measures).
    """

    config: Any
    field: Any
    loop: Any
    truth_known: bool = True
    _pure: dict = _dcfield(default_factory=dict, repr=False)
    _in_flight: dict = _dcfield(default_factory=dict, repr=False)  # leg index -> PlannedLeg, until absorbed
    _cell_m: tuple | None = _dcfield(default=None, repr=False)  # the grid's (dy, dx) metres, once

    def __post_init__(self) -> None:
        # The GP carries a residual no longer than the mission's field stays correlated in time
        # (GPReconstructor.max_time_scale), unless the mission's gp.options set max_time_scale itself
        # (a number in field time units, or null for no cap).
        gp = getattr(self.loop, "gp", None)
        if gp is not None and "max_time_scale" not in self.config.gp.options:
            gp.max_time_scale = self.field.decorrelation_time()

    @property
    def grid(self):
        return self.field.grid

    @property
    def dt(self) -> float:
        return float(self.field.dt)

    @property
    def speed(self) -> float:
        """Vehicle speed in m/s (the mission's ``vehicle.speed_mps``)."""
        return float(self.config.vehicle.speed_mps)

    @property
    def current_aware(self) -> bool:
        """Legs planned and timed in the forecast current (the mission's ``planner.current_aware``)."""
        return bool(getattr(self.config.planner, "current_aware", False))

    def timing(self, path, forecast, speed: float, *, start_s: float = 0.0, max_water_speed: float | None = None):
        """The grid ``path`` timed in the current of ``forecast`` ((S+1, 2, R, C) field units, snapshot 0
        at the leg's start, ``dt`` apart; held after the last) by an ArduPilot boat commanded ``speed`` m/s
        (held over ground up to the hull's ``max_water_speed`` m/s through the water, default ``speed``):
        :func:`passt_mav.planning.transit.leg_timing` in m/s and vehicle seconds."""
        from passt_mav.planning.transit import leg_timing

        cur = np.asarray(forecast, np.float64) * float(self.config.field.velocity_scale)
        if self._cell_m is None:
            self._cell_m = self.grid.cell_size_m
        snap_s = self.dt * float(self.config.field.time_scale)
        hold = _hold_kw(speed, max_water_speed)
        return leg_timing(path, cur, self._cell_m, float(speed), snapshot_s=snap_s, start_s=start_s, **hold)

    def expected_vehicle_s(self, index, cells, speed: float, still_s: float) -> float:
        """Vehicle seconds leg ``index`` should take over the waypoint ``cells`` ((n, 2) corner cells of
        the mission flown; None = the planned path) at ``speed`` m/s: a current-aware mission's figure
        is the approach from the planned start position to the first cell's centre and the path's moves,
        timed in the leg's forecast current from the clock reading it was planned at (as many snapshots
        as are forecast, the last held), else
        ``still_s`` (the caller's still-water figure). Kept as the planned leg's
        ``planned_duration_vehicle_s``."""
        planned = self._in_flight.get(index)
        if planned is None:
            return float(still_s)
        out = float(still_s)
        if self.current_aware:
            from passt_mav.planning.transit import corners_to_path, segment_timing

            path = planned.plan.path
            if cells is not None:
                try:
                    path = corners_to_path(cells)
                except ValueError:
                    pass
            path = np.asarray(path, np.int64)
            start_s = 0.0
            if planned.start_latlon is not None:  # the approach: from where the boat is to the start cell's centre
                fr, fc = self.grid.latlon_to_fcell(*planned.start_latlon)
                if self._cell_m is None:
                    self._cell_m = self.grid.cell_size_m
                dy, dx = self._cell_m
                d = np.array([(path[0, 1] - float(fc)) * dx, (path[0, 0] - float(fr)) * dy])
                c0 = np.asarray(planned.plan.forecast[0][:, path[0, 0], path[0, 1]], np.float64)
                c0 = np.nan_to_num(c0 * float(self.config.field.velocity_scale))
                dur, _, _ = segment_timing(d, c0, float(speed), **_hold_kw(speed, planned.max_water_speed_mps))
                start_s = float(dur) if np.isfinite(dur) else float(np.hypot(*d)) / float(speed)
            # the leg begins at the clock reading it was planned from, not at its forecast's first snapshot
            lag = (
                0.0
                if planned.t_now is None
                else (planned.t_now - planned.t_start) * float(self.config.field.time_scale)
            )
            fc, mws = planned.plan.forecast, planned.max_water_speed_mps
            out = self.timing(path, fc, speed, start_s=lag + start_s, max_water_speed=mws).total_s - lag
        planned.planned_duration_vehicle_s = round(out, 3)
        return out

    def initial_state(self) -> tuple[np.ndarray, float]:
        """The truth at snapshot ``config.t0`` (land NaN) and its field time."""
        t0 = self.config.t0
        state = self.field.state_at(t0)  # gaps that come and go: FlowField.state_at
        state[:, self.field.land_mask] = np.nan
        return state, float(self.field.times[t0])

    def start_cell(self, lat: float, lon: float, *, check: bool = True) -> tuple[int, int]:
        """The grid cell of a position (deg); with ``check`` a position outside the region (+ the
        mission's geofence margin, m) or on land raises :class:`UserError`."""
        grid, margin = self.grid, float(self.config.geofence_margin_m)
        if check and not bool(grid.contains(lat, lon, margin)):
            raise UserError(
                f"the vehicle at {lat:.6f},{lon:.6f} is outside the mission region (+{margin:g} m); "
                "bring it into the region before starting a leg"
            )
        r, c = grid.latlon_to_cell(lat, lon, clip=True)
        start = (int(r), int(c))
        if check and self.field.land_mask[start]:
            raise UserError(f"the vehicle is in cell {start}, which is land in the mission's field")
        return start

    def resume_after(self, n_done: int, t_state: float) -> None:
        """The loop of a controller resumed after ``n_done`` legs, the last estimate at field time ``t_state``:
        its planner seeds follow the global leg number, the model alone runs from the mission's first state as
        it did before the stop (not from the resumed estimate), and that estimate's correction fades from
        ``t_state`` (:func:`passt_mav.loop.guard.relax_to_open_loop`). Shared by the controller and replay."""
        state0, t0 = self.initial_state()
        self.loop.leg_index = int(n_done)
        self.loop.anchor_open_loop(state0, t0, self.dt)
        self.loop.t_recon_ = float(t_state)

    @single_threaded
    def prepare(self, state) -> None:
        """Work that needs only the initial ``state`` ((2, R, C), field units), done before the
        vehicle is waited for (:meth:`PasstLoop.prepare`: the model background's roll-out, the
        information reward's prior). At 150x the first leg's planning took 3.5 s of wall clock with
        them, 520 s of field time in which the boat waited and the current moved on (the oscillating
        wake's 50-move demo); now 0.1-0.2 s."""
        self.loop.prepare(state)

    def forecast_steps(self, t_now: float, t_state: float) -> int:
        """Snapshots to bring a state at ``t_state`` forward to ``t_now`` (field time, never negative)."""
        return max(0, int(round((t_now - t_state) / self.dt)))

    @single_threaded
    def plan(
        self,
        index: int,
        state,
        t_state: float,
        start_cell,
        *,
        t_now: float | None = None,
        k: int | None = None,
        start_latlon=None,
        clock_reading=None,
        taken=None,
        avoid=None,
        speed: float | None = None,
        max_water_speed: float | None = None,
    ) -> PlannedLeg:
        """Forecast the state to now (``k`` snapshots, from ``t_now`` unless given) and plan leg ``index``.

        Does not advance the loop's leg counter (its planner seeds follow the update).
        ``taken`` / ``avoid``: a fleet's other boats (see :meth:`PasstLoop.plan_leg`).
        ``speed``: the boat's speed (m/s) that sizes the leg in time (default the mission's
        ``vehicle.speed_mps``; a fleet passes each boat's own).
        """
        if k is None:
            if t_now is None:
                raise ValueError("plan() needs t_now or k")
            k = self.forecast_steps(t_now, t_state)
        if k:
            state = self.loop.forecast(state, k)[-1]
            t_state += k * self.dt
        spd = self.speed if speed is None else float(speed)
        mws = self.config.vehicle.max_water_speed_mps if speed is None else max_water_speed
        aware = self.current_aware
        if aware:  # the planner is offered only the moves the boat can make in the forecast current
            scale = 1.0 / float(self.config.field.velocity_scale)
            self.loop.vehicle_speed = spd * scale
            self.loop.transit_kw = _hold_kw(spd, mws, scale)
        t0 = time.perf_counter()
        # the path needs the one-step prediction only (the reward map); the forecast over the whole
        # leg (the GP prior, prediction.nc) follows in forecast_leg(), while the vehicle is underway
        plan = self.loop.plan_leg(
            state, tuple(int(x) for x in start_cell), t_state, self.dt, steps=1, taken=taken, avoid=avoid
        )
        timing = None
        if aware:  # the leg spans the snapshots of its path timed in the current (refined in forecast_leg)
            from passt_mav.loop.passt import steps_for_duration

            timing = self.timing(plan.path, plan.forecast, spd, max_water_speed=mws)
            steps = steps_for_duration(timing.total_s, self.dt * float(self.config.field.time_scale))
        else:
            steps = leg_steps(self.config, self.grid, spd, self.dt, float(self.config.field.time_scale))
        plan.steps = int(steps)
        planned = PlannedLeg(
            int(index),
            tuple(int(x) for x in start_cell),
            None if start_latlon is None else (float(start_latlon[0]), float(start_latlon[1])),
            t_now,
            int(k),
            plan,
            int(steps),
            time.perf_counter() - t0,
            clock_reading,
            timing,
            speed_mps=spd,
            max_water_speed_mps=mws,
        )
        self._in_flight[int(index)] = planned
        return planned

    @single_threaded
    def forecast_leg(self, planned: PlannedLeg) -> np.ndarray:
        """The model's forecast over the whole planned leg, (steps+1, 2, R, C) from the leg's start state
        (:meth:`plan` predicts one step only); computed once, timed as ``timings["forecast"]``. The
        same numbers as one ``plan_leg`` over the leg: the first step of a roll-out is the one-step
        prediction."""
        plan = planned.plan
        if plan.forecast.shape[0] < plan.steps + 1:
            t0 = time.perf_counter()
            plan.forecast = self.loop.forecast(plan.forecast[0], plan.steps)
            if planned.timing is not None:
                # the path timed again in the forecast over the leg (the current changes under way): a
                # longer leg spans more snapshots (never fewer: the leg's span only grows, as at its end)
                from passt_mav.loop.passt import steps_for_duration

                planned.timing = self.timing(
                    plan.path,
                    plan.forecast,
                    planned.speed_mps or self.speed,
                    max_water_speed=planned.max_water_speed_mps,
                )
                need = steps_for_duration(planned.timing.total_s, self.dt * float(self.config.field.time_scale))
                if need > plan.steps:
                    plan.forecast = self.loop.forecast(plan.forecast[0], need)
                    plan.steps = planned.steps = need
            plan.timings["forecast"] = time.perf_counter() - t0
        return plan.forecast

    @single_threaded
    def absorb(self, planned: PlannedLeg, recs, clock: FieldClock, *, strict: bool = True) -> AbsorbedLeg:
        """The leg's samples into the state: field units, field time, thinning, stretch, GP update, RMSE.

        ``recs``: sample records (``time_boot_ms``, ``boot``, ``lat``, ``lon``, ``u``, ``v`` in m/s
        east/north; store rows or dicts). ``clock``: vehicle time -> field time (with every boot's
        anchor). Without usable samples: ``strict`` raises :class:`ReconstructionError`; otherwise
        the state is the forecast at the leg's end (a damaged log's replay) and ``note`` says so.
        The loop's leg counter advances either way (later legs' planner seeds stay aligned).
        """
        plan, dt, grid = planned.plan, self.dt, self.grid
        self.forecast_leg(planned)
        self._in_flight.pop(planned.index, None)
        col = _columns(recs)
        u, v = to_field_units(grid, col["u"], col["v"], self.config.field.velocity_scale)
        t_s = clock.field_time(col["time_boot_ms"], col["boot"])
        samples = thin_samples(grid, t_s, col["lat"], col["lon"], u, v, t_start=plan.t_start, dt=dt)
        if strict and len(samples) == 0:
            raise ReconstructionError(f"leg {planned.index + 1}: no usable current samples")
        planned.steps = extend_leg_to_end(self.loop, plan, t_s, dt)
        t_new = plan.t_start + planned.steps * dt
        note, t0 = None, time.perf_counter()
        try:
            if len(samples) == 0:
                raise ReconstructionError("no samples")
            state = self.loop.update(plan, samples)
        except ReconstructionError:
            if strict:
                raise
            self.loop.leg_index += 1
            samples = type(samples)(*(np.empty(0),) * 5)
            state = np.asarray(plan.forecast[-1], np.float32)
            note = "too few samples in this leg to reconstruct: the state is the forecast"
        gp_s = time.perf_counter() - t0
        r_p, r_m = self.rmse_at(state, t_new)
        std = None if note is not None or self.loop.std is None else np.asarray(self.loop.std, np.float32)
        gp = self.loop.gp_summary()
        guard = gp.pop("guard", None)
        if guard is not None and note is None:
            guard = self.guard_for_people(guard, planned.index)
        else:
            guard = None  # no samples reconstructed: nothing was scored for this leg
        return AbsorbedLeg(
            samples,
            state,
            float(t_new),
            int(planned.steps),
            len(recs),
            gp_s,
            r_p,
            r_m,
            note,
            gp,
            std,
            guard,
            *self.scores_at(state, std, t_new),
        )

    @single_threaded
    def scores_at(self, state, std, t: float) -> tuple[dict | None, dict | None]:
        """The map's calibration and the trivial maps' RMSE vs the truth at field time ``t``
        (:func:`passt_mav.loop.scoring.leg_scores`; the forecast's time mean: the model alone from the
        mission's start up to ``t``, as :meth:`rmse_at` rolls it out); (None, None) when the truth is unknown."""
        from passt_mav.loop.scoring import leg_scores

        tr = truth_at(self.field, t) if self.truth_known else None
        if tr is None:
            return None, None
        pure, fm = self._pure.get("pure"), None
        if pure is not None:
            k = int(np.clip(np.ceil((t - float(self.field.times[self.config.t0])) / self.dt), 0, len(pure) - 1))
            with warnings.catch_warnings():  # land cells are NaN at every step: their mean stays NaN, said nowhere
                warnings.simplefilter("ignore", RuntimeWarning)
                fm = np.nanmean(np.asarray(pure[: k + 1], np.float64), axis=0)
        return leg_scores(state, std, tr, fm)

    def guard_for_people(self, guard: dict, index: int) -> dict:
        """The guard's record of leg ``index`` (0-based) with its RMSE in m/s (``*_m_s``; the field's
        units times ``field.velocity_scale``) and its one-line ``message`` naming leg ``index + 1``."""
        from passt_mav.loop.guard import guard_message

        scale = float(self.config.field.velocity_scale)
        out = dict(guard)
        out["rmse_loop_m_s"] = scale * guard["rmse_loop"]
        out["rmse_open_loop_m_s"] = scale * guard["rmse_open_loop"]
        out["message"] = guard_message(guard, leg_label=f"leg {index + 1}", scale=scale)
        return out

    @single_threaded
    def rmse_at(self, state, t: float) -> tuple[float | None, float | None]:
        """RMSE (field units) of ``state`` and of the model alone (from the truth at t0, never
        re-initialised) vs the truth at field time ``t``; (None, None) when the truth is unknown."""
        if not self.truth_known:
            return None, None
        tr = truth_at(self.field, t)
        if tr is None:
            return None, None
        pm = pure_model_at(self.loop, self.field, self.config.t0, self.dt, t, self._pure)
        return rmse(state, tr), (rmse(pm, tr) if pm is not None else None)


# -- a fleet's shared step -------------------------------------------------------------------------
def in_field_time(recs, clock) -> list[dict]:
    """Sample records (store rows or dicts) with ``time_boot_ms`` replaced by their field time (read
    back with :data:`FIELD_TIME`): legs of boats with different clocks can go to one GP update."""
    if not len(recs):
        return []
    col = _columns(recs)
    t = np.atleast_1d(clock.field_time(col["time_boot_ms"], col["boot"]))
    return [
        {
            "time_boot_ms": float(t[j]),
            "boot": 0,
            "lat": float(col["lat"][j]),
            "lon": float(col["lon"][j]),
            "u": float(col["u"][j]),
            "v": float(col["v"][j]),
        }
        for j in range(len(t))
    ]


#: the clock of :func:`in_field_time`'s records: ``time_boot_ms`` already is field time
FIELD_TIME = FieldClock(0.0, 1e-3)


class FleetStep:
    """The between-leg step of a fleet: one state, the boats' paths in flight, joint planning.

    Pure (no MAVLink); :class:`passt_mav.vehicle.fleet_controller.FleetController` calls it under its
    lock and :func:`passt_mav.analysis.replay.replay` repeats a fleet run's calls in the order
    they were made (``seq``: one count per plan and per update).

    Joint planning (:meth:`plan_for`), sequential allocation: a boat plans keeping out of
    every cell of the other boats' current paths (two boats never collect the same cells in
    the same leg interval; its own start cell excepted). Boxed in by their paths, it plans
    with those cells' reward zeroed instead and keeps out of any cell another boat's path
    reaches at the same time (within one move's duration, from the paths, the boats' speeds
    (``config.fleet[k].speed_mps``, m/s; with ``planner.current_aware`` each path's arrival times in the
    forecast current) and their legs' start times) or holds after its path
    ended: the offline engine's rule (:func:`passt_mav.loop.engine.plan_keeping_out`).

    Absorbing (:meth:`absorb`): the GP prior is the leg's own forecast (from the state it was
    planned from, so every sample is compared with the forecast at its own time), and the
    GP gets this leg's samples *and* those of every leg absorbed since this one was planned
    (their information is not in its forecast), each at its own time; another leg's samples
    from before this leg's forecast begins are left out (they cannot be compared with it at
    their own time). The result replaces the shared state, at
    the leg's end or at the state's time if that is later (the state never goes back in
    time, and concurrent legs never run it ahead). With one boat this is exactly
    :meth:`LegStep.absorb`.
    """

    def __init__(self, step: LegStep):
        self.step, self.loop = step, step.loop
        self.config, self.field = step.config, step.field
        self.state, self.t_state = step.initial_state()
        self.seq = 0  # plans and updates so far
        self._version = 0  # state updates so far
        self._reserved: dict[int, dict[str, Any]] = {}  # boat -> its path in flight
        self._plan_version: dict[int, int] = {}  # leg in flight -> the state version it was planned from
        self._absorbed: list[tuple[int, int, list[dict]]] = []  # (version after, leg, its samples in field time)

    def release(self, boat: int) -> None:
        """The boat's path is no longer in flight (it dropped out)."""
        self._reserved.pop(boat, None)

    def _timeline(self, path, t_start: float, speed: float, timing=None) -> np.ndarray:
        """Field time at which a boat at ``speed`` m/s reaches each cell of ``path`` from ``t_start``: the
        planned leg's ``timing`` in the current when given (:attr:`PlannedLeg.timing`), else in still water."""
        if timing is not None and np.all(np.isfinite(timing.arrival)):
            secs = np.asarray(timing.arrival, float)
        else:
            grid = self.field.grid
            steps = np.linalg.norm(np.diff(np.asarray(path, float), axis=0), axis=1) * grid.mean_cell_size_m
            secs = np.concatenate([[0.0], np.cumsum(steps)]) / speed
        return t_start + secs / float(self.config.field.time_scale)

    def _move_time(self, speed: float) -> float:
        return self.field.grid.mean_cell_size_m / speed / float(self.config.field.time_scale)

    def _conflicts(self, boat: int, path, t_start: float, timing=None) -> np.ndarray:
        """(R, C) bool: cells of ``path`` (after its start) another boat is at when this one gets there
        (:func:`passt_mav.loop.engine.keep_out`, the offline engine's rule too: within one move of either boat,
        or on its last cell after its path ended)."""
        from passt_mav.loop.engine import keep_out

        speed = float(self.config.fleet[boat].speed_mps)
        others = [
            (
                res["path"],
                self._timeline(res["path"], res["t_start"], res["speed"], res.get("timing")),
                max(self._move_time(speed), self._move_time(res["speed"])),
            )
            for other, res in self._reserved.items()
            if other != boat
        ]
        return keep_out(path, self._timeline(path, t_start, speed, timing), others, self.field.grid.shape)

    def plan_for(self, boat: int, i: int, start, **kw):
        """Plan leg ``i`` of ``boat`` from the shared state (class docstring, "joint planning");
        ``kw`` as :meth:`LegStep.plan` (``k``, ``t_now``, ...).

        Raises :class:`PlannerError` if no path avoids the other boats in time.
        """
        taken = np.zeros(self.field.grid.shape, bool)
        for other, res in self._reserved.items():
            if other != boat:
                taken[res["path"][:, 0], res["path"][:, 1]] = True
        taken[tuple(start)] = False
        self.loop.leg_index = i  # planner seeds by global leg number
        # each boat's leg is sized by its own speed: sized by the mission's single-vehicle default
        # (2 m/s) a 5 m/s boat's legs ended in the estimate's future, the shared state's time ran
        # ahead of the boats' clocks, and the next legs compared their samples with a forecast
        # starting hours after them (the 3-boat demo's last leg: 0.023 m/s against the model
        # alone's 0.010)
        kw.setdefault("speed", float(self.config.fleet[boat].speed_mps))
        kw.setdefault("max_water_speed", self.config.fleet[boat].max_water_speed_mps)
        from passt_mav.loop.engine import plan_keeping_out

        planned = plan_keeping_out(
            lambda taken, avoid: self.step.plan(i, self.state, self.t_state, start, taken=taken, avoid=avoid, **kw),
            taken,
            lambda p: self._conflicts(boat, p.plan.path, p.t_start, p.timing),
            f"leg {i + 1}: boat {boat}",
        )
        self._reserved[boat] = {
            "path": np.asarray(planned.plan.path, int),
            "t_start": planned.t_start,
            "speed": float(self.config.fleet[boat].speed_mps),
            "timing": planned.timing,  # its arrival times in the forecast current (None: still water)
        }
        self._plan_version[i] = self._version  # the state this leg was planned from
        self.seq += 1
        return planned

    def absorb(self, boat: int, planned, recs, clock):
        """A boat's leg samples into the shared state (class docstring, "absorbing"); returns the
        AbsorbedLeg (``n_samples``: this leg's; ``n_gp_points``: every thinned sample the GP got).
        Raises :class:`ReconstructionError` when the leg brought no samples (as for one boat)."""
        dt = self.step.dt
        own = in_field_time(recs, clock)
        if not own:
            self._plan_version.pop(planned.index, None)
            raise ReconstructionError(f"leg {planned.index + 1}: no usable current samples")
        since = self._plan_version.pop(planned.index, self._version)
        # another leg's samples taken before this leg's forecast begins cannot be compared with
        # that forecast at their own time (it starts at this leg's planning state): clipped to
        # its first snapshot they read the flow's change since then as a model error and drag
        # the estimate off (seen before this rule: the 3-boat demo's last leg 0.034 m/s against
        # the model alone's 0.010). They are left out of this reconstruction: a loss of what
        # they knew, which a smoother over the legs' overlap would keep (not built)
        t_first = planned.t_start
        extra = [
            r
            for v, leg, rr in self._absorbed
            if v > since and leg != planned.index
            for r in rr
            if r["time_boot_ms"] >= t_first
        ]
        self.step.forecast_leg(planned)
        # the state never goes back in time: reconstruct at its time at least
        need = int(round((self.t_state - planned.t_start) / dt))
        if need > planned.plan.steps:
            planned.plan.forecast = self.loop.forecast(planned.plan.forecast[0], need)
            planned.plan.steps = planned.steps = need
        self.loop.leg_index = planned.index
        absorbed = self.step.absorb(planned, own + extra, FIELD_TIME)
        absorbed.n_samples = len(recs)
        self.state, self.t_state = absorbed.state, absorbed.t_state
        self._version += 1
        self._absorbed.append((self._version, planned.index, own))
        # what no leg in flight was planned without is in the state for good
        oldest = min(self._plan_version.values(), default=self._version)
        self._absorbed = [x for x in self._absorbed if x[0] > oldest]
        self._reserved.pop(boat, None)
        self.seq += 1
        return absorbed
