"""Vehicle control for an ArduPilot Rover boat: readiness, modes, arming, mission progress.

Written to shared/ARDUPILOT_ROVER.md. Every command checks its COMMAND_ACK and a
refusal raises :class:`CommandRejected` carrying the STATUSTEXT that came with
it ("Arm: System not initialised", "Flight mode change failed", ...). A mode
change counts only once the vehicle's HEARTBEAT shows the new custom mode.

Parameters (PARAM_SET / PARAM_REQUEST_READ) count only once the vehicle's PARAM_VALUE
echo carries the value. The waypoint acceptance radius of a Rover is its WP_RADIUS
parameter (a NAV_WAYPOINT's param2 is dropped by the firmware): :meth:`Vehicle.set_wp_radius`
sets it, remembering the vehicle's own value, and :meth:`Vehicle.restore_params` puts
back whatever this object changed.
"""

from __future__ import annotations

import logging
import threading

from passt_mav.errors import CommandRejected, LinkTimeout, MavlinkError, UserError, VehicleNotReady
from passt_mav.mavlink.clock import Timeout, wall_seconds
from passt_mav.mavlink.link import Link, mavlink2
from passt_mav.mavlink.mission_client import MissionClient
from passt_mav.mavlink.modes import ROVER_MODE_NAMES, ROVER_MODES  # (re-exported: __all__)

__all__ = ["Vehicle", "ROVER_MODES", "ROVER_MODE_NAMES", "mode_number", "MissionProgress", "PARAM_TYPES"]

log = logging.getLogger(__name__)
M = mavlink2

#: MAV_PARAM_TYPE of the parameters this module sets (ArduPilot keeps WP_RADIUS/WP_SPEED as float)
PARAM_TYPES = {"WP_RADIUS": M.MAV_PARAM_TYPE_REAL32, "WP_SPEED": M.MAV_PARAM_TYPE_REAL32}

#: EKF_STATUS_REPORT flags: absolute horizontal position; constant-position (not yet navigating) mode
EKF_POS_HORIZ_ABS = 16
EKF_CONST_POS_MODE = 128
#: STATUSTEXT fragments of a vehicle that will accept arming a little later
_NOT_YET = ("not initialised", "not initialized", "initialising", "accels inconsistent", "waiting for")


def _param_name(raw) -> str:
    """PARAM_VALUE.param_id as text (pymavlink gives str or bytes, NUL padded)."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return raw.split("\x00", 1)[0]


def mode_number(mode: str | int) -> int:
    """Rover custom mode number from a name (case-insensitive) or a number; UserError if unknown."""
    if isinstance(mode, int) or (isinstance(mode, str) and mode.strip().isdigit()):
        num = int(mode)
        if num not in ROVER_MODE_NAMES:
            raise UserError(f"unknown Rover mode number {num}; valid: {sorted(ROVER_MODE_NAMES)}")
        return num
    key = str(mode).strip().upper()
    if key not in ROVER_MODES:
        raise UserError(f"unknown Rover mode {mode!r}; valid: {', '.join(ROVER_MODES)}")
    return ROVER_MODES[key]


class MissionProgress:
    """Mission progress seen since :meth:`Vehicle.start_mission` (updated by the reader thread).

    ``current``: MISSION_CURRENT.seq; ``total``: MISSION_CURRENT.total (excludes home);
    ``state``: mission_state (1 none, 2 not started, 3 active, 5 complete, 0 unknown);
    ``reached``: seqs of MISSION_ITEM_REACHED in arrival order.
    """

    def __init__(self):
        self.current = 0
        self.total = 0
        self.state = 0
        self.reached: list[int] = []
        self.changed = threading.Condition()

    def on_message(self, m) -> None:
        with self.changed:
            if m.get_type() == "MISSION_CURRENT":
                self.current, self.total = int(m.seq), int(getattr(m, "total", 0))
                self.state = int(getattr(m, "mission_state", 0))
            elif m.get_type() == "MISSION_ITEM_REACHED" and (not self.reached or self.reached[-1] != int(m.seq)):
                self.reached.append(int(m.seq))
            self.changed.notify_all()


class Vehicle:
    """Commands and state of one Rover boat over a connected :class:`Link`.

    Args:
        link: connected link.
        mission: mission client (default: one on ``link``).
        retry_delay_s: pause between arming attempts while the vehicle initialises.
        show_progress: show :meth:`wait_ready`'s wait on stderr once it has to wait (:mod:`passt_mav.progress`:
            a bar on a terminal, a plain line every 5 s otherwise).
    """

    #: DO_CHANGE_SPEED commands sent while the vehicle answers FAILED (:meth:`set_speed`)
    SPEED_TRIES = 10

    def __init__(
        self,
        link: Link,
        mission: MissionClient | None = None,
        *,
        retry_delay_s: float = 1.0,
        show_progress: bool = False,
    ):
        self.link = link
        self.show_progress = bool(show_progress)
        self.mission = mission or MissionClient(link)
        self.retry_delay_s = retry_delay_s
        self.progress = MissionProgress()
        #: the vehicle flies a mission this run did not upload, and the run refused to start: its clean-up sends
        #: nothing (:meth:`keep_station_if_auto`)
        self.hands_off = False
        self._listening = False
        #: name -> the vehicle's value before this object first changed it (see restore_params)
        self.changed_params: dict[str, float] = {}
        #: the mode :meth:`keep_station` waits in: ``LOITER`` keeps a boat on its spot (inside LOIT_RADIUS);
        #: ``HOLD`` stops the motor and centres the steering, so a boat in HOLD drifts with the current
        #: (Rover's mode_hold.cpp; shared/ARDUPILOT_ROVER.md). Set from the mission's ``vehicle.wait_mode``.
        self.wait_mode = "HOLD"

    # -- state ---------------------------------------------------------------------------------
    @property
    def mode(self) -> int | None:
        hb = self.link.latest("HEARTBEAT")
        return None if hb is None else int(hb.custom_mode)

    @property
    def mode_name(self) -> str | None:
        m = self.mode
        return None if m is None else ROVER_MODE_NAMES.get(m, str(m))

    @property
    def armed(self) -> bool:
        hb = self.link.latest("HEARTBEAT")
        return bool(hb is not None and hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)

    def position(self) -> tuple[float, float] | None:
        """Last GLOBAL_POSITION_INT (lat, lon) degrees, None before a GPS fix (lat/lon 0)."""
        g = self.link.latest("GLOBAL_POSITION_INT")
        if g is None or (g.lat == 0 and g.lon == 0):
            return None
        return g.lat / 1e7, g.lon / 1e7

    def _ready_reason(self) -> str:
        ekf = self.link.latest("EKF_STATUS_REPORT")
        if ekf is None:
            return "no EKF_STATUS_REPORT yet"
        if not ekf.flags & EKF_POS_HORIZ_ABS:
            return f"EKF has no absolute horizontal position (flags {ekf.flags})"
        if ekf.flags & EKF_CONST_POS_MODE:
            return f"EKF in constant-position mode (flags {ekf.flags})"
        if self.position() is None:
            return "GLOBAL_POSITION_INT has no fix (lat/lon 0)"
        return ""

    def wait_ready(self, timeout: float = 60.0) -> None:
        """Wait until EKF_STATUS_REPORT has flags & 16 set and & 128 clear and
        GLOBAL_POSITION_INT is non-zero; raises :class:`VehicleNotReady` naming what is missing."""
        from passt_mav.progress import progress

        deadline = Timeout(self.link.clock, timeout)
        bar = None  # shown only once there is something to wait for
        with self.link.subscribe(("EKF_STATUS_REPORT", "GLOBAL_POSITION_INT")) as sub:
            try:
                while reason := self._ready_reason():
                    if deadline.expired():
                        raise VehicleNotReady(
                            f"vehicle not ready after {timeout:.1f} s: {reason}"
                            + (" (link lost)" if self.link.lost else "")
                        )
                    if bar is None:
                        bar = progress(
                            None,
                            f"waiting for the vehicle (up to {timeout:.0f} s)",
                            "s",
                            quiet=not self.show_progress,
                            every_s=5.0,
                        )
                    bar.note(reason)
                    bar.tick()
                    sub.get(min(deadline.left(), 1.0))
            finally:
                if bar is not None:
                    bar.close("ready" if not self._ready_reason() else "gave up")

    # -- modes ---------------------------------------------------------------------------------
    def _wait_heartbeat(self, cond, what: str, timeout: float | None) -> None:
        timeout = max(3 * self.link.config.heartbeat_period_s, self.link.reply_timeout) if timeout is None else timeout
        # Subscribe before looking at the latest HEARTBEAT: one that lands between the two
        # would otherwise be missed and the wait would hang on for the next one.
        with self.link.subscribe("HEARTBEAT") as sub:
            hb = self.link.latest("HEARTBEAT")
            if hb is not None and cond(hb):
                return
            left = Timeout(self.link.clock, timeout).left
            while (m := sub.get(left())) is not None:
                if m.get_srcSystem() == self.link.target_system and cond(m):
                    return
        raise LinkTimeout(
            f"vehicle heartbeat never showed {what} within {timeout:.1f} s" + (" (link lost)" if self.link.lost else "")
        )

    def set_mode(self, mode: str | int, *, timeout: float | None = None) -> int:
        """MAV_CMD_DO_SET_MODE (176, param1 = 1 custom) and wait until the HEARTBEAT shows it.

        Returns the mode number. Raises CommandRejected (with the vehicle's STATUSTEXT),
        LinkTimeout, or UserError for an unknown mode name.
        """
        num = mode_number(mode)
        self.link.command_long(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, num)
        self._wait_heartbeat(lambda m: m.custom_mode == num, f"mode {ROVER_MODE_NAMES[num]}", timeout)
        return num

    def hold(self) -> None:
        """HOLD: on a boat the motor stops and the boat drifts with the current (see :meth:`keep_station`)."""
        self.set_mode("HOLD")

    def keep_station(self) -> str:
        """Wait where the boat is, in :attr:`wait_mode` (LOITER keeps station; HOLD drifts). A LOITER the vehicle
        refuses (no absolute position yet, a mode the firmware lacks) falls back to HOLD, logged. Returns the
        mode name the vehicle is in now."""
        mode = self.wait_mode
        if mode != "HOLD":
            try:
                self.set_mode(mode)
                return mode
            except CommandRejected as exc:
                log.warning("the vehicle refused %s (%s); HOLD instead: the boat drifts with the current", mode, exc)
        self.set_mode("HOLD")
        return "HOLD"

    def set_speed(self, speed_mps: float, *, speedup: float = 1.0) -> None:
        """MAV_CMD_DO_CHANGE_SPEED: ``speed_mps`` m/s (Rover holds it over ground along the bow) for the mission
        being flown. Rover resets its speed to WP_SPEED whenever AUTO is entered, and on a boat it runs a mission's
        DO_CHANGE_SPEED placed before the first waypoint in AUTO's loiter submode, where it is lost (Rover 4.7
        SITL: tests/test_sitl_current.py); right after AUTO is entered the command may meet that submode too and
        be refused (FAILED): it is sent again every 0.2 s of vehicle time (``speedup``: vehicle s per wall s), up
        to :attr:`SPEED_TRIES` times. Raises CommandRejected or LinkTimeout."""
        for attempt in range(self.SPEED_TRIES):
            try:
                self.link.command_long(M.MAV_CMD_DO_CHANGE_SPEED, 1, float(speed_mps), -1)
                return
            except CommandRejected as exc:
                if exc.result != M.MAV_RESULT_FAILED or attempt == self.SPEED_TRIES - 1:
                    raise
                self.link.idle(wall_seconds(0.2, speedup))

    def keep_station_if_auto(self, *, always: bool = False) -> None:
        """:meth:`keep_station` if the vehicle flies a mission (AUTO; ``always``: whatever its mode); a failure is
        logged, never raised (the clean-up of a run that stops). Nothing is sent while :attr:`hands_off` (the
        vehicle flies another controller's mission: a run that refused to start leaves it alone)."""
        if self.hands_off:
            return
        try:
            if always or self.mode == ROVER_MODES["AUTO"]:
                self.keep_station()
        except MavlinkError as exc:
            log.warning("could not stop the boat (%s): %s", self.wait_mode, exc)

    def request_mode(self, mode: str | int) -> None:
        """Send MAV_CMD_DO_SET_MODE once, without waiting for its ACK or the HEARTBEAT (:meth:`set_mode`
        confirms it): a mark in the telemetry log at the moment it is sent."""
        num = mode_number(mode)
        link = self.link
        link.send(
            M.MAVLink_command_long_message(
                link.target_system,
                link.target_component,
                M.MAV_CMD_DO_SET_MODE,
                0,
                M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                num,
                0,
                0,
                0,
                0,
                0,
            )
        )

    # -- arming --------------------------------------------------------------------------------
    def arm(self, *, timeout: float = 60.0, force: bool = False, attempts: int = 3) -> None:
        """Arm; while the vehicle refuses because it is still initialising ("Arm: System not
        initialised", ...) retry every ``retry_delay_s`` until ``timeout``. Other refusals
        raise CommandRejected at once. Confirmed by the HEARTBEAT armed flag.

        An accepted arm whose next HEARTBEAT already says disarmed is sent again, up to
        ``attempts`` times: ArduPilot arms, then disarms within the same tick when its main
        loop stalls for 0.2 s of its time (Rover's CPU failsafe, "Throttle armed" followed at
        once by "Throttle disarmed"); on SITL sped up 20x on a loaded machine the stall of
        opening the DataFlash log at arming is enough. We armed it a moment ago ourselves, so
        arming again overrides no one.
        """
        end = self.link.clock.now() + timeout
        default = max(3 * self.link.config.heartbeat_period_s, self.link.reply_timeout)
        armed = M.MAV_MODE_FLAG_SAFETY_ARMED
        for attempt in range(1, attempts + 1):
            self._arm_command(force, end)
            # the first HEARTBEAT after the ACK was made after arming (one ordered stream);
            # it may lag on a loaded machine: wait within what is left of ``timeout``
            wait = max(default, end - self.link.clock.now())
            hb = self._next_heartbeat(wait)
            if hb is None:
                raise LinkTimeout(
                    f"vehicle heartbeat never showed armed within {wait:.1f} s"
                    + (" (link lost)" if self.link.lost else "")
                )
            if hb.base_mode & armed:
                return
            log.warning(
                "the vehicle accepted arming but its heartbeat says disarmed (attempt %d/%d)", attempt, attempts
            )
        raise CommandRejected(
            M.MAV_CMD_COMPONENT_ARM_DISARM,
            M.MAV_RESULT_FAILED,
            f"the vehicle accepted arming {attempts} times but disarmed again each time "
            "(an autopilot failsafe; see its messages)",
        )

    def _arm_command(self, force: bool, end: float) -> None:
        """MAV_CMD_COMPONENT_ARM_DISARM(1) until accepted; transient refusals retried until ``end``."""
        while True:
            try:
                self.link.command_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 2989 if force else 0)
                return
            except CommandRejected as exc:
                transient = (
                    any(s in exc.text.lower() for s in _NOT_YET) or exc.result == M.MAV_RESULT_TEMPORARILY_REJECTED
                )
                if not transient or self.link.clock.now() + self.retry_delay_s > end:
                    raise
                log.info("arming refused (%s); retrying", exc.text)
                self.link.clock.sleep(self.retry_delay_s)

    def _next_heartbeat(self, timeout: float):
        """The vehicle's next HEARTBEAT (arriving from now on) within ``timeout`` s, or None."""
        with self.link.subscribe("HEARTBEAT") as sub:
            left = Timeout(self.link.clock, timeout).left
            while (m := sub.get(left())) is not None:
                if m.get_srcSystem() == self.link.target_system:
                    return m
        return None

    def disarm(self, *, force: bool = False) -> None:
        self.link.command_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196 if force else 0)
        self._wait_heartbeat(lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, "disarmed", None)

    # -- parameters ------------------------------------------------------------------------------
    def _param_exchange(self, name: str, send, accept, what: str, timeout: float | None) -> float:
        """Send (and resend on silence) until a PARAM_VALUE for ``name`` satisfies ``accept``."""
        link = self.link
        per_try = link.reply_timeout if timeout is None else timeout / (link.config.retries + 1)
        last = None
        with link.subscribe("PARAM_VALUE") as sub:
            for _ in range(link.config.retries + 1):
                send()
                left = Timeout(link.clock, per_try).left
                while (m := sub.get(left())) is not None:
                    if m.get_srcSystem() != link.target_system or _param_name(m.param_id) != name:
                        continue
                    last = float(m.param_value)
                    if accept(last):
                        return last
        if last is not None:
            raise CommandRejected(
                f"PARAM_SET {name}", M.MAV_RESULT_DENIED, f"{what}: the vehicle keeps {name} = {last:g}"
            )
        raise LinkTimeout(
            f"{what}: no PARAM_VALUE for {name} (unknown parameter on this firmware?)"
            + (" (link lost)" if link.lost else "")
        )

    def get_param(self, name: str, *, timeout: float | None = None) -> float:
        """Value of parameter ``name`` (PARAM_REQUEST_READ -> PARAM_VALUE). LinkTimeout if the
        vehicle never answers (ArduPilot stays silent for names it does not have)."""
        link = self.link
        return self._param_exchange(
            name,
            lambda: link.send(
                M.MAVLink_param_request_read_message(link.target_system, link.target_component, name.encode(), -1)
            ),
            lambda v: True,
            f"reading {name}",
            timeout,
        )

    def set_param(self, name: str, value: float, *, timeout: float | None = None, tol: float = 1e-4) -> float:
        """PARAM_SET ``name`` = ``value``, confirmed by the PARAM_VALUE echo (float32, ``tol``
        relative). Returns the echoed value. The first change of each name remembers the
        vehicle's previous value in :attr:`changed_params` for :meth:`restore_params`.

        Raises CommandRejected when the vehicle echoes another value, LinkTimeout when it
        never echoes (ArduPilot ignores unknown names).
        """
        value = float(value)
        if name not in self.changed_params:
            self.changed_params[name] = self.get_param(name, timeout=timeout)
        link = self.link
        ptype = PARAM_TYPES.get(name, M.MAV_PARAM_TYPE_REAL32)
        return self._param_exchange(
            name,
            lambda: link.send(
                M.MAVLink_param_set_message(link.target_system, link.target_component, name.encode(), value, ptype)
            ),
            lambda v: abs(v - value) <= tol * max(1.0, abs(value)),
            f"setting {name} to {value:g}",
            timeout,
        )

    def set_wp_radius(self, radius_m: float) -> float:
        """Waypoint acceptance radius (m) through WP_RADIUS (Rover ignores a waypoint's param2).
        Only sent when the vehicle holds another value; returns the vehicle's value now."""
        if radius_m <= 0:
            raise UserError(f"waypoint radius must be > 0 m, got {radius_m:g}")
        current = self.get_param("WP_RADIUS")
        if abs(current - radius_m) <= 1e-4 * max(1.0, radius_m):
            return current
        return self.set_param("WP_RADIUS", radius_m)

    def restore_params(self) -> dict[str, float]:
        """Set every parameter changed through :meth:`set_param` back to the vehicle's own
        value; returns what was restored. Errors are logged, not raised (used on the way out)."""
        done = {}
        for name, old in list(self.changed_params.items()):
            try:
                self.set_param(name, old)
                done[name] = old
                del self.changed_params[name]
            except Exception as exc:  # noqa: BLE001 - a failed restore must not hide the run's own outcome
                log.warning("could not restore %s to %g: %s", name, old, exc)
        return done

    # -- missions --------------------------------------------------------------------------------
    def _listen(self) -> None:
        if not self._listening:
            self.link.add_listener(self.progress.on_message, ("MISSION_CURRENT", "MISSION_ITEM_REACHED"))
            self._listening = True

    def start_mission(self, *, use_mission_start: bool = False) -> None:
        """Enter AUTO (DO_SET_MODE), or MAV_CMD_MISSION_START (300, first = last = 0); confirmed by
        the HEARTBEAT. Progress is tracked in :attr:`progress` from here on."""
        self._listen()
        with self.progress.changed:
            self.progress.reached.clear()
            self.progress.state = 0
        if use_mission_start:
            self.link.command_long(M.MAV_CMD_MISSION_START, 0, 0)
            self._wait_heartbeat(lambda m: m.custom_mode == ROVER_MODES["AUTO"], "mode AUTO", None)
        else:
            self.set_mode("AUTO")

    def wait_mission_complete(
        self, n_items: int, *, timeout: float = 3600.0, hold: bool = True, on_progress=None
    ) -> MissionProgress:
        """Wait until MISSION_CURRENT says complete (mission_state 5 with ``total == n_items``) or
        item ``n_items`` is reached (``n_items`` excludes home); then switch to HOLD (a boat
        otherwise stays armed in AUTO, loitering). ``on_progress(progress)`` on each update.

        Raises LinkTimeout if not complete within ``timeout`` seconds.
        """
        self._listen()
        p = self.progress
        end = self.link.clock.now() + timeout
        with p.changed:
            while not ((p.state == M.MISSION_STATE_COMPLETE and p.total == n_items) or n_items in p.reached):
                left = end - self.link.clock.now()
                if left <= 0:
                    raise LinkTimeout(
                        f"mission not complete after {timeout:.0f} s (item {p.current}/{p.total}, "
                        f"reached {p.reached[-5:]})" + (" (link lost)" if self.link.lost else "")
                    )
                if self.link.lockstep is not None:  # the vehicle's clock runs only while we wait: one step
                    p.changed.release()
                    try:
                        self.link.idle(0.0)
                    finally:
                        p.changed.acquire()
                else:
                    p.changed.wait(min(left, 0.5))
                if on_progress is not None:
                    on_progress(p)
        if hold:
            self.keep_station()
        return p
