"""The mission's safety budget (mission key ``budget``; :class:`~passt_mav.mission.config.BudgetConfig`).

:class:`SafetyBudget` watches one boat while its legs fly: the vehicle seconds spent flying legs and the metres
moved meanwhile (both counted per controller session), and the battery's remaining charge (SYS_STATUS and
BATTERY_STATUS ``battery_remaining``, %; the lower of the two when both are known, -1 = unknown is ignored).
:meth:`VehicleSession.fly <passt_mav.vehicle.session.VehicleSession.fly>` asks it once a turn
(:meth:`SafetyBudget.spent`); once a limit is reached the leg is cut there (``"budget"``: HOLD, its samples
absorbed, the leg complete), and the controller sends the boat to ``on_spent`` (RTL or HOLD) and ends the run
cleanly (status ``ended``; ``--resume`` continues, its budget counted afresh).

Before a leg is uploaded the controller fits it to what is left (:meth:`SafetyBudget.left`, :func:`waypoints_that_fit`):
its distance is estimated along its waypoints from the boat's position (geodesic, WGS84) and its duration at the
mission's speed (no current); a leg that would overrun ``max_distance_m`` or ``max_time_s`` keeps only the waypoints
that fit. With ``on_spent: rtl`` the way home (straight, from the last waypoint kept to the vehicle's home, at the
same speed) must fit too, so the last leg leaves the range to come back. The battery is not forecast (there is no
consumption model): the reserve is only watched in flight. The first report at or below the reserve is kept
as it arrives (the link's reader thread), so the cut is judged at the charge that crossed it, not at a lower one
reported by the time the controller's next turn comes.

The distance is the sum of geodesic steps between successive GLOBAL_POSITION_INT fixes (deg -> m, WGS84)
while a leg flies; the time is the vehicle's uptime (``time_boot_ms``) over the same spans, so a reboot's
restart of that clock does not count backwards.
"""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["SafetyBudget", "battery_remaining", "waypoints_that_fit"]


def battery_remaining(link) -> float | None:
    """The battery's remaining charge (%) the vehicle reports last (SYS_STATUS, BATTERY_STATUS: the lower of
    those known), None when neither is known."""
    vals = []
    for typ in ("SYS_STATUS", "BATTERY_STATUS"):
        m = link.latest(typ)
        pct = None if m is None else getattr(m, "battery_remaining", -1)
        if pct is not None and 0 <= pct <= 100:
            vals.append(float(pct))
    return min(vals) if vals else None


def waypoints_that_fit(
    to_wp_m: np.ndarray, back_m: np.ndarray, left_m: float | None, left_s: float | None, speed_mps: float
) -> int:
    """How many of a leg's first waypoints fit the budget left: the largest ``k`` such that flying to waypoint
    ``k`` (``to_wp_m[k - 1]``: metres from the boat along the waypoints) and then ``back_m[k - 1]`` metres home
    (0 without a return) is at most ``left_m`` metres and, at ``speed_mps`` (m/s), ``left_s`` seconds (each None:
    no limit). 0 when not even the first fits."""
    need = np.asarray(to_wp_m, float) + np.asarray(back_m, float)
    fits = np.ones(need.shape, bool)
    if left_m is not None:
        fits &= need <= left_m
    if left_s is not None:
        fits &= need / float(speed_mps) <= left_s
    ok = np.flatnonzero(fits)
    return int(ok[-1]) + 1 if ok.size else 0


class SafetyBudget:
    """One boat's budget on ``link`` from ``config`` (:class:`~passt_mav.mission.config.BudgetConfig`).

    :meth:`start_leg` / :meth:`end_leg` bracket each leg's flight; :meth:`spent` says why the budget is spent
    (one line), or None. ``reason`` keeps the first such line.
    """

    def __init__(self, link, config):
        self.link, self.config = link, config
        self.flown_s = 0.0  # vehicle seconds of legs ended in this session
        self.distance_m = 0.0
        self.reason: str | None = None
        self._lock = threading.Lock()
        self._leg_t0: float | None = None  # vehicle uptime at the start of the leg in flight
        self._last_fix: tuple[float, float] | None = None
        self._listening = False
        #: the first charge (%) reported at or below ``battery_reserve_pct`` since :meth:`request_battery` (set by
        #: the reader thread, so the cut is judged at the report that crossed the reserve, in the vehicle's time,
        #: however late the controller's next turn comes on a busy machine)
        self._battery_low: float | None = None
        self._battery_listening = False

    @property
    def watched(self) -> bool:
        """Any limit is set."""
        c = self.config
        return any(x is not None for x in (c.max_time_s, c.max_distance_m, c.battery_reserve_pct))

    def left(self) -> tuple[float | None, float | None]:
        """What is left of ``max_distance_m`` (m) and ``max_time_s`` (vehicle s) in this session, each None when
        unset (never below 0)."""
        c = self.config
        with self._lock:
            t, d = self._time_s(), self.distance_m
        return (
            None if c.max_distance_m is None else max(0.0, c.max_distance_m - d),
            None if c.max_time_s is None else max(0.0, c.max_time_s - t),
        )

    def home(self) -> tuple[float, float] | None:
        """The vehicle's home (lat, lon deg): its last HOME_POSITION, else asked for once (MAV_CMD_REQUEST_MESSAGE);
        None when it has none (a vehicle without a home, or no answer)."""
        from passt_mav.errors import CommandRejected, LinkTimeout
        from passt_mav.mavlink.link import mavlink2 as M

        m = self.link.latest("HOME_POSITION")
        if m is None:
            with self.link.subscribe("HOME_POSITION") as sub:
                try:  # (ArduPilot acknowledges first, then sends the message)
                    self.link.command_long(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION, retries=1)
                    m = sub.get(self.link.reply_timeout)
                except (CommandRejected, LinkTimeout):
                    m = None
        return None if m is None else (m.latitude / 1e7, m.longitude / 1e7)

    def request_battery(self) -> None:
        """Ask the vehicle for BATTERY_STATUS at 1 Hz of its time (a fast simulator's lean streams leave it off),
        the other streams left as they are, and again whenever the link's streams are requested again (after an
        autopilot reboot, a reconnect: :meth:`~passt_mav.mavlink.Link.keep_stream`); a refusal is logged (SYS_STATUS
        may still carry the charge). The charge last reported before is forgotten."""
        if self.config.battery_reserve_pct is None:
            return
        # a charge reported before this session (a battery swapped meanwhile) must not end its first leg
        self.link.forget("SYS_STATUS", "BATTERY_STATUS")
        with self._lock:
            self._battery_low = None
        if not self._battery_listening:
            self.link.add_listener(self._on_battery, ("SYS_STATUS", "BATTERY_STATUS"))
            self._battery_listening = True
        self.link.keep_stream("BATTERY_STATUS", 1.0)

    def _on_battery(self, m) -> None:
        """From the reader thread: one SYS_STATUS or BATTERY_STATUS; the first charge (%) at or below the reserve
        is kept (-1, unknown, is not a charge)."""
        pct = getattr(m, "battery_remaining", -1)
        if pct is not None and 0 <= pct <= self.config.battery_reserve_pct:
            with self._lock:
                if self._battery_low is None:
                    self._battery_low = float(pct)

    def _on_fix(self, m) -> None:
        """From the reader thread: one GLOBAL_POSITION_INT; the step from the last fix is added while a leg flies."""
        import geo

        if m.lat == 0 and m.lon == 0:
            return  # no GPS fix yet
        p = (m.lat / 1e7, m.lon / 1e7)
        with self._lock:
            if self._leg_t0 is not None and self._last_fix is not None:
                self.distance_m += float(geo.geodesic_distance_m(self._last_fix[0], self._last_fix[1], p[0], p[1]))
            self._last_fix = p

    def start_leg(self) -> None:
        """A leg starts flying (AUTO): count its time and distance from now."""
        if not self.watched:
            return
        if not self._listening and self.config.max_distance_m is not None:
            self.link.add_listener(self._on_fix, "GLOBAL_POSITION_INT")
            self._listening = True
        with self._lock:
            self._leg_t0 = self.link.vehicle_uptime_s()
            self._last_fix = None

    def end_leg(self) -> None:
        """The leg in flight ended (complete, cut, or stopped): its time is added."""
        with self._lock:
            self.flown_s = self._time_s()
            self._leg_t0 = None

    def close(self) -> None:
        """Stop listening to the link."""
        if self._listening:
            self.link.remove_listener(self._on_fix)
            self._listening = False
        if self._battery_listening:
            self.link.remove_listener(self._on_battery)
            self._battery_listening = False

    def _time_s(self) -> float:
        up = self.link.vehicle_uptime_s()
        if self._leg_t0 is None or up is None or up < self._leg_t0:  # (a reboot restarted the clock)
            return self.flown_s
        return self.flown_s + (up - self._leg_t0)

    def spent(self) -> str | None:
        """Why the budget is spent now (time, distance, battery; one line), or None. Remembered in ``reason``."""
        if self.reason is not None or not self.watched:
            return self.reason
        c = self.config
        with self._lock:
            t, d = self._time_s(), self.distance_m
        why = None
        if c.max_time_s is not None and t >= c.max_time_s:
            why = f"time: {t:.0f} s of legs flown >= budget.max_time_s {c.max_time_s:g} s"
        elif c.max_distance_m is not None and d >= c.max_distance_m:
            why = f"distance: {d:.0f} m moved >= budget.max_distance_m {c.max_distance_m:g} m"
        elif c.battery_reserve_pct is not None:
            with self._lock:
                low = self._battery_low
            pct = low if low is not None else battery_remaining(self.link)
            if pct is not None and pct <= c.battery_reserve_pct:
                why = f"battery: {pct:.0f} % remaining <= budget.battery_reserve_pct {c.battery_reserve_pct:g} %"
        self.reason = why
        return why

    def record(self) -> dict:
        """The budget's figures now (summary.json ``budget``)."""
        with self._lock:
            t = self._time_s()
        return {
            "flown_s": round(t, 1),
            "distance_m": round(self.distance_m, 1),
            "battery_pct": battery_remaining(self.link),
            "spent": self.reason,
        }
