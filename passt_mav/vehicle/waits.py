"""The boat's waits, measured: where it was when the controller made it wait, and where it was when the wait ended.

A boat waits whenever the controller is not flying a leg: between legs (absorbing the samples, planning, an
operator's approval), while paused, after a reboot with ``on_reboot: hold``. It waits in the vehicle's
:attr:`~passt_mav.mavlink.Vehicle.wait_mode` (mission key ``vehicle.wait_mode``): LOITER keeps station, HOLD
stops the motor and the boat drifts with the current. Either way the wait's drift is recorded, so a run in HOLD
says how far the current took the boat, and a LOITER that does not hold (a current stronger than the boat)
shows.

Units: drift in metres (geodesic, WGS84), durations in vehicle seconds (the vehicle's time since boot); a record's
``uptime_s`` is ``[begin, end]`` on that clock (s since boot, None where unknown), so a wait can be placed among the
telemetry log's ``time_boot_ms``.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["WaitLog", "DRIFT_WARN_FACTOR"]

#: a wait whose drift exceeds this many waypoint radii (and 10 m) is said on the console
DRIFT_WARN_FACTOR = 2.0


@dataclass
class _Open:
    kind: str
    leg: int
    mode: str
    latlon: tuple[float, float] | None
    uptime_s: float | None


class WaitLog:
    """Begin and end the boat's waits; each ended wait is a record in :attr:`records`.

    Args:
        vehicle: :class:`~passt_mav.mavlink.Vehicle` (its position and :attr:`wait_mode`).
        link: its :class:`~passt_mav.mavlink.Link` (the vehicle's time since boot).
        say: one line on the console (a drift past :data:`DRIFT_WARN_FACTOR` x ``wp_radius_m``).
        wp_radius_m: the mission's waypoint radius (m).
    """

    def __init__(self, vehicle, link, say, wp_radius_m: float = 2.0):
        self.vehicle, self.link, self.say = vehicle, link, say
        self.wp_radius_m = float(wp_radius_m)
        self.records: list[dict] = []
        self._open: _Open | None = None
        #: how the run left the boat (:meth:`finish`; summary.json ``end``), None before
        self.end_state: dict | None = None

    @property
    def waiting(self) -> bool:
        """A wait is open."""
        return self._open is not None

    def begin(self, kind: str, leg: int) -> None:
        """The boat starts waiting (``kind``: ``between legs``, ``pause``, ``approval``, ``end``) before or in leg
        ``leg`` (0-based). A wait already open goes on (the first reason counts)."""
        if self._open is not None:
            return
        # the mode the vehicle reports (a refused LOITER left it in HOLD), else the one it was asked for
        mode = self.vehicle.mode_name or self.vehicle.wait_mode
        self._open = _Open(kind, int(leg), str(mode), self._where(), self.link.vehicle_uptime_s())

    def end(self) -> dict | None:
        """The wait ends (the boat flies again, or the run ends): its record, or None when none was open."""
        w, self._open = self._open, None
        if w is None:
            return None
        now, up = self._where(), self.link.vehicle_uptime_s()
        drift = None
        if w.latlon is not None and now is not None:
            import geo

            drift = float(geo.geodesic_distance_m(w.latlon[0], w.latlon[1], now[0], now[1]))
        dur = None if (w.uptime_s is None or up is None or up < w.uptime_s) else up - w.uptime_s
        rec = {
            "kind": w.kind,
            "leg": w.leg,
            "mode": w.mode,
            "vehicle_s": None if dur is None else round(dur, 1),
            # where the wait lies on the vehicle's clock (s since its boot), to place it in the telemetry log
            "uptime_s": [_s3(w.uptime_s), _s3(up)],
            "drift_m": None if drift is None else round(drift, 1),
            "from": None if w.latlon is None else [round(w.latlon[0], 7), round(w.latlon[1], 7)],
            "to": None if now is None else [round(now[0], 7), round(now[1], 7)],
        }
        self.records.append(rec)
        if drift is not None and drift > max(DRIFT_WARN_FACTOR * self.wp_radius_m, 10.0):
            dur_txt = "" if dur is None else f" in {dur:.0f} s of vehicle time"
            hint = " (a boat in HOLD drifts with the current: vehicle.wait_mode: loiter keeps station)"
            self.say(
                f"leg {w.leg + 1}: the boat drifted {drift:.0f} m{dur_txt} while waiting ({w.kind}, {w.mode})"
                + (hint if w.mode == "HOLD" else "")
            )
        return rec

    def finish(self, on_end: str, note) -> dict:
        """The run is complete: the boat loiters (``on_end`` ``loiter``: armed, in LOITER, keeping station) or is
        disarmed (``disarm``: the motor cannot start, the boat drifts). Said in one line and by ``note(kind,
        text)`` (the run's events); returns :attr:`end_state`. Never raises: a refusal is said and recorded."""
        from passt_mav.errors import MavlinkError

        last = self.end()
        v = self.vehicle
        try:
            if on_end == "disarm":
                v.disarm()
                what = "disarmed (the motor cannot start; the boat drifts with the current)"
            else:
                v.set_mode("LOITER")
                what = "LOITER, armed, keeping station: take it over or disarm it"
        except MavlinkError as exc:
            what = f"WARNING: {on_end} refused or not confirmed ({exc}); the boat is in {v.mode_name}"
        pos = self._where()
        self.end_state = {
            "on_end": on_end,
            "mode": v.mode_name,
            "armed": bool(v.armed),
            "latlon": None if pos is None else [round(pos[0], 7), round(pos[1], 7)],
            "last_wait": last,
        }
        note("boat_end", f"run complete: the boat {what}")
        self.say(f"run complete: the boat {what}")
        return self.end_state

    def for_leg(self, leg: int) -> list[dict]:
        """The waits recorded before or in leg ``leg``."""
        return [r for r in self.records if r["leg"] == leg]

    def _where(self) -> tuple[float, float] | None:
        """The vehicle's last GLOBAL_POSITION_INT (lat, lon) degrees, None before its first fix."""
        return self.vehicle.position()


def _s3(x: float | None) -> float | None:
    """Seconds rounded to the millisecond of ``time_boot_ms`` (None stays None)."""
    return None if x is None else round(float(x), 3)
