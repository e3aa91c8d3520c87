"""Mission configuration: one YAML file per mission, validated with pydantic.

Example (``missions/north_atlantic.yaml``)::

    name: north_atlantic
    region: {south: 39.360065, west: -64.24, north: 41.130714, east: -61.92004, rows: 30, cols: 30}
    field: {source: "builtin:ocean", clock: auto}   # clock: auto | utc | boot (see FieldConfig)
    model: builtin:ocean            # default: the shipped model of the field's scenario
    planner: {name: policy_gradient, path_length: 50, reward: speed, options: {}}
    legs: 4
    start_cell: [15, 15]
    t0: 0
    vehicle: {connect: "tcp:127.0.0.1:5760", speed_mps: 2.0, wp_radius_m: 5.0, on_reboot: resume}
    # or a fleet sharing one field estimate (passt_mav.vehicle.fleet_controller), one entry per boat:
    # vehicles: [{connect: "tcp:127.0.0.1:5760"}, {connect: "tcp:127.0.0.1:5770", start_cell: [5, 5]}]
    sensors: {u: CUR_U, v: CUR_V, noise_std: 0.02}
    geofence_margin_m: 500
    gp: {prior: forecast, hyper: every_leg, background: 200, prior_blend: select, forgetting: 0.8, prior_share: 0.05, options: {}}
    model_update: {online: off, budget_s: 5, lr: 1.0e-4, horizon: 1, max_steps: null, window: 10}  # learning at sea
    seeds: {planner: 0, gp: 0, sensor: 0, field: 0}
    budget: {max_time_s: 14400, max_distance_m: 30000, battery_reserve_pct: 30, on_spent: rtl}   # unset: no limit
    approve: {enabled: false, timeout_s: 300, on_timeout: hold}   # run --approve: the operator approves each leg

``region`` is geographic (south/west/north/east/rows/cols: the lat/lon of the
corner cell *centres*, :class:`geo.RegionGrid`) or metric (x0/x1/y0/y1/rows/cols
+ anchor_lat/anchor_lon/rotation_deg/scale, :class:`geo.MetricRegionGrid`); an
optional ``kind: geographic|metric`` may say which, otherwise the keys do.

``model`` is ``builtin:NAME`` (a shipped checkpoint; the deprecated spelling
``shipped:NAME`` is accepted and normalised to ``builtin:NAME``, the one spelling every
command uses), a checkpoint path (``.pt``) or a predictor registry name (``knode``,
``dmd``, ``persistence``; fitted on the field). It is resolved by the commands,
not here.

Every problem raises :class:`passt_mav.errors.MissionConfigError` with ONE line
``FILE: key.path: problem (got VALUE)``. Every number must be finite (no ``.inf``/``.nan``) and within
physical bounds (``vehicle.speed_mps <= 20``, grids of at most :data:`MAX_GRID` rows and columns, ...); a key
given twice in one mapping, and aliases that expand the file past :data:`MAX_YAML_VALUES` values (an alias
bomb), are refused as the YAML is read. Relative paths in the file (field
source, model checkpoint) are relative to the YAML file's directory, not the working directory; the
validated config holds them absolute, and so does the copy a run directory keeps
(:func:`recorded_mission_text`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from passt_mav.errors import MissionConfigError
from passt_mav.loop.presets import DEFAULT, Preset
from passt_mav.reconstruction.background import background_steps_problem

__all__ = [
    "mission_overrides",
    "recorded_mission_text",
    "MissionConfig",
    "GeographicRegion",
    "MetricRegion",
    "FieldConfig",
    "PlannerConfig",
    "VehicleConfig",
    "SensorConfig",
    "GPConfig",
    "ModelUpdateConfig",
    "SeedConfig",
    "load_mission",
    "BUILTIN_FIELDS",
    "SHIPPED_MODELS",
    "DEFAULT_MODEL",
]

BUILTIN_FIELDS = ("ocean", "cylinder", "oscillating", "rtofs")
#: shipped predictor checkpoints (resolved by passt_mav.models)
SHIPPED_MODELS = ("cylinder", "cylinder-dmd", "ocean")
#: the default model of each built-in field: the oscillating cylinder uses the static one (paper)
DEFAULT_MODEL = {
    "ocean": "builtin:ocean",
    "cylinder": "builtin:cylinder",
    "oscillating": "builtin:cylinder",
    "rtofs": "persistence",
}  # no KNODE is trained on the real RTOFS currents
#: predictor registry names accepted when passt_mav.models cannot be imported (yet)
_KNOWN_PREDICTORS = ("knode", "dmd", "persistence")
_NAMED_VALUE_MAX = 10  # NAMED_VALUE_FLOAT.name is char[10]
#: bounds of a mission's numbers (physical, or what a run can do in reasonable time and memory)
MAX_GRID = 1000  # rows, cols
MAX_SPEED_MPS = 20.0  # a survey boat's speed through the water (about 39 knots)
MAX_PATH_LENGTH = 1000  # moves per leg
MAX_LEGS = 10_000
MAX_STEPS = 10_000  # snapshot indices and counts
MAX_BOATS = 64  # a fleet's boats
DAY_S = 86_400.0
#: values (scalars, lists and mappings, aliases expanded) a mission file may hold: a file of aliases that
#: expand past it (a "billion laughs" alias bomb) is refused before it is built
MAX_YAML_VALUES = 100_000


class _Strict(BaseModel):
    # a field's docstring is its description (the mission-key reference, docs/missions.md, is generated from it)
    # (allow_inf_nan=False: every float is finite; .inf and .nan are refused by name)
    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True, allow_inf_nan=False)


def _base_dir(info: ValidationInfo) -> Path:
    ctx = info.context or {}
    return Path(ctx.get("base_dir", "."))


def _resolved_path(v: str, info: ValidationInfo) -> Path:
    """The path ``v`` of a mission key made absolute: a relative one is taken from the mission file's folder
    (the validation's ``base_dir``), not the working directory, so the config (and every record of it: the run
    directory's ``mission.yaml``, ``summary.json``'s ``config``) names a file that resolves from anywhere."""
    p = Path(v)
    return Path(os.path.abspath(p if p.is_absolute() else _base_dir(info) / p))


class GeographicRegion(_Strict):
    """Lat/lon of the corner cell centres (degrees) and the grid shape."""

    kind: Literal["geographic"] = "geographic"
    """Which kind of region; optional, the other keys say it."""
    south: float = Field(ge=-90, le=90)
    """Latitude of the southern row's cell centres (degrees north)."""
    west: float = Field(ge=-360, le=360)
    """Longitude of the western column's cell centres (degrees east)."""
    north: float = Field(ge=-90, le=90)
    """Latitude of the northern row's cell centres (degrees north)."""
    east: float = Field(ge=-360, le=360)
    """Longitude of the eastern column's cell centres (degrees east)."""
    rows: int = Field(ge=2, le=MAX_GRID)
    """Grid rows, south to north (row 0 is the southern edge)."""
    cols: int = Field(ge=2, le=MAX_GRID)
    """Grid columns, west to east (column 0 is the western edge)."""

    @model_validator(mode="after")
    def _check(self):
        self.grid()  # GeoError (a ValueError) -> reported at "region"
        return self

    def grid(self):
        """The :class:`geo.RegionGrid`."""
        from geo import RegionGrid

        return RegionGrid(self.south, self.west, self.north, self.east, self.rows, self.cols)


class MetricRegion(_Strict):
    """A metric data grid (cylinder crop) placed on Earth, see :class:`geo.MetricRegionGrid`."""

    kind: Literal["metric"] = "metric"
    """Which kind of region; optional, the other keys say it."""
    x0: float = Field(ge=-1e7, le=1e7)
    """Data-frame x of the first column's cell centres (data metres)."""
    x1: float = Field(ge=-1e7, le=1e7)
    """Data-frame x of the last column's cell centres (data metres)."""
    y0: float = Field(ge=-1e7, le=1e7)
    """Data-frame y of the first row's cell centres (data metres)."""
    y1: float = Field(ge=-1e7, le=1e7)
    """Data-frame y of the last row's cell centres (data metres)."""
    rows: int = Field(ge=2, le=MAX_GRID)
    """Grid rows along y (row 0 at y0)."""
    cols: int = Field(ge=2, le=MAX_GRID)
    """Grid columns along x (column 0 at x0)."""
    anchor_lat: float = Field(ge=-90, le=90)
    """Latitude where the data frame's centre lies (degrees north)."""
    anchor_lon: float = Field(ge=-360, le=360)
    """Longitude where the data frame's centre lies (degrees east)."""
    rotation_deg: float = Field(default=0.0, ge=-360, le=360)
    """Counter-clockwise rotation of the data frame on the map (degrees)."""
    scale: float = Field(default=1.0, gt=0, le=1e6)
    """Earth metres per data metre."""

    @model_validator(mode="after")
    def _check(self):
        self.grid()
        return self

    def grid(self):
        """The :class:`geo.MetricRegionGrid`."""
        from geo import MetricRegionGrid

        return MetricRegionGrid(
            self.x0,
            self.x1,
            self.y0,
            self.y1,
            self.rows,
            self.cols,
            anchor_lat=self.anchor_lat,
            anchor_lon=self.anchor_lon,
            rotation_deg=self.rotation_deg,
            scale=self.scale,
        )


def _region_kind(v: Any) -> str | None:
    if isinstance(v, dict):
        if "kind" in v:
            return v["kind"] if v["kind"] in ("geographic", "metric") else None
        return "metric" if ({"x0", "x1", "y0", "y1", "anchor_lat", "anchor_lon"} & set(v)) else "geographic"
    if isinstance(v, (GeographicRegion, MetricRegion)):
        return v.kind
    return None


Region = Annotated[
    Annotated[GeographicRegion, Tag("geographic")] | Annotated[MetricRegion, Tag("metric")],
    Discriminator(
        _region_kind,
        custom_error_type="region_kind",
        custom_error_message="must be a mapping with south/west/north/east/rows/cols (geographic) "
        "or x0/x1/y0/y1/rows/cols/anchor_lat/anchor_lon (metric)",
    ),
]


class FieldConfig(_Strict):
    """Where the current field comes from.

    source: ``builtin:ocean`` | ``builtin:cylinder`` | ``builtin:oscillating`` | a ``.nc``
    path. velocity_scale: m/s per field velocity unit (the cylinder is non-dimensional,
    inflow = 1; geographic fields are already in m/s: 1). time_scale: seconds per field
    time unit (geographic fields count seconds: 1; for a scaled cylinder
    ``region.scale / velocity_scale``).

    clock: how vehicle time maps to field time.
      ``utc``: through the vehicle's UTC (SYSTEM_TIME ``time_unix_usec - time_boot_ms``):
      field time = seconds since the field's ``time_origin`` (a real forecast, e.g. RTOFS of a
      date, sampled at the right hour); the run stops with a one-line error if the vehicle has
      no UTC or its time lies outside the field's snapshots.
      ``boot``: field time at vehicle boot = snapshot ``t0`` (or ``--field-time-at-boot``), then
      ``time_boot_ms`` (simulators without a clock).
      ``auto`` (default): ``utc`` when the field has a time origin, the vehicle sends UTC and
      that UTC lies within the field's snapshots; otherwise ``boot``, saying why.
    """

    source: str
    """`builtin:ocean`, `builtin:cylinder`, `builtin:oscillating`, `builtin:rtofs` or a `.nc` file made by `passt-mav data import` (relative to the mission file); a plain string is the same as `{source: ...}`."""
    velocity_scale: float = Field(default=1.0, gt=0, le=100)
    """m/s per field velocity unit: 1 for geographic fields (already m/s); the cylinder is non-dimensional (inflow = 1)."""
    time_scale: float = Field(default=1.0, gt=0, le=1e6)
    """Seconds per field time unit: 1 for geographic fields (seconds); for a scaled cylinder `region.scale / velocity_scale`."""
    clock: Literal["auto", "utc", "boot"] = "auto"
    """How vehicle time maps to field time: `utc` (the vehicle's UTC against the field's time origin), `boot` (field time at boot = snapshot `t0`), `auto` (`utc` when possible, else `boot`, saying why)."""

    @field_validator("source")
    @classmethod
    def _source(cls, v: str, info: ValidationInfo) -> str:
        if v.startswith("builtin:"):
            name = v.split(":", 1)[1]
            if name not in BUILTIN_FIELDS:
                raise ValueError(
                    f"unknown built-in field {name!r}; choose one of "
                    + ", ".join(f"builtin:{n}" for n in BUILTIN_FIELDS)
                    + " or a .nc file"
                )
            return v
        if not v.endswith(".nc"):
            raise ValueError(
                "must be builtin:ocean, builtin:cylinder, builtin:oscillating, builtin:rtofs or a path to a .nc file"
            )
        p = _resolved_path(v, info)
        if not p.exists():
            raise ValueError(f"field file not found: {p}")
        return str(p)

    @property
    def builtin(self) -> str | None:
        """The built-in scenario name, or None for a file."""
        return self.source.split(":", 1)[1] if self.source.startswith("builtin:") else None


class PlannerConfig(_Strict):
    """Planner name (``passt_mav.planning.PLANNERS``), moves per leg L, reward, planner options;
    ``memory``: ``fitted`` = the information reward's prior remembers per cell the local error past
    legs' samples removed (:class:`passt_mav.loop.memory.CellMemory`), ``off`` = the stationary prior
    every leg."""

    name: str = DEFAULT.planner
    """Planner (`passt_mav.planning.PLANNERS`: `policy_gradient`, `lawnmower`, `greedy`, `random`, `information`; `pg` = `policy_gradient`)."""
    path_length: int = Field(default=50, ge=1, le=MAX_PATH_LENGTH)
    """Moves per leg L (grid cells; a move is one cell, diagonals included)."""
    reward: str = DEFAULT.reward
    """Reward map the planner maximises (`passt_mav.planning.REWARDS`: `speed`, `vorticity`, `std`, `speed_std`, `change`, `variance_reduction`; `speed` is the predicted current speed, `variance_reduction` the error variance a sample removes from the next reconstruction)."""
    options: dict[str, Any] = Field(default_factory=dict)
    """Planner-specific keyword options, passed on unchanged."""
    memory: Literal["off", "fitted"] = DEFAULT.memory
    """`fitted`: the information reward's prior remembers per cell the error past legs' samples removed; `off`: the same stationary prior every leg."""
    current_aware: bool = False
    """`true` (missions where the current is a sizeable part of the boat's speed, e.g. `missions/north_atlantic.yaml`): a leg is planned and timed in the forecast current: the planner is offered only the moves the boat can make with its crab angle held against it (ArduPilot's ground speed held up to `vehicle.max_water_speed_mps` through the water; at least 0.25 x `vehicle.speed_mps` over ground, `passt_mav.planning.transit.FEASIBLE_MARGIN`), the leg spans the snapshots of its path's time in that current, and the overrun rule expects that time (leg.json `planned_duration_vehicle_s`); `false`: every move at `vehicle.speed_mps` over ground, as in still water."""

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        from passt_mav.planning import PLANNERS

        if v == "pg":
            return "policy_gradient"
        if v not in PLANNERS:
            raise ValueError(f"unknown planner {v!r}; choose one of {', '.join(PLANNERS)}")
        return v

    @field_validator("reward")
    @classmethod
    def _reward(cls, v: str) -> str:
        from passt_mav.planning import REWARDS

        if v not in REWARDS:
            raise ValueError(f"unknown reward {v!r}; choose one of {', '.join(REWARDS)}")
        return v

    @model_validator(mode="after")
    def _options(self):
        if self.options:
            from passt_mav.planning import PLANNERS

            _check_options(self.options, PLANNERS[self.name], f"of planner {self.name!r}")
        return self


class VehicleConfig(_Strict):
    """MAVLink connection string, cruise speed (m/s, sent as DO_CHANGE_SPEED) and waypoint radius (m).

    source_system / source_component: the ids the controller speaks as on this link (default
    245/195: never QGroundControl's 255/190; on the boat's companion computer give the vehicle's
    system id and keep component 195).

    on_reboot: what the controller does when the autopilot reboots mid-leg (brown-out,
    watchdog; recognised by ``time_boot_ms`` going back, not taken for a pilot's mode change):
    ``resume`` (default) waits for the EKF, verifies the stored mission (re-uploads it if
    lost), re-arms and continues AUTO at the interrupted item; ``hold`` waits for the vehicle,
    switches it to HOLD and stops the run (status ``paused``) for a person to look first.

    link_loss_window_s: how long (vehicle seconds; wall seconds ``/ --speedup-hint`` while nothing is
    heard) the controller keeps trying to reach a vehicle whose link died mid-mission, back-off capped,
    one line per attempt; the vehicle flies its uploaded leg meanwhile. Past it the run stops cleanly
    (status ``paused``, continue with ``--resume``). on_signal: what SIGTERM/SIGINT/SIGHUP do to the
    vehicle: ``hold`` (default) switches it to HOLD, ``auto`` leaves it flying its leg. overrun_factor /
    on_overrun: a leg still flying after ``overrun_factor`` x its planned vehicle time (+30 s for the
    start) is reported; ``cut`` (default) ends it there (HOLD, its samples absorbed, the next leg
    planned from where the boat is), ``warn`` only reports it.

    wait_mode: whenever the controller makes the boat wait (between legs, paused, awaiting approval, at a
    budget stop ``hold``, after a stop signal) it switches to LOITER (``loiter``, default: the boat keeps station
    inside LOIT_RADIUS) or HOLD (``hold``: Rover's HOLD stops the motor and centres the steering, so a boat in
    HOLD drifts with the current: 60 m in two minutes in a 0.5 m/s tide). A vehicle that refuses LOITER (no
    position yet) is put in HOLD, said in the log. on_end: when the run completes the boat ``loiter`` s (armed,
    keeping station) or is disarmed (``disarm``; the motor cannot start, so it drifts); the run says which.
    """

    connect: str = "tcp:127.0.0.1:5760"
    """MAVLink connection: `tcp:HOST:PORT`, `udpin:HOST:PORT`, `udpout:HOST:PORT` or `DEVICE,BAUD` (a radio); `--connect` overrides it."""
    speed_mps: float = Field(default=2.0, gt=0, le=MAX_SPEED_MPS)
    """Cruise speed (m/s), sent as DO_CHANGE_SPEED; legs are sized in time from it (set it to the boat's `WP_SPEED`)."""
    wp_radius_m: float = Field(default=2.0, ge=0, le=1000)
    """Waypoint acceptance radius (m)."""
    max_water_speed_mps: float | None = Field(default=None, gt=0, le=MAX_SPEED_MPS)
    """The hull's top speed through the water (m/s; null = `speed_mps`). ArduPilot Rover holds `speed_mps` over ground along the bow, asking the hull for more water speed against a current and less with it, up to this; beyond it the boat makes what full throttle gives. With `planner.current_aware` legs are planned and timed so (`passt_mav.planning.transit`, `hold="ground"`)."""
    on_reboot: Literal["resume", "hold"] = "resume"
    """After an autopilot reboot mid-leg: `resume` (wait for the EKF, verify or re-upload the mission, re-arm, continue AUTO) or `hold` (stop the boat in its `wait_mode` and stop the run, status `paused`)."""
    link_loss_window_s: float = Field(default=600.0, gt=0, le=DAY_S)
    """How long (vehicle s; wall s = this / `--speedup-hint` while nothing is heard) the controller keeps reconnecting to a vehicle whose link died mid-mission; past it the run stops cleanly (status `paused`, continue with `--resume`)."""
    on_signal: Literal["hold", "auto"] = "hold"
    """What SIGTERM/SIGINT/SIGHUP do to the vehicle: `hold` stops it where it is (in its `wait_mode`: LOITER by default), `auto` leaves it flying its leg."""
    overrun_factor: float = Field(default=2.0, gt=1.0, le=100)
    """A leg still flying after this many times its planned vehicle time (+30 s for the start) is an overrun."""
    on_overrun: Literal["cut", "warn"] = "cut"
    """What an overrun does: `cut` ends the leg (the boat waits in its `wait_mode`, its samples absorbed, the next leg planned from where the boat is); `warn` only reports it."""
    wait_mode: Literal["loiter", "hold"] = "loiter"
    """How the boat waits whenever the controller makes it wait (between legs, paused, awaiting approval, at a budget stop or a stop signal): `loiter` keeps station (LOITER, inside `LOIT_RADIUS`); `hold` stops the motor, and a boat in HOLD drifts with the current."""
    on_end: Literal["loiter", "disarm"] = "loiter"
    """What the boat does when the run completes: `loiter` keeps station, armed, for the pilot to take over; `disarm` disarms it (the motor cannot start, and the boat drifts with the current)."""
    start_cell: tuple[int, int] | None = None
    """[row, col] where a simulator starts this boat (a fleet's demo; row 0 south, col 0 west); else unused."""
    #: our MAVLink identity on this boat's link (None = passt_mav.mavlink.link.DEFAULT_SOURCE_SYSTEM /
    #: DEFAULT_SOURCE_COMPONENT, 245/195; docs/real-boat.md, "Identity on a shared link")
    source_system: int | None = Field(default=None, ge=1, le=255)
    """Our MAVLink system id on this link (unset: 245; never QGroundControl's 255)."""
    source_component: int | None = Field(default=None, ge=1, le=255)
    """Our MAVLink component id on this link (unset: 195, MAV_COMP_ID_PATHPLANNER)."""

    @model_validator(mode="after")
    def _hull(self) -> VehicleConfig:
        if self.max_water_speed_mps is not None and self.max_water_speed_mps < self.speed_mps:
            raise ValueError(
                f"max_water_speed_mps {self.max_water_speed_mps:g} is below speed_mps {self.speed_mps:g}: "
                "the hull's top speed through the water is at least the cruise speed"
            )
        return self


class BudgetConfig(_Strict):
    """The mission's safety budget (docs/console.md): each limit unset is no limit. Checked while a leg flies
    (:mod:`passt_mav.vehicle.budget`): past ``max_time_s`` (vehicle seconds in AUTO since this controller session's
    first leg started) or ``max_distance_m`` (metres the boat moved meanwhile, from its GPS fixes) the leg is cut
    there (its samples absorbed); at ``battery_reserve_pct`` (SYS_STATUS / BATTERY_STATUS remaining %) as well.
    Before its upload a leg that would overrun the distance or time left is shortened to its first waypoints that
    fit (with ``on_spent: rtl`` the way home from the last one too); when none fits the run ends. Then the boat goes to ``on_spent`` (RTL or HOLD) and the run ends cleanly (status ``ended``); ``--resume``
    continues it with the budget counted afresh."""

    max_time_s: float | None = Field(default=None, gt=0, le=365 * DAY_S)
    """Vehicle seconds of legs flown per controller session; unset: no limit."""
    max_distance_m: float | None = Field(default=None, gt=0, le=1e8)
    """Metres moved during legs per controller session (from GLOBAL_POSITION_INT); unset: no limit."""
    battery_reserve_pct: float | None = Field(default=None, gt=0, lt=100)
    """Battery remaining (%, SYS_STATUS / BATTERY_STATUS) at which the boat returns; unset: not watched."""
    on_spent: Literal["rtl", "hold"] = "rtl"
    """Where the boat goes once a limit is reached: `rtl` (return to launch) or `hold` (it stops where it is, in its `vehicle.wait_mode`)."""


class ApproveConfig(_Strict):
    """Approve each leg before it is uploaded (``run --approve`` sets ``enabled``; docs/console.md): the live page
    shows the planned leg (path, waypoints, reward map, distance, expected duration) and the operator approves
    it, or rejects it (it is planned again from the boat's position and the time then); the console takes
    ``a`` / ``r`` + Enter when no browser is open. Past ``timeout_s`` (wall seconds) ``on_timeout`` decides:
    ``hold`` stops the run in HOLD (status ``paused``, ``--resume`` plans the leg again), ``approve`` flies it."""

    enabled: bool = False
    """Wait for the operator's approval before each leg's upload."""
    timeout_s: float = Field(default=300.0, gt=0, le=DAY_S)
    """Wall seconds to wait for the operator's answer."""
    on_timeout: Literal["hold", "approve"] = "hold"
    """What an unanswered leg does: `hold` (stop the run, the boat waiting in its `wait_mode`, status paused) or `approve` (fly it)."""


class SensorConfig(_Strict):
    """NAMED_VALUE_FLOAT names of the current sensor's east/north components, and its noise std (m/s)."""

    u: str = Field(default="CUR_U", min_length=1, max_length=_NAMED_VALUE_MAX)
    """NAMED_VALUE_FLOAT name of the current's east component (m/s; at most 10 characters)."""
    v: str = Field(default="CUR_V", min_length=1, max_length=_NAMED_VALUE_MAX)
    """NAMED_VALUE_FLOAT name of the current's north component (m/s; at most 10 characters)."""
    noise_std: float = Field(default=0.0, ge=0, le=10)
    """The sensor's noise standard deviation (m/s); the GP never assumes less."""


#: the mission defaults of ``gp.bias``, ``gp.prior_blend`` and ``gp.prior_share``
#: (:data:`passt_mav.loop.presets.DEFAULT`, where every default of the loop is set; why these:
#: docs/research/2026-11-27-prior-blend-and-bias.md)
BIAS_DEFAULT = DEFAULT.bias
PRIOR_BLEND_DEFAULT = DEFAULT.prior_blend
PRIOR_SHARE_DEFAULT = DEFAULT.prior_share


class GPConfig(_Strict):
    """GP reconstruction (defaults: :data:`passt_mav.loop.presets.DEFAULT`): prior ``forecast`` (residual vs
    the model forecast) or ``none`` (the paper's GP on samples alone, a constant mean; ``constant``, the
    spelling before, is read as ``none``); hyper-parameter schedule; ``background``: snapshots of
    the model's roll-out whose anomaly covariance the residual GP adds to its stationary
    kernels (0 = none; see :func:`passt_mav.reconstruction.model_background`); ``prior_blend``:
    ``off`` (the forecast restarted from the last estimate is the prior), ``bma`` (that forecast, the
    model alone from the mission's first state and persistence, weighed leg by leg by how well each
    explains the leg's samples, memory ``forgetting``) or ``select`` (the most probable alone; see
    :class:`passt_mav.loop.passt.PasstLoop`); ``guard``: ``on`` (default) scores the loop's forecast
    against the model alone at each leg's samples before they enter the estimate, says so when the
    loop's fits worse and falls back to the model alone (:mod:`passt_mav.loop.guard`); ``prior_share``: the blend's
    fixed share (every candidate keeps ``prior_share / 3`` of the weight, so one bad leg of a good
    model is won back; 0 = off, ``PasstLoop(share=...)``); ``bias``: the
    residual GP may shift the forecast by a constant and rescale its anomaly where a leg's samples show it (fitted only from samples that
    see half of the region, kept only when their likelihood pays for it;
    :class:`passt_mav.reconstruction.gp.GPReconstructor` ``bias``); ``nugget``: what the white variance the
    GP fits above the sensor's is (``GPReconstructor`` ``nugget``); ``options``: further GPReconstructor options."""

    prior: Literal["forecast", "none"] = DEFAULT.prior
    """`forecast`: the GP corrects the model's forecast (residuals); `none`: the paper's GP on the samples alone, a constant mean (`constant` is read as `none`)."""
    hyper: Literal["first_leg", "state", "every_leg"] = "every_leg"
    """When the GP's kernel hyper-parameters are fitted: on every leg's samples (`every_leg`), on the first leg's only (`first_leg`), or once on the initial state (`state`)."""
    background: int = Field(default=DEFAULT.background, ge=0, le=MAX_STEPS)
    """Snapshots of the model's roll-out whose anomaly covariance the GP adds to its kernels (0 = stationary kernels only)."""
    prior_blend: Literal["off", "bma", "select"] = PRIOR_BLEND_DEFAULT
    """`off`: the forecast restarted from the last estimate is the prior; `bma`: that forecast, the model alone from the mission's first state and persistence weighed leg by leg by their samples' likelihood; `select`: the most probable of them alone."""
    forgetting: float = Field(default=DEFAULT.forgetting, ge=0.0, le=1.0)
    """The blend's forgetting factor: past legs' evidence is multiplied by it once per leg (0 = only the last leg counts, 1 = all legs alike)."""
    prior_share: float = Field(default=PRIOR_SHARE_DEFAULT, ge=0.0, le=1.0)
    """The blend's fixed share: every candidate keeps `prior_share / 3` of the weight, so one bad leg of a good model is won back (0 = off)."""
    bias: bool = BIAS_DEFAULT
    """The GP may shift the forecast by a constant and rescale its anomaly where a leg's samples see half of the region and pay for it."""
    nugget: Literal["state", "noise"] = DEFAULT.nugget
    """What the white variance the GP fits above the sensor's noise is: `state`, the field's grid-scale error (a sample corrects its own cell by it), or `noise`, measurement noise."""
    guard: Literal["on", "off"] = DEFAULT.guard
    """`on`: before a leg's samples enter the estimate, the forecast restarted from the last estimate and the model alone are compared at them; the leg falls back to the model alone when it fits better, and 'sampling is not helping' is raised after two such legs running or one by more than 10 %."""

    @field_validator("prior", mode="before")
    @classmethod
    def _prior(cls, v: Any) -> Any:
        return "none" if v == "constant" else v

    @field_validator("background")
    @classmethod
    def _background(cls, v: int) -> int:
        problem = background_steps_problem(v)
        if problem:
            raise ValueError(problem)
        return v

    options: dict[str, Any] = Field(default_factory=dict)
    """Keyword options of `GPReconstructor` (e.g. `nugget: noise`), passed on unchanged."""

    @model_validator(mode="after")
    def _options(self):
        if self.options:
            from passt_mav.reconstruction.gp import GPReconstructor

            _check_options(self.options, GPReconstructor, "of GPReconstructor", internal=("grid_xy",))
        return self

    @property
    def loop_prior(self) -> str:
        """The GP prior as :class:`passt_mav.loop.passt.PasstLoop` takes it: ``prior`` (the same names)."""
        return self.prior


class ModelUpdateConfig(_Strict):
    """Learning at sea (:mod:`passt_mav.loop.online`): between legs, a copy of the model is fine-tuned on
    the mission's reconstructed states so far and kept only when it explains the next leg's samples
    better than the current model (innovation log likelihood); off by default. Only a KNODE has weights
    to update (DMD and persistence are left as they are)."""

    online: Literal["off", "on"] = "off"
    """`on`: update the model between legs, keeping an update only when the next leg's samples find it more probable; `off` (default): the model stays as loaded."""
    budget_s: float = Field(default=5.0, gt=0, le=DAY_S)
    """Seconds of gradient steps per leg (wall clock; overrun by at most one step)."""
    lr: float = Field(default=1e-4, gt=0, le=1)
    """Adam's learning rate of the update."""
    horizon: int = Field(default=1, ge=1, le=MAX_LEGS)
    """Later states each state's roll-out is compared with (1 = the next leg's)."""
    max_steps: int | None = Field(default=None, ge=1, le=10**9)
    """A cap on the gradient steps per leg (unset: the budget alone); set it, with a budget large enough for it, for a run that replays bit for bit whatever the machine's speed."""
    window: int = Field(default=10, ge=2, le=MAX_LEGS)
    """The most recent reconstructed states (one per leg) the update trains on."""

    @field_validator("online", mode="before")
    @classmethod
    def _yaml_bool(cls, v: Any) -> Any:
        # YAML 1.1 reads a bare on / off as a boolean
        return {True: "on", False: "off"}.get(v, v) if isinstance(v, bool) else v


class SeedConfig(_Strict):
    """Seeds of everything random (recorded with the run)."""

    planner: int = Field(default=0, ge=0, le=2**32 - 1)
    """Seed of the planner's randomness."""
    gp: int = Field(default=0, ge=0, le=2**32 - 1)
    """Seed of the GP's hyper-parameter fit restarts."""
    sensor: int = Field(default=0, ge=0, le=2**32 - 1)
    """Seed of simulated sensor noise (`demo`'s simulator, the counterfactuals)."""
    field: int = Field(default=0, ge=0, le=2**32 - 1)
    """Seed of a generated field (`builtin:ocean`'s realisation)."""


class MissionConfig(_Strict):
    """A validated mission file (see the module docstring for the keys)."""

    name: str = Field(min_length=1)
    """The mission's name (run directories are named after it)."""
    region: Region
    """The mission's grid: geographic (`south/west/north/east/rows/cols`) or metric (`x0/x1/y0/y1/rows/cols/anchor_lat/anchor_lon`); must equal the field's grid."""
    field: FieldConfig
    """Where the current field comes from (the truth a simulator replays and the RMSE is computed on, and the model's initial state)."""
    model: str | None = None
    """`builtin:cylinder`, `builtin:ocean` (shipped KNODEs), a `.pt` checkpoint, or `knode`, `dmd`, `persistence`; unset: the built-in field's model, else `dmd`."""
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    """How each leg's path is chosen."""
    legs: int = Field(default=1, ge=1, le=MAX_LEGS)
    """Number of legs (plan, fly, reconstruct); `--legs` overrides it."""
    start_cell: tuple[int, int] | None = None
    """[row, col] where `plan`, `demo` and the offline counterfactuals start the first leg (row 0 is the southern edge and grows north, col 0 the western edge and grows east); unset: the grid's centre. A live `run` starts every leg at the boat's own cell."""
    t0: int = Field(default=0, ge=0, le=MAX_STEPS)
    """Snapshot index of the field at the mission's start (the model's initial state)."""
    steps_per_leg: int | None = Field(default=None, ge=1, le=MAX_STEPS)
    """Field snapshots per leg given to the loop (unset: 1)."""
    vehicle: VehicleConfig = Field(default_factory=VehicleConfig)
    """The boat (one boat)."""
    vehicles: list[VehicleConfig] | None = Field(default=None, max_length=MAX_BOATS)
    """A fleet sharing one field estimate: one entry per boat, each with the keys of `vehicle`; give either `vehicle` or `vehicles`."""
    sensors: SensorConfig = Field(default_factory=SensorConfig)
    """The current sensor's messages and noise."""
    geofence_margin_m: float = Field(default=0.0, ge=0, le=1e6)
    """Geofence margin around the region's outer cell edges (m): a leg with a waypoint outside region + margin is not uploaded, and a boat outside it is not planned for."""
    gp: GPConfig = Field(default_factory=GPConfig)
    """The GP reconstruction."""
    model_update: ModelUpdateConfig = Field(default_factory=ModelUpdateConfig)
    """Learning at sea: the model's update between legs, kept only when it explains the next leg's samples better (off by default)."""
    seeds: SeedConfig = Field(default_factory=SeedConfig)
    """Seeds of everything random (recorded with the run)."""
    budget: BudgetConfig = Field(default_factory=BudgetConfig)
    """The safety budget: time, distance and battery reserve (unset: no limit)."""
    approve: ApproveConfig = Field(default_factory=ApproveConfig)
    """The operator approves each leg before its upload (off unless enabled, or `run --approve`)."""

    @field_validator("field", mode="before")
    @classmethod
    def _field_shorthand(cls, v: Any) -> Any:
        return {"source": v} if isinstance(v, str) else v

    @field_validator("model")
    @classmethod
    def _model(cls, v: str | None, info: ValidationInfo) -> str | None:
        if v is None:
            return None
        if v.startswith(("builtin:", "shipped:")):
            name = v.split(":", 1)[1]
            if name not in SHIPPED_MODELS:
                raise ValueError(
                    f"unknown shipped model {name!r}; choose one of "
                    + ", ".join(f"builtin:{n}" for n in SHIPPED_MODELS)
                )
            return f"builtin:{name}"
        if v.endswith((".pt", ".pth")):
            p = _resolved_path(v, info)
            if not p.exists():
                raise ValueError(f"model checkpoint not found: {p}")
            return str(p)
        names = _predictor_names()
        if v not in names:
            raise ValueError(
                f"unknown model {v!r}; use builtin:cylinder, builtin:ocean, a .pt checkpoint or one of "
                + ", ".join(names)
            )
        return v

    @model_validator(mode="after")
    def _cross(self):
        if self.model is None:
            src = self.field.builtin
            object.__setattr__(self, "model", DEFAULT_MODEL[src] if src else "dmd")
        g = self.region
        cells = [("start_cell", self.start_cell)] + [
            (f"vehicles[{k}].start_cell", v.start_cell) for k, v in enumerate(self.vehicles or ())
        ]
        for key, cell in cells:
            if cell is not None and not (0 <= cell[0] < g.rows and 0 <= cell[1] < g.cols):
                raise ValueError(f"{key} {list(cell)} lies outside the {g.rows}x{g.cols} grid")
        if self.vehicles is not None:
            if not self.vehicles:
                raise ValueError("vehicles: give at least one vehicle (or use vehicle: for one)")
            # (a dumped config carries the default vehicle beside vehicles: that one is fine)
            if "vehicle" in self.model_fields_set and self.vehicle != VehicleConfig():
                raise ValueError("give either vehicle: (one boat) or vehicles: (a fleet), not both")
            conns = [v.connect for v in self.vehicles]
            if len(set(conns)) != len(conns):
                raise ValueError(f"vehicles: two boats share a connection string ({conns})")
        return self

    @property
    def fleet(self) -> list[VehicleConfig]:
        """Every boat of the mission: ``vehicles``, or the one ``vehicle``."""
        return list(self.vehicles) if self.vehicles is not None else [self.vehicle]

    def grid(self):
        """The region's :mod:`geo` grid object."""
        return self.region.grid()

    def loop_preset(self) -> Preset:
        """The mission's loop settings as a :class:`passt_mav.loop.presets.Preset` (the same names)."""
        planner = {"planner": self.planner.name, "reward": self.planner.reward, "memory": self.planner.memory}
        gp = {k: getattr(self.gp, k) for k in Preset.__dataclass_fields__ if k not in planner}  # gp.* by its names
        return Preset(**planner, **gp)


def _check_options(options: dict, cls: type, what: str, internal: tuple[str, ...] = ()) -> None:
    """``options`` (a planner's or the GP's keyword options) name keyword parameters of ``cls`` (not ``internal``
    ones, which the loop sets) and hold finite numbers only: else ValueError naming the first problem."""
    import inspect
    import math

    params = inspect.signature(cls.__init__).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        allowed = [
            n
            for n, p in params.items()
            if n != "self" and n not in internal and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
        ]
        for key in options:
            if key not in allowed:
                raise ValueError(f"options: unknown option {_short(key)} {what} (allowed: {', '.join(allowed)})")

    def finite(v: Any, where: str) -> None:
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"options.{where}: must be a finite number (got {v})")
        if isinstance(v, dict):
            for k, x in v.items():
                finite(x, f"{where}.{k}")
        elif isinstance(v, list):
            for i, x in enumerate(v):
                finite(x, f"{where}[{i}]")

    for key, val in options.items():
        finite(val, str(key))


def _predictor_names() -> tuple[str, ...]:
    """Predictor registry names, from passt_mav.models when it imports (lazily), else the known ones."""
    try:
        from passt_mav.models.base import PREDICTORS  # noqa: PLC0415 - optional, heavy
    except Exception:  # noqa: BLE001 - the predictors package may be absent or broken in this build
        return _KNOWN_PREDICTORS
    return tuple(PREDICTORS)


# -- loading and one-line errors ------------------------------------------------------


def _fmt_loc(loc: tuple) -> str:
    parts = []
    for i, p in enumerate(loc):
        # drop the union tag pydantic inserts after "region", and the validator-function markers
        if i == 1 and loc[0] == "region" and p in ("geographic", "metric"):
            continue
        if isinstance(p, int):
            parts.append(f"[{p}]")
        else:
            parts.append(("." if parts else "") + str(p))
    return "".join(parts)


def _short(v: Any) -> str:
    s = repr(v)
    return s if len(s) <= 60 else s[:57] + "..."


def _fmt_error(e: dict, model_cls: type[BaseModel]) -> str:
    loc, typ, ctx, inp = tuple(e["loc"]), e["type"], e.get("ctx") or {}, e.get("input")
    where = _fmt_loc(loc)
    if typ == "missing":
        return f"{where}: required key is missing"
    if typ == "extra_forbidden":
        allowed = _allowed_keys(model_cls, loc[:-1])
        hint = f" (allowed: {', '.join(allowed)})" if allowed else ""
        return f"{where}: unknown key{hint}"
    bounds = {"greater_than_equal": ">=", "greater_than": ">", "less_than_equal": "<=", "less_than": "<"}
    if typ in bounds:
        key = {"greater_than_equal": "ge", "greater_than": "gt", "less_than_equal": "le", "less_than": "lt"}[typ]
        b = ctx.get(key)
        b = int(b) if isinstance(b, float) and b.is_integer() else b
        return f"{where}: must be {bounds[typ]} {b} (got {_short(inp)})"
    msg = str(e["msg"])
    msg = msg.removeprefix("Value error, ")
    msg = msg[0].lower() + msg[1:] if msg else msg
    if typ in ("value_error", "assertion_error"):
        return f"{where}: {msg}" if where else msg
    return f"{where}: {msg} (got {_short(inp)})"


def _allowed_keys(model_cls: type[BaseModel], loc: tuple) -> list[str]:
    """Keys allowed in the mapping at ``loc`` (for the "unknown key" message)."""
    tags = {"geographic": GeographicRegion, "metric": MetricRegion}
    cls: Any = model_cls
    i = 0
    while i < len(loc):
        if cls is model_cls and loc[i] == "region":
            if i + 1 < len(loc) and loc[i + 1] in tags:
                cls, i = tags[loc[i + 1]], i + 2
                continue
            return []
        f = cls.model_fields.get(loc[i]) if isinstance(loc[i], str) else None
        ann = getattr(f, "annotation", None)
        if not (isinstance(ann, type) and issubclass(ann, BaseModel)):
            return []
        cls, i = ann, i + 1
    return list(cls.model_fields)


def validate_mission(data: Any, *, source: str = "mission", base_dir: str | Path = ".") -> MissionConfig:
    """Validate a parsed mapping; errors raise :class:`MissionConfigError` ``"SOURCE: key: problem"``."""
    if not isinstance(data, dict):
        raise MissionConfigError(
            f"{source}: the mission file must be a YAML mapping of keys, got {type(data).__name__}"
        )
    try:
        return MissionConfig.model_validate(data, context={"base_dir": str(base_dir)})
    except ValidationError as exc:
        errs = exc.errors()
        more = f" (and {len(errs) - 1} more problem{'s' if len(errs) > 2 else ''})" if len(errs) > 1 else ""
        raise MissionConfigError(f"{source}: {_fmt_error(errs[0], MissionConfig)}{more}".replace("\n", " ")) from None


def _mission_loader():
    """A ``yaml.SafeLoader`` that refuses a key given twice in one mapping (PyYAML keeps the last silently) and a
    document whose aliases expand it past :data:`MAX_YAML_VALUES` values (counted on the node graph, each shared
    node once per use, without building anything); both as ``yaml.YAMLError`` with the place in the file."""
    import yaml
    from yaml.constructor import ConstructorError
    from yaml.nodes import MappingNode, SequenceNode

    class MissionLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, MappingNode):
                seen: dict[Any, Any] = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue  # '<<: *base' keys are overridden by the mapping's own, as YAML says
                    key = self.construct_object(key_node, deep=True)
                    try:
                        first = seen.setdefault(key, key_node)
                    except TypeError:
                        continue  # an unhashable key: SafeLoader names it below
                    if first is not key_node:
                        raise ConstructorError(
                            None,
                            None,
                            f"duplicate key {_short(key)} (first given at line {first.start_mark.line + 1}); "
                            "YAML would keep only the last",
                            key_node.start_mark,
                        )
            return super().construct_mapping(node, deep=deep)

        def get_single_data(self):
            node = self.get_single_node()
            if node is None:
                return None
            size: dict[int, int] = {}

            def count(n) -> int:  # values under n, aliases expanded (memoised: linear in the file)
                k = id(n)
                if k in size:
                    if size[k] < 0:
                        raise ConstructorError(None, None, "an alias refers to the value that holds it", n.start_mark)
                    return size[k]
                size[k] = -1
                total = 1
                if isinstance(n, SequenceNode):
                    children = n.value
                elif isinstance(n, MappingNode):
                    children = [c for kv in n.value for c in kv]
                else:
                    children = ()
                for c in children:
                    total += count(c)
                    if total > MAX_YAML_VALUES:
                        raise ConstructorError(
                            None,
                            None,
                            f"its aliases expand it past {MAX_YAML_VALUES:,} values (an alias bomb?); "
                            "a mission file is far smaller",
                            n.start_mark,
                        )
                size[k] = total
                return total

            count(node)
            return self.construct_document(node)

    return MissionLoader


def read_mission_data(path: str | Path) -> Any:
    """The parsed YAML of a mission file, not validated (None when empty): a file that cannot be read, is not
    YAML, is nested too deep, gives a key twice in one mapping or holds an alias bomb (:func:`_mission_loader`)
    is one :class:`MissionConfigError` naming it."""
    import yaml

    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise MissionConfigError(f"{p}: no such mission file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MissionConfigError(f"{p}: cannot read the mission file ({exc})") from None
    try:
        return yaml.load(text, Loader=_mission_loader())  # noqa: S506 - a SafeLoader (refusing more)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise MissionConfigError(f"{p}: invalid YAML{where}: {problem}") from None
    except RecursionError:
        raise MissionConfigError(f"{p}: invalid YAML: nested too deep for a mission file") from None


def load_mission(path: str | Path) -> MissionConfig:
    """Read and validate a mission YAML file (see module docstring)."""
    p = Path(path)
    data = read_mission_data(p)
    if data is None:
        raise MissionConfigError(f"{p}: the mission file is empty")
    try:
        return validate_mission(data, source=str(p), base_dir=p.parent)
    except RecursionError:
        raise MissionConfigError(f"{p}: nested too deep for a mission file") from None


def recorded_mission_text(text: str, config: MissionConfig) -> str:
    """The text of a mission file as a run directory keeps it (``mission.yaml``): ``text`` unchanged when its
    paths (``field.source``, a ``.pt``/``.pth`` ``model``) are ``builtin:`` or already as ``config`` resolved
    them (absolute); else the mission's mapping with those paths replaced by ``config``'s absolute ones (a YAML
    dump: comments are not kept), so that ``replay RUN_DIR`` and ``report`` find the files from any working
    directory. ``text`` must be the mission ``config`` was validated from."""
    import yaml

    data = yaml.load(text, Loader=_mission_loader())  # noqa: S506 - a SafeLoader (refusing more)
    if not isinstance(data, dict):
        return text
    changed = False
    field = data.get("field")
    source = field.get("source") if isinstance(field, dict) else field
    if isinstance(source, str) and config.field.builtin is None and source != config.field.source:
        data["field"] = {**field, "source": config.field.source} if isinstance(field, dict) else config.field.source
        changed = True
    model = data.get("model")
    if isinstance(model, str) and model.endswith((".pt", ".pth")) and model != config.model:
        data["model"] = config.model
        changed = True
    return yaml.safe_dump(data, sort_keys=False) if changed else text


def mission_overrides(data: dict, overrides: dict) -> dict:
    """A copy of a mission mapping with dotted-key overrides (``{"planner.path_length": 6}``)."""
    import copy

    out = copy.deepcopy(data)
    for key, val in overrides.items():
        cur = out
        parts = key.split(".")
        for i, p in enumerate(parts):
            if not isinstance(cur, dict):  # a dotted key through a value that holds no keys (a name, a list)
                where = ".".join(parts[:i])
                raise MissionConfigError(f"{key}: {where} is not a mapping of keys (got {_short(cur)})")
            if i < len(parts) - 1:
                cur = cur.setdefault(p, {})
        cur[parts[-1]] = val
    return out
