"""The simulated ArduPilot Rover (boat) autopilot: modes, arming, commands,
parameters, mission execution, telemetry streams, current sensor, GCS failsafe.

Everything runs in *simulated* seconds since boot (``t``). The
:class:`vehicle_sim.Simulator` owns the clock and the links and calls
:meth:`Autopilot.handle` for each message received and :meth:`Autopilot.update`
once per physics step.

Behaviour follows shared/ARDUPILOT_ROVER.md; choices where it is silent:

* Position-requiring modes (AUTO, GUIDED, LOITER, RTL, SMART_RTL, CIRCLE, FOLLOW,
  DOCK) are refused while armed without an absolute EKF position (ArduPilot's
  ``requires_position()``); HOLD/MANUAL/ACRO/STEERING/SIMPLE are always accepted.
* HOLD stops the motor and centres the steering (Rover's ``mode_hold.cpp``: throttle 0), so
  an armed boat in HOLD **drifts with the current**, as do MANUAL/ACRO/STEERING/SIMPLE (no RC
  input in a simulator) and any mode while disarmed. Rover 4.7 SITL (motorboat, ``SIM_TIDE_DIR``
  90, ``SIM_TIDE_SPEED`` 0.5 m/s): 120 s in HOLD moved it 60 m west when it was already drifting,
  49-50 m from a standstill in LOITER (the hull picks the current up against its drag:
  ``BoatParams.coast_drag_per_m``; tests/test_sitl_current.py).
* LOITER, CIRCLE, FOLLOW, DOCK, GUIDED without a target, RTL at home and AUTO's loiter
  submode keep station (Rover's ``mode_loiter.cpp``): the motor is off inside ``LOIT_RADIUS``
  (m) of the point where the mode began and the boat drives back (at most WP_SPEED) when the
  current sets it outside. SITL: 120 s of LOITER in the same current stayed within 2.7 m.
* AUTO's submodes as Rover's ``ModeAuto`` runs them on a boat: it enters in *loiter* (``_enter``:
  ``start_loiter``) until the first navigation command starts (*wp*); the end of the mission
  follows MIS_DONE_BEHAVE (``exit_mission``): 0 HOLD = *stop* (``start_stop``: ``stop_vehicle``
  brakes, then the motor is off and the boat drifts, still in AUTO), 1 *loiter* (keeps station,
  the boats' default), 2 ACRO, 3 MANUAL (mode changes: drift).
* Speed (m/s): the navigation speed is a **ground speed** along the bow, as Rover's speed
  controller holds it (``AR_AttitudeControl::get_forward_speed``: the EKF's ground velocity
  projected on the heading); the water speed commanded to the hull is that minus the current's
  component along the heading. SITL in a 0.5 m/s current flew 5.0 m/s over ground both with and
  against it (WP_SPEED 5). Entering AUTO, GUIDED, RTL or SMART_RTL resets the speed to
  WP_SPEED (``g2.wp_nav.init()``). DO_CHANGE_SPEED (mission item or COMMAND_LONG) sets the
  speed of the submode that runs it (``ModeAuto::set_desired_speed``): in AUTO's *wp* submode
  the waypoint speed; in the *loiter* submode (a DO_CHANGE_SPEED before the mission's first
  navigation command on a boat, or after the mission ended) it is **not** applied and the legs
  fly at WP_SPEED (Rover 4.7 SITL: "Mission: 1 ChangeSpeed", then 5.0 m/s); as a command it is
  then FAILED, as in HOLD, LOITER and the manual modes (their ``set_desired_speed`` is Mode's,
  which returns false).
* Arming before ``arm_ready_s`` is refused even with ARMING_SKIPCHK (ArduPilot's
  "System not initialised" is not a skippable check); force-arm (param2 = 2989)
  bypasses it.
* The GCS failsafe acts only while armed and only after a heartbeat from
  MAV_GCS_SYSID has been seen.
* Two clocks: ``t`` is the time since the last boot (``time_boot_ms``, the boot
  timeline); ``clock`` runs on through reboots (the world: the current field, UTC in
  SYSTEM_TIME, link timing). They are equal until :meth:`Autopilot.reboot`.
* Reboot (:meth:`Autopilot.reboot`, or MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN 246 with
  param1 = 1 while disarmed; Rover 4.7 SITL answered FAILED while armed and, disarmed,
  ACCEPTED then closed its TCP links): parameters and the stored mission survive (they
  are in eeprom), everything else restarts: INITIALISING, disarmed, no home, the boot
  timeline from 0, SET_MESSAGE_INTERVAL rates and mission transfers forgotten. The
  vehicle is silent for ``downtime_s`` while the boat drifts.
* GPS noise (``gps_noise_m`` > 0): reported positions (GLOBAL_POSITION_INT,
  GPS_RAW_INT, the current sensor's fix) carry a first-order Gauss-Markov error per
  axis (std ``gps_noise_m``, correlation time ``gps_noise_tau_s``), seeded; the boat
  navigates on its true position.
"""

from __future__ import annotations

import math
import random
import time as _time
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from vehicle_sim import telemetry
from vehicle_sim.boat import BoatState, CurrentModel, LocalFrame, guidance, step_boat
from vehicle_sim.config import SimConfig
from vehicle_sim.fence import PARAMS as FENCE_PARAMS
from vehicle_sim.fence import Fence
from vehicle_sim.mission_server import GLOBAL_FRAMES, MissionServer, MissionStore
from vehicle_sim.modes import MANUAL_INPUT, MODE_NAMES, MODES, NEEDS_POSITION, SETTABLE

__all__ = ["Autopilot", "MODES", "MODE_NAMES", "DEFAULT_PARAMS"]

M = mavlink2

_I8, _I16, _I32, _F = M.MAV_PARAM_TYPE_INT8, M.MAV_PARAM_TYPE_INT16, M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_REAL32

#: name -> (default, MAV_PARAM_TYPE); Rover 4.7 names (MAV_SYSID, MAV1_*, ARMING_SKIPCHK)
DEFAULT_PARAMS: dict[str, tuple[float, int]] = {
    "ARMING_SKIPCHK": (0, _I32),
    "ARMING_REQUIRE": (1, _I8),
    "BATT_CAPACITY": (5000, _I32),
    "CRUISE_SPEED": (2.0, _F),
    "FRAME_CLASS": (2, _I8),  # boat
    "FS_ACTION": (2, _I8),  # Hold
    "FS_GCS_ENABLE": (0, _I8),
    "FS_TIMEOUT": (1.5, _F),
    "LOIT_RADIUS": (2.0, _F),
    "MAV_GCS_SYSID": (255, _I16),
    "MAV_SYSID": (1, _I16),
    "MIS_DONE_BEHAVE": (1, _I8),  # boats: loiter
    "MIS_OPTIONS": (0, _I16),
    "MIS_RESTART": (0, _I8),
    "MIS_TOTAL": (0, _I16),
    "WP_ACCEL": (0.0, _F),
    "WP_RADIUS": (2.0, _F),
    "WP_SPEED": (2.0, _F),
}
_STREAM_PARAMS = (
    "RAW_SENS",
    "EXT_STAT",
    "RC_CHAN",
    "RAW_CTRL",
    "POSITION",
    "EXTRA1",
    "EXTRA2",
    "EXTRA3",
    "PARAMS",
    "ADSB",
)
for _n in range(1, 5):
    for _s in _STREAM_PARAMS:
        DEFAULT_PARAMS[f"MAV{_n}_{_s}"] = (1 if _s not in ("RC_CHAN", "RAW_CTRL", "RAW_SENS", "ADSB") else 0, _I16)
    DEFAULT_PARAMS[f"MAV{_n}_OPTIONS"] = (0, _I16)
DEFAULT_PARAMS.update(FENCE_PARAMS)

#: stream group -> messages (ArduPilot's ap_message groups, reduced to what we send)
STREAM_GROUPS = {
    "EXT_STAT": (
        "SYS_STATUS",
        "GPS_RAW_INT",
        "MISSION_CURRENT",
        "NAV_CONTROLLER_OUTPUT",
        "POWER_STATUS",
        "MEMINFO",
        "FENCE_STATUS",  # (none while the fence is disabled)
    ),
    "POSITION": ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    "EXTRA1": ("ATTITUDE",),
    "EXTRA2": ("VFR_HUD",),
    "EXTRA3": ("SYSTEM_TIME", "BATTERY_STATUS", "EKF_STATUS_REPORT"),
}
#: MAV_DATA_STREAM id -> group
DATA_STREAM_IDS = {2: "EXT_STAT", 6: "POSITION", 10: "EXTRA1", 11: "EXTRA2", 12: "EXTRA3"}
#: messages always sent at 1 Hz unless SET_MESSAGE_INTERVAL says otherwise
FIXED_STREAMS = ("HEARTBEAT", "TIMESYNC")

#: messages SET_MESSAGE_INTERVAL refuses (Rover 4.7: result 2, "No ap_message for mavlink id (111)")
NOT_STREAMS = frozenset({"TIMESYNC"})

ARM_FORCE_MAGIC = 2989
DISARM_FORCE_MAGIC = 21196


@dataclass
class LinkStreams:
    """Per-link telemetry schedule (intervals in simulated seconds; <= 0 off)."""

    group_hz: dict
    overrides: dict  # msg name -> interval s (-1 off)
    next_due: dict


class Autopilot:
    """A Rover boat: see the module docstring.

    Args:
        home: ``(lat, lon)`` degrees: start position and home.
        current: the :class:`CurrentModel` the boat drifts in.
        config: :class:`SimConfig`.
        send: ``send(link, msg)`` queues one message on one link.
        links: ``links() -> list`` of the live links (telemetry goes to all).
        epoch0: UTC epoch seconds at boot (SYSTEM_TIME, tlog).
    """

    MAVLINK = mavlink2

    def __init__(
        self,
        home: tuple[float, float],
        current: CurrentModel,
        config: SimConfig,
        send: Callable,
        links: Callable[[], list],
        epoch0: float | None = None,
        home_alt: float = 0.0,
    ):
        self.cfg = config
        self.current_model = current
        self._send_raw = send
        self._links = links
        self.epoch0 = _time.time() if epoch0 is None else float(epoch0)
        self.home_latlon = (float(home[0]), float(home[1]))
        self.home_alt = float(home_alt)
        self.frame = LocalFrame(*self.home_latlon)
        self.boat = BoatState()
        self.t = 0.0  # seconds since the last boot (time_boot_ms)
        self.clock = 0.0  # seconds since the simulation started: runs on through reboots
        self.boot_count = 0
        self.down_until: float | None = None  # clock time a rebooting vehicle speaks again
        self.sysid, self.compid = config.sysid, config.compid
        self.params: dict[str, float] = {k: float(v) for k, (v, _) in DEFAULT_PARAMS.items()}
        self.params["MAV_SYSID"] = float(config.sysid)
        for k, v in config.params:
            if k not in self.params:
                raise ValueError(f"unknown parameter {k!r}")
            self.params[k] = float(v)
        self._param_names = sorted(self.params)
        self.mode = MODES["INITIALISING"]
        self.armed = False
        self.first_armed_clock: float | None = None  # ``clock`` at the first arming (kept over reboots)
        self.home_set = False
        self.store = MissionStore(config.mission_capacity)
        self.missions = MissionServer(
            self.store,
            config,
            self.send,
            self.text,
            self.home,
            self._mission_changed,
            sysid=self.sysid,
            compid=self.compid,
        )
        # mission executor
        self.mission_index = 0  # current nav index (0 = none)
        self.mission_state = "stopped"  # stopped | running | complete
        self.mission_started = False
        self.active_item = None  # cached item being executed (continues by old sequence)
        self.leg_origin: tuple[float, float] | None = None
        self.loiter_until: float | None = None
        self.reached_current = False
        self.jump_counts: dict[int, int] = {}
        self.speed_override: float | None = None  # m/s from DO_CHANGE_SPEED; None: WP_SPEED
        #: AUTO's submode (Rover's ModeAuto::_submode): "loiter" (on entry, and MIS_DONE_BEHAVE 1),
        #: "wp" (a navigation command runs), "stop" (MIS_DONE_BEHAVE 0: brakes, then motor off)
        self.auto_submode = "loiter"
        self.station: tuple[float, float] | None = None  # station-keeping point (x, y)
        self.guided_target: tuple[float, float] | None = None
        # failsafe
        self.last_gcs_hb: float | None = None
        self.failsafe = False
        self.fence = Fence()  # (vehicle_sim.fence: FENCE_* parameters, the stored fence list)
        # sensors
        self._rng = random.Random(config.seed)
        self._gps_rng = random.Random(
            config.seed * 7919 + 17
        )  # its own stream: adding GPS noise keeps the current noise
        self._gps_err = (
            [self._gps_rng.gauss(0.0, config.gps_noise_m), self._gps_rng.gauss(0.0, config.gps_noise_m)]
            if config.gps_noise_m > 0
            else [0.0, 0.0]
        )
        self._next_sample = 0.0
        self.samples_sent = 0
        self.energy_wh = 0.0  # energy the boat used since boot (Wh): the battery telemetry's
        self.streams: dict[int, LinkStreams] = {}
        self.texts: list[tuple[float, str]] = []  # every STATUSTEXT sent (tests, console)
        self._boot_events_done: set[str] = set()
        self.reboot_requested = False

    # -- parameters ---------------------------------------------------------------
    def p(self, name: str) -> float:
        return self.params[name]

    # -- sending ---------------------------------------------------------------------
    def send(self, link, msg) -> None:
        """Queue ``msg`` on ``link`` (None = every link)."""
        if link is None:
            for ln in self._links():
                self._send_raw(ln, msg)
        else:
            self._send_raw(link, msg)

    def text(self, link, severity: int, text: str) -> None:
        self.texts.append((self.t, text))
        self.send(link, M.MAVLink_statustext_message(severity, text.encode()[:50], 0, 0))

    def _ack(self, link, msg, command: int, result: int) -> None:
        self.send(
            link, M.MAVLink_command_ack_message(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        )

    # -- derived state ----------------------------------------------------------------
    @property
    def time_boot_ms(self) -> int:
        return int(round(self.t * 1000.0))

    @property
    def gps_ok(self) -> bool:
        return self.t >= self.cfg.gps_s

    @property
    def ekf_abs(self) -> bool:
        return self.t >= self.cfg.ekf_gps_s

    def position(self) -> tuple[float, float]:
        """Boat (lat, lon) degrees (true position)."""
        return self.frame.to_latlon(self.boat.x, self.boat.y)

    def reported_position(self) -> tuple[float, float]:
        """What the GPS reports, (lat, lon) degrees: the true position plus the GPS error (``gps_noise_m``)."""
        if self.cfg.gps_noise_m <= 0:
            return self.position()
        return self.frame.to_latlon(self.boat.x + self._gps_err[0], self.boat.y + self._gps_err[1])

    def _gps_noise_step(self, dt: float) -> None:
        sd = self.cfg.gps_noise_m
        if sd <= 0:
            return
        # first-order Gauss-Markov: stationary std sd, correlation time tau (a GPS error wanders, it is not white)
        a = math.exp(-dt / max(self.cfg.gps_noise_tau_s, 1e-6))
        q = sd * math.sqrt(max(1.0 - a * a, 0.0))
        self._gps_err = [a * e + self._gps_rng.gauss(0.0, q) for e in self._gps_err]

    @property
    def down(self) -> bool:
        """Rebooting: the vehicle neither sends nor hears anything."""
        return self.down_until is not None and self.clock < self.down_until

    def reboot(self, downtime_s: float = 2.0) -> None:
        """Restart the autopilot (brown-out, watchdog, or a commanded reboot); see the module docstring.

        Kept: parameters, the stored missions (eeprom), the boat where it is, ``clock``. Reset: the
        boot timeline (``t`` = 0), mode INITIALISING, disarmed, home unset, mission progress, stream
        rates set by SET_MESSAGE_INTERVAL, open mission transfers, failsafe. Silent for ``downtime_s``.
        """
        self.boot_count += 1
        self.down_until = self.clock + max(float(downtime_s), 0.0)
        self.t = 0.0
        self.mode = MODES["INITIALISING"]
        self.armed = False
        self.home_set = False
        self.home_latlon = self.position()  # the new home is where the boat is when GPS comes back
        self.missions = MissionServer(
            self.store,
            self.cfg,
            self.send,
            self.text,
            self.home,
            self._mission_changed,
            sysid=self.sysid,
            compid=self.compid,
            normalise=self.missions.normalise,
        )
        self.mission_index = 0
        self.mission_state = "stopped"
        self.mission_started = False
        self.active_item = None
        self.leg_origin = None
        self.loiter_until = None
        self.reached_current = False
        self.jump_counts.clear()
        self.speed_override = None
        self.auto_submode = "loiter"
        self.station = None
        self.guided_target = None
        self.last_gcs_hb = None
        self.failsafe = False
        self.fence.reset()
        self._next_sample = 0.0
        self.streams.clear()
        self._boot_events_done.clear()

    def home(self) -> tuple[float, float, float]:
        if not self.home_set:
            return (0.0, 0.0, 0.0)
        return (self.home_latlon[0], self.home_latlon[1], self.home_alt)

    def wp_speed(self) -> float:
        """The navigation speed (m/s over ground along the bow): DO_CHANGE_SPEED's, else WP_SPEED."""
        return self.speed_override if self.speed_override else self.p("WP_SPEED")

    def _speed_settable(self) -> bool:
        """Whether DO_CHANGE_SPEED has a taker in this mode (Rover: the mode overrides ``set_desired_speed``;
        AUTO passes it to its submode, and its loiter submode has none)."""
        if self.mode == MODES["AUTO"]:
            return self.auto_submode != "loiter"
        return self.mode not in (
            MODES["HOLD"],
            MODES["LOITER"],
            MODES["MANUAL"],
            MODES["ACRO"],
            MODES["STEERING"],
            MODES["SIMPLE"],
            MODES["INITIALISING"],
        )

    def mission_total(self) -> int:
        return max(self.store.count(0) - 1, 0)

    def mission_state_code(self) -> int:
        if self.store.count(0) <= 1:
            return M.MISSION_STATE_NO_MISSION
        if self.mission_state == "complete":
            return M.MISSION_STATE_COMPLETE
        if self.mission_state == "running" and self.mode == MODES["AUTO"]:
            return M.MISSION_STATE_ACTIVE
        return M.MISSION_STATE_PAUSED if self.mission_started else M.MISSION_STATE_NOT_STARTED

    # -- message handling ----------------------------------------------------------------
    def handle(self, link, msg) -> None:
        """React to one received message (already through the link's impairment)."""
        if self.down:
            return
        typ = msg.get_type()
        if typ == "HEARTBEAT":
            if msg.get_srcSystem() == int(self.p("MAV_GCS_SYSID")):
                self.last_gcs_hb = self.t
            return
        if self.missions.handle(link, msg, self.t) and not (
            typ in ("MISSION_ITEM_INT", "MISSION_ITEM") and int(msg.current) in (2, 3)
        ):
            return
        ts = getattr(msg, "target_system", None)
        if ts is not None and ts not in (0, self.sysid):
            return  # for another vehicle
        handler = getattr(self, "_on_" + typ.lower(), None)
        if handler is not None:
            handler(link, msg)

    def _on_mission_item_int(self, link, msg):  # guided goto via MISSION_ITEM(_INT) current=2
        if int(msg.current) == 2 and msg.frame in GLOBAL_FRAMES:
            scale = 1e7 if msg.get_type() == "MISSION_ITEM_INT" else 1.0
            if self.mode != MODES["GUIDED"]:
                self.missions._ack(link, msg, 0, M.MAV_MISSION_ERROR)
                return
            self.guided_target = self.frame.to_xy(msg.x / scale, msg.y / scale)
            self.missions._ack(link, msg, 0, M.MAV_MISSION_ACCEPTED)

    _on_mission_item = _on_mission_item_int

    def _on_command_long(self, link, msg):
        if msg.target_component not in (0, self.compid):
            return
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        self._command(link, msg, int(msg.command), params, is_int=False)

    def _on_command_int(self, link, msg):
        if msg.target_component not in (0, self.compid):
            return
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        self._command(link, msg, int(msg.command), params, is_int=True)

    def _command(self, link, msg, cmd: int, p: list, is_int: bool) -> None:
        R = M
        result = R.MAV_RESULT_UNSUPPORTED
        if cmd == R.MAV_CMD_DO_SET_MODE:
            result = (
                self.set_mode(int(p[1]), link)
                if int(p[0]) & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                else R.MAV_RESULT_UNSUPPORTED
            )
        elif cmd == R.MAV_CMD_MISSION_START:
            # first/last item arguments are not supported by ArduPilot: DENIED unless both are 0
            result = self.set_mode(MODES["AUTO"], link) if p[0] == 0 and p[1] == 0 else R.MAV_RESULT_DENIED
        elif cmd == R.MAV_CMD_COMPONENT_ARM_DISARM:
            result = self.arm(link) if p[0] >= 0.5 else self.disarm()
            if p[0] >= 0.5 and int(round(p[1])) == ARM_FORCE_MAGIC and result != R.MAV_RESULT_ACCEPTED:
                result = self.arm(link, force=True)
        elif cmd == R.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_message_interval(link, int(p[0]), float(p[1]))
        elif cmd == R.MAV_CMD_REQUEST_MESSAGE:
            result = R.MAV_RESULT_ACCEPTED if self._send_one(link, int(p[0]), msg) else R.MAV_RESULT_DENIED
            if result == R.MAV_RESULT_ACCEPTED:
                self._ack(link, msg, cmd, result)  # ArduPilot acks first, then the message follows
                self._send_one(link, int(p[0]), msg, send=True)
                return
        elif cmd == R.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            # Rover 4.7 SITL: FAILED while armed (no STATUSTEXT); disarmed, ACCEPTED and then the reboot
            if int(p[0]) != 1:
                result = R.MAV_RESULT_UNSUPPORTED
            elif self.armed:
                result = R.MAV_RESULT_FAILED
            else:
                self._ack(link, msg, cmd, R.MAV_RESULT_ACCEPTED)
                self.reboot_requested = True  # the Simulator reboots after this step (it owns the links)
                return
        elif cmd == R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._ack(link, msg, cmd, R.MAV_RESULT_ACCEPTED)
            self.send(link, telemetry.autopilot_version(self))
            return
        elif cmd == R.MAV_CMD_GET_HOME_POSITION:
            result = R.MAV_RESULT_ACCEPTED if self.home_set else R.MAV_RESULT_FAILED
            if self.home_set:
                self.send(link, telemetry.home_position(self))
        elif cmd == R.MAV_CMD_DO_SET_HOME:
            if int(p[0]) == 1:
                lat, lon = self.position()
            else:
                lat, lon = (p[4] / 1e7, p[5] / 1e7) if is_int else (p[4], p[5])
            if not (-90 <= lat <= 90 and -180 <= lon <= 180) or not self.gps_ok:
                result = R.MAV_RESULT_FAILED
            else:
                self.home_latlon = (float(lat), float(lon))
                self.home_set = True
                self.store.set_home(lat, lon, self.home_alt)
                self.send(None, telemetry.home_position(self))
                result = R.MAV_RESULT_ACCEPTED
        elif cmd == R.MAV_CMD_DO_SET_MISSION_CURRENT:
            result = (
                R.MAV_RESULT_ACCEPTED
                if self.set_mission_current(int(p[0]), reset=int(p[1]) == 1)
                else R.MAV_RESULT_DENIED
            )
        elif cmd == R.MAV_CMD_DO_CHANGE_SPEED:
            # Rover: control_mode->set_desired_speed(param2); FAILED where the mode has none (see _speed_settable)
            if p[1] > 0 and self._speed_settable():
                self.speed_override = float(p[1])
                result = R.MAV_RESULT_ACCEPTED
            else:
                result = R.MAV_RESULT_FAILED
        elif cmd == R.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            result = self.set_mode(MODES["RTL"], link)
        elif cmd == R.MAV_CMD_DO_REPOSITION and is_int:
            if (
                self.mode != MODES["GUIDED"]
                and (int(p[1]) & 1)  # MAV_DO_REPOSITION_FLAGS_CHANGE_MODE
                and self.set_mode(MODES["GUIDED"], link) != R.MAV_RESULT_ACCEPTED
            ):
                self._ack(link, msg, cmd, R.MAV_RESULT_FAILED)
                return
            if self.mode == MODES["GUIDED"]:
                self.guided_target = self.frame.to_xy(p[4] / 1e7, p[5] / 1e7)
                result = R.MAV_RESULT_ACCEPTED
            else:
                result = R.MAV_RESULT_FAILED
        self._ack(link, msg, cmd, result)

    def _on_set_mode(self, link, msg):
        result = (
            self.set_mode(int(msg.custom_mode), link)
            if msg.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            else M.MAV_RESULT_UNSUPPORTED
        )
        # ArduPilot acknowledges SET_MODE with a COMMAND_ACK whose command is the message id (11)
        self._ack(link, msg, M.MAVLINK_MSG_ID_SET_MODE, result)

    def _on_mission_set_current(self, link, msg):
        if self.set_mission_current(int(msg.seq)):
            self.send(None, telemetry.mission_current(self))

    def _on_param_request_list(self, link, msg):
        for i, name in enumerate(self._param_names):
            self.send(link, self._param_value(name, i))

    def _on_param_request_read(self, link, msg):
        name = _pname(msg.param_id)
        if msg.param_index >= 0:
            if msg.param_index < len(self._param_names):
                name = self._param_names[msg.param_index]
            else:
                return
        if name in self.params:
            self.send(link, self._param_value(name))

    def _on_param_set(self, link, msg):
        name = _pname(msg.param_id)
        if name not in self.params:
            return  # unknown names get no reply, like ArduPilot (e.g. 4.7 has no ARMING_CHECK)
        value = float(msg.param_value)
        if not math.isfinite(value):
            return
        if DEFAULT_PARAMS[name][1] != _F:
            value = float(int(round(value)))
        self.params[name] = value
        if name.startswith("MAV") and name[3:4].isdigit():
            self._refresh_stream_params()
        self.send(None, self._param_value(name))

    def _on_request_data_stream(self, link, msg):
        groups = list(STREAM_GROUPS) if msg.req_stream_id == 0 else [DATA_STREAM_IDS.get(msg.req_stream_id)]
        ls = self._streams(link)
        for g in groups:
            if g is None:
                continue
            ls.group_hz[g] = float(msg.req_message_rate) if msg.start_stop else 0.0
            for name in STREAM_GROUPS[g]:
                ls.next_due[name] = self.t

    def _on_set_position_target_global_int(self, link, msg):
        if self.mode == MODES["GUIDED"] and not (msg.type_mask & 0b111):
            self.guided_target = self.frame.to_xy(msg.lat_int / 1e7, msg.lon_int / 1e7)

    def _on_timesync(self, link, msg):
        if msg.tc1 == 0:  # a request: answer with our clock (ns since boot)
            self.send(link, M.MAVLink_timesync_message(int(self.t * 1e9), msg.ts1))

    # -- modes and arming -----------------------------------------------------------------
    def set_mode(self, mode: int, link=None) -> int:
        """Try to change mode; returns a MAV_RESULT."""
        if mode not in SETTABLE or self.mode == MODES["INITIALISING"]:
            return M.MAV_RESULT_FAILED
        if self.armed and mode in NEEDS_POSITION and not self.ekf_abs:
            self.text(link, M.MAV_SEVERITY_WARNING, "Flight mode change failed")
            return M.MAV_RESULT_FAILED
        if mode == self.mode:
            return M.MAV_RESULT_ACCEPTED  # like ArduPilot: asking for the current mode does not re-enter it
        self._enter_mode(mode)
        return M.MAV_RESULT_ACCEPTED

    def _enter_mode(self, mode: int) -> None:
        prev = self.mode
        self.mode = mode
        self.station = (self.boat.x, self.boat.y)
        self.guided_target = None if mode != MODES["GUIDED"] or prev != MODES["GUIDED"] else self.guided_target
        if mode in (MODES["AUTO"], MODES["GUIDED"], MODES["RTL"], MODES["SMART_RTL"]):
            self.speed_override = None  # their _enter calls g2.wp_nav.init(): the speed is WP_SPEED again
        if mode == MODES["AUTO"]:
            self.auto_submode = "loiter"  # ModeAuto::_enter on a boat: start_loiter() until a nav command runs
            self._start_or_resume()
        elif prev == MODES["AUTO"] and self.mission_state == "running":
            self.mission_state = "stopped"

    def arm(self, link=None, force: bool = False) -> int:
        if self.armed:
            return M.MAV_RESULT_ACCEPTED
        if not force and (self.t < self.cfg.arm_ready_s or self.mode == MODES["INITIALISING"]):
            self.text(link, M.MAV_SEVERITY_CRITICAL, "Arm: System not initialised")
            return M.MAV_RESULT_FAILED
        self.armed = True
        if self.first_armed_clock is None:
            self.first_armed_clock = self.clock
            for ln in self._links():  # arm-relative outages (LinkConfig.arm_drops) count from here
                ln.armed_at = self.clock
        return M.MAV_RESULT_ACCEPTED

    def disarm(self) -> int:
        self.armed = False
        self.failsafe = False
        return M.MAV_RESULT_ACCEPTED

    # -- mission execution ------------------------------------------------------------------
    def _mission_changed(self, mtype: int) -> None:
        if mtype != 0:
            return
        self.params["MIS_TOTAL"] = float(self.store.count(0))  # ArduPilot's read-only count (incl. home)
        if self.store.count(0) <= 1:
            self.mission_state = "stopped"
            self.mission_started = False
            self.mission_index = 0
            self.active_item = None
        elif self.mission_state == "complete":
            pass  # a new mission after completion starts afresh on the next AUTO entry
        # otherwise: the cached active item goes on (ArduPilot continues by the old sequence)

    def _start_or_resume(self) -> None:
        n = self.store.count(0)
        if n <= 1:
            self.mission_state = "stopped"
            self.active_item = None
            return
        restart = int(self.p("MIS_RESTART")) == 1 or self.mission_state == "complete" or not self.mission_started
        idx = 1 if restart or not (1 <= self.mission_index < n) else self.mission_index
        if restart:
            self.jump_counts.clear()
        self.mission_started = True
        self.mission_state = "running"
        self._load(idx)

    def _load(self, idx: int) -> None:
        """Make item ``idx`` current (skipping/doing non-navigation items)."""
        guard = 0
        while True:
            guard += 1
            if idx >= self.store.count(0) or guard > 1000:
                self._complete()
                return
            it = self.store.items[0][idx]
            if it.command == M.MAV_CMD_DO_CHANGE_SPEED:
                # ModeAuto::do_change_speed -> set_desired_speed of the submode: before the first navigation
                # command of this AUTO entry a boat is in its loiter submode, which takes no speed (no text)
                if it.param2 > 0 and self.auto_submode != "loiter":
                    self.speed_override = float(it.param2)
                    self.text(None, M.MAV_SEVERITY_INFO, f"speed: {float(it.param2):.1f} m/s")
                # Rover verifies DO_CHANGE_SPEED itself and reports it reached (servo/relay items it does not)
                self.send(None, M.MAVLink_mission_item_reached_message(idx))
                idx += 1
                continue
            if it.command == M.MAV_CMD_DO_JUMP:
                target, repeat = int(it.param1), int(it.param2)
                done = self.jump_counts.get(idx, 0)
                if repeat < 0 or done < repeat:
                    self.jump_counts[idx] = done + 1
                    idx = max(1, target)
                else:
                    idx += 1
                continue
            if it.command in (
                M.MAV_CMD_NAV_WAYPOINT,
                M.MAV_CMD_NAV_LOITER_UNLIM,
                M.MAV_CMD_NAV_LOITER_TIME,
                M.MAV_CMD_NAV_LOITER_TURNS,
                M.MAV_CMD_NAV_RETURN_TO_LAUNCH,
            ):
                break
            idx += 1  # other DO_/CONDITION_ items: nothing to simulate
        prev_target = self.item_xy(self.active_item) if self.active_item is not None else None
        self.mission_index = idx
        self.active_item = it
        self.auto_submode = "wp"
        self.leg_origin = prev_target if prev_target is not None else (self.boat.x, self.boat.y)
        self.loiter_until = None
        self.reached_current = False
        self.send(None, telemetry.mission_current(self))

    def item_xy(self, it) -> tuple[float, float]:
        """Local (x east, y north) metres of mission item ``it``: home for RTL, the boat's position for an item
        without a global position."""
        if it.command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self.frame.to_xy(*self.home_latlon)
        if (it.x == 0 and it.y == 0) or it.frame not in GLOBAL_FRAMES:
            return (self.boat.x, self.boat.y)  # no location: "here"
        return self.frame.to_xy(it.lat, it.lon)

    def _complete(self) -> None:
        if self.mission_state != "complete":
            self.mission_state = "complete"
            self.mission_index = self.store.count(0) - 1
            self.active_item = None
            self.station = (self.boat.x, self.boat.y)
            self.text(None, M.MAV_SEVERITY_INFO, "Mission Complete")
            self.send(None, telemetry.mission_current(self))
            # ModeAuto::exit_mission: 1 loiter (keeps station), 2 ACRO, 3 MANUAL; 0 HOLD (and any failure):
            # start_stop(), the Stop submode: brakes, then motor off in AUTO, the boat drifts
            behave = int(self.p("MIS_DONE_BEHAVE"))
            self.auto_submode = "loiter" if behave == 1 else "stop"
            if behave == 2:
                self._enter_mode(MODES["ACRO"])
            elif behave == 3:
                self._enter_mode(MODES["MANUAL"])

    def set_mission_current(self, seq: int, reset: bool = False) -> bool:
        n = self.store.count(0)
        if seq == 0 and n > 1:
            seq = 1
        if not 1 <= seq < n:
            return False
        if reset:
            self.jump_counts.clear()
        if self.mode == MODES["AUTO"] and self.mission_state in ("running", "complete"):
            self.mission_state = "running"
            self.mission_started = True
            self.active_item = None
            self._load(seq)
        else:
            self.mission_index = seq
            self.mission_started = True if not reset else self.mission_started
            if self.mission_state == "complete":
                self.mission_state = "stopped"
            self.active_item = None
        return True

    def _advance(self) -> None:
        self._load(self.mission_index + 1)

    # -- the control loop ----------------------------------------------------------------------
    def _boot_events(self) -> None:
        if self.mode == MODES["INITIALISING"] and self.t >= self.cfg.init_s:
            self.mode = MODES["MANUAL"]
            self.station = (self.boat.x, self.boat.y)
        if self.gps_ok and not self.home_set:
            self.home_set = True
            self.store.set_home(self.home_latlon[0], self.home_latlon[1], self.home_alt)
            self.send(None, telemetry.home_position(self))
        if self.ekf_abs and "ekf" not in self._boot_events_done:
            self._boot_events_done.add("ekf")
            self.text(None, M.MAV_SEVERITY_INFO, "EKF3 IMU0 is using GPS")

    def _command_motion(self, current) -> tuple[float, float | None]:
        """(commanded heading rad, water speed m/s) for the mode and mission; speed None: motor off (the hull
        coasts, :func:`vehicle_sim.boat.step_boat`), the boat drifts with the current."""
        b = self.boat
        if not self.armed or self.mode in MANUAL_INPUT or self.mode in (MODES["SIMPLE"], MODES["INITIALISING"]):
            return b.heading, None
        if self.mode == MODES["HOLD"]:
            return b.heading, None  # mode_hold.cpp: throttle 0, steering centred: the boat drifts
        if self.mode == MODES["AUTO"] and self.mission_state == "running" and self.active_item is not None:
            return self._auto_motion(current)
        if self.mode == MODES["AUTO"] and self.auto_submode == "stop":
            # ModeAuto's Stop submode (MIS_DONE_BEHAVE 0): stop_vehicle() brakes to a stop, then throttle 0 (drifts)
            return b.heading, 0.0
        if self.mode in (MODES["RTL"], MODES["SMART_RTL"]):
            home = self.frame.to_xy(*self.home_latlon)
            if math.hypot(home[0] - b.x, home[1] - b.y) > self.p("WP_RADIUS") and self.station != home:
                return self._navigate(home, None, current)
            self.station = home
        if self.mode == MODES["GUIDED"] and self.guided_target is not None:
            tgt = self.guided_target
            if math.hypot(tgt[0] - b.x, tgt[1] - b.y) > self.p("WP_RADIUS"):
                return self._navigate(tgt, None, current)
            self.station, self.guided_target = tgt, None
        return self._station_keep(current)

    def _navigate(self, target, origin, current) -> tuple[float, float]:
        """(heading rad, water speed m/s) toward ``target`` (east, north m) at :meth:`wp_speed` over ground.

        Rover's speed controller holds the ground speed along the bow (the EKF's ground velocity projected on the
        heading), so the hull is asked for that speed minus the current's component along its heading
        (``current`` east, north m/s): with the current it slows down through the water, against it speeds up.
        """
        b = self.boat
        heading, speed = guidance(b, target, self.wp_speed(), current, self.cfg.boat, origin)
        along = current[0] * math.sin(b.heading) + current[1] * math.cos(b.heading)
        return heading, max(0.0, speed - along)

    def _station_keep(self, current) -> tuple[float, float]:
        """Rover's loiter (mode_loiter.cpp): motor off inside LOIT_RADIUS (m) of :attr:`station`, else drive back."""
        b = self.boat
        if self.station is None:
            self.station = (b.x, b.y)
        sx, sy = self.station
        d = math.hypot(sx - b.x, sy - b.y)
        radius = max(self.p("LOIT_RADIUS"), 0.5)
        if d <= radius:
            return b.heading, 0.0  # motor off inside the circle: let it drift
        cur = math.hypot(*current)
        # Rover's loiter drives back at most at WP_SPEED (wp_nav's default speed, not DO_CHANGE_SPEED's)
        speed = min(self.cfg.boat.max_speed, max(self.p("WP_SPEED"), 1.5 * cur))
        speed = min(speed, max(0.5, d))  # slow down on approach so it does not overshoot
        return guidance(b, (sx, sy), speed, current, self.cfg.boat, None)

    def _auto_motion(self, current) -> tuple[float, float]:
        b = self.boat
        # several items may be reached at once (stacked waypoints): bounded, the rest waits for the next step
        for _ in range(32):
            it = self.active_item
            if it is None or self.mission_state != "running":
                return self._station_keep(current)
            tgt = self.item_xy(it)
            if self.reached_current:
                self.station = tgt
                return self._station_keep(current)
            d = math.hypot(tgt[0] - b.x, tgt[1] - b.y)
            passed = False
            if self.cfg.boat.nav == "crosstrack" and self.leg_origin is not None:
                ox, oy = self.leg_origin
                lx, ly = tgt[0] - ox, tgt[1] - oy
                leg = math.hypot(lx, ly)
                passed = leg > 1e-6 and ((b.x - ox) * lx + (b.y - oy) * ly) / leg >= leg
            if not (d <= self.p("WP_RADIUS") or passed):
                return self._navigate(tgt, self.leg_origin, current)
            self._reached(it, d)
        return self._station_keep(current)

    def _reached(self, it, dist: float) -> None:
        """The boat is at the active item: report, then loiter or advance."""
        idx = self.mission_index
        cmd = it.command
        if cmd == M.MAV_CMD_NAV_LOITER_UNLIM:
            if not self.reached_current:
                self.reached_current = True
                self.send(None, M.MAVLink_mission_item_reached_message(idx))
            return
        # texts as Rover 4.7 SITL words them (tests/test_sitl_differential.py); RTL reaches home silently
        if cmd in (M.MAV_CMD_NAV_LOITER_TIME,) or (cmd == M.MAV_CMD_NAV_WAYPOINT and it.param1 > 0):
            if self.loiter_until is None:
                self.loiter_until = self.t + max(float(it.param1), 0.0)
                self.reached_current = True
                self.text(None, M.MAV_SEVERITY_INFO, f"Reached waypoint #{idx}. Loiter for {int(it.param1)} seconds")
                self.send(None, M.MAVLink_mission_item_reached_message(idx))
            return
        if cmd != M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self.text(None, M.MAV_SEVERITY_INFO, f"Reached waypoint #{idx}")
        self.send(None, M.MAVLink_mission_item_reached_message(idx))
        self._advance()

    def update(self, dt: float) -> None:
        """Advance the vehicle by ``dt`` simulated seconds (physics, mission, failsafe, streams)."""
        if self.down:
            # powered off: the boat drifts with the motor off; the boot timeline starts when it is back
            lat, lon = self.position()
            cur = self.current_model.at(self.clock, lat, lon)
            step_boat(self.boat, self.boat.heading, 0.0, cur, dt, self.cfg.boat, motor_off=True)
            self._gps_noise_step(dt)
            self.clock += dt
            return
        self._boot_events()
        self.missions.update(self.t)
        self._failsafe_check()
        if (
            self.mode == MODES["AUTO"]
            and self.mission_state == "running"
            and self.loiter_until is not None
            and self.t >= self.loiter_until
        ):
            self._advance()
        lat, lon = self.position()
        current = self.current_model.at(self.clock, lat, lon)
        heading, speed = self._command_motion(current)
        step_boat(self.boat, heading, speed or 0.0, current, dt, self.cfg.boat, motor_off=speed is None)
        self._gps_noise_step(dt)
        power_w = 5.0 + 40.0 * (self.boat.speed / 2.0) ** 2
        self.energy_wh += power_w * dt / 3600.0
        self.t += dt
        self.clock += dt
        self._boot_events()
        self._fence_check()
        self._telemetry()

    def _fence_check(self) -> None:
        """Rover's ``fence_check``: a new breach sends FENCE_STATUS at once and, while armed, takes ``FENCE_ACTION``
        (1: RTL, HOLD if refused; 2: HOLD; 0: report only)."""
        if not self.fence.check(self):
            return
        self.send(None, self.fence.status(self))
        action = int(self.p("FENCE_ACTION"))
        if not self.armed or action == 0:
            return
        if action != 1 or self.set_mode(MODES["RTL"]) != M.MAV_RESULT_ACCEPTED:
            self._enter_mode(MODES["HOLD"])

    def _failsafe_check(self) -> None:
        enable = int(self.p("FS_GCS_ENABLE"))
        if not enable or self.last_gcs_hb is None or not self.armed:
            if self.failsafe and (self.last_gcs_hb is not None and self.t - self.last_gcs_hb <= self.p("FS_TIMEOUT")):
                self.failsafe = False
            return
        lost = self.t - self.last_gcs_hb > self.p("FS_TIMEOUT")
        if lost and not self.failsafe:
            self.failsafe = True
            if self.mode == MODES["AUTO"] and enable == 2:
                self.text(None, M.MAV_SEVERITY_WARNING, "Failsafe - Continuing Auto Mode")
                return
            self.text(None, M.MAV_SEVERITY_WARNING, "GCS Failsafe")
            action = int(self.p("FS_ACTION"))
            if action in (1, 3):
                if self.set_mode(MODES["RTL"]) != M.MAV_RESULT_ACCEPTED:
                    self._enter_mode(MODES["HOLD"])
            elif action in (2, 4):
                self._enter_mode(MODES["HOLD"])
        elif not lost and self.failsafe:
            self.failsafe = False
            self.text(None, M.MAV_SEVERITY_INFO, "GCS Failsafe Cleared")

    # -- telemetry -------------------------------------------------------------------------------
    def _streams(self, link) -> LinkStreams:
        ls = self.streams.get(id(link))
        if ls is None:
            ls = LinkStreams(group_hz={}, overrides={}, next_due={})
            self.streams[id(link)] = ls
            self._apply_stream_params(link, ls)
        return ls

    def _apply_stream_params(self, link, ls: LinkStreams) -> None:
        n = getattr(link, "index", 0) + 1
        for g in STREAM_GROUPS:
            key = f"MAV{n}_{g}"
            ls.group_hz[g] = self.params.get(key, 1.0)

    def _refresh_stream_params(self) -> None:
        for ln in self._links():
            self._apply_stream_params(ln, self._streams(ln))

    def forget_link(self, link) -> None:
        self.streams.pop(id(link), None)

    def _interval(self, ls: LinkStreams, name: str) -> float:
        ov = ls.overrides.get(name)
        if ov is not None:
            return ov
        if name in FIXED_STREAMS:
            return 1.0
        for g, names in STREAM_GROUPS.items():
            if name in names:
                hz = ls.group_hz.get(g, 1.0)
                return 1.0 / hz if hz > 0 else -1.0
        return -1.0

    STREAMED = (
        "HEARTBEAT",
        "SYS_STATUS",
        "GPS_RAW_INT",
        "GLOBAL_POSITION_INT",
        "ATTITUDE",
        "VFR_HUD",
        "MISSION_CURRENT",
        "EKF_STATUS_REPORT",
        "BATTERY_STATUS",
        "SYSTEM_TIME",
        "TIMESYNC",
        "NAV_CONTROLLER_OUTPUT",
        "LOCAL_POSITION_NED",
        "POWER_STATUS",
        "MEMINFO",
        "FENCE_STATUS",
    )

    def _telemetry(self) -> None:
        cache: dict[str, object] = {}
        t = self.t
        for ln in self._links():
            ls = self._streams(ln)
            names = set(self.STREAMED) | set(ls.overrides)
            for name in sorted(names):
                iv = self._interval(ls, name)
                if iv <= 0:
                    continue
                due = ls.next_due.get(name)
                if due is None:
                    due = ls.next_due[name] = t
                if t + 1e-9 >= due:
                    if name not in cache:
                        cache[name] = self._make(name)
                    if cache[name] is not None:
                        self._send_raw(ln, cache[name])
                    ls.next_due[name] = due + iv if due + iv > t else t + iv
        self._current_sensor()

    def _current_sensor(self) -> None:
        rate = self.cfg.current_rate_hz
        if rate <= 0 or not self.gps_ok or self.t + 1e-9 < self._next_sample:
            return
        self._next_sample = (
            max(self._next_sample + 1.0 / rate, self.t) if self._next_sample > 0 else self.t + 1.0 / rate
        )
        lat, lon = self.position()
        uv = self.current_model.measure(self.clock, lat, lon)  # measured where the boat really is
        if uv is None:
            return  # on land / off the field: the sensor has nothing to say (like the Lua sensor)
        u, v = uv
        sd = self.cfg.current_noise_std
        if sd > 0:
            u, v = u + self._rng.gauss(0.0, sd), v + self._rng.gauss(0.0, sd)
        # one instant: the position fix and both readings carry the same time_boot_ms
        gpi = telemetry.global_position_int(self)
        self.send(None, gpi)
        self.send(None, M.MAVLink_named_value_float_message(gpi.time_boot_ms, b"CUR_U", float(u)))
        self.send(None, M.MAVLink_named_value_float_message(gpi.time_boot_ms, b"CUR_V", float(v)))
        self.samples_sent += 1

    def _set_message_interval(self, link, msgid: int, interval_us: float) -> int:
        name = _msg_name(msgid)
        if name is None or name in NOT_STREAMS:
            # ArduPilot has no ap_message for it (TIMESYNC is answered per request, not streamed)
            self.text(link, M.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({int(msgid)})")
            return M.MAV_RESULT_DENIED
        ls = self._streams(link)
        if interval_us < 0:
            ls.overrides[name] = -1.0
        elif interval_us == 0:
            ls.overrides.pop(name, None)
            if name not in self.STREAMED:
                return M.MAV_RESULT_ACCEPTED
        else:
            if self._make(name) is None and name not in self.STREAMED:
                return M.MAV_RESULT_DENIED
            ls.overrides[name] = interval_us / 1e6
        ls.next_due[name] = self.t
        return M.MAV_RESULT_ACCEPTED

    def _send_one(self, link, msgid: int, req, send: bool = False) -> bool:
        name = _msg_name(msgid)
        if name is None or (name == "HOME_POSITION" and not self.home_set):
            return False
        m = self._make(name)
        if m is None:
            return False
        if send:
            self.send(link, m)
        return True

    def _make(self, name: str):
        """Build one telemetry message by name (None if we do not produce it): :func:`vehicle_sim.telemetry.build`."""
        return telemetry.build(self, name)

    def _param_value(self, name: str, index: int | None = None):
        idx = self._param_names.index(name) if index is None else index
        return M.MAVLink_param_value_message(
            name.encode(), float(self.params[name]), DEFAULT_PARAMS[name][1], len(self._param_names), idx
        )


def _pname(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


def _msg_name(msgid: int) -> str | None:
    cls = M.mavlink_map.get(int(msgid))
    return cls.msgname if cls is not None else None  # type: ignore[attr-defined]
