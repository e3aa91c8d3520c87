"""Riding out link outages: the part of :class:`~passt_mav.vehicle.session.VehicleSession` that reconnects
within the link-loss window and resyncs with the vehicle afterwards (docs/resilience.md).

A mixin: it uses the session's ``link`` (and its clock), ``vehicle``, ``journal``, ``speedup``, ``link_loss_window_s``,
``outages``, ``rebooted``, ``set_speed_again`` and ``_say``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from passt_mav.errors import LinkTimeout, MavlinkError
from passt_mav.mavlink.clock import wall_seconds
from passt_mav.mavlink.mission_client import differences
from passt_mav.mavlink.vehicle import ROVER_MODES
from passt_mav.vehicle.flow import LinkWindowOver, utc_now

if TYPE_CHECKING:
    import threading

    from passt_mav.mavlink.link import Link
    from passt_mav.mavlink.vehicle import Vehicle
    from passt_mav.vehicle.session import Journal

__all__ = ["LinkOutages"]

AUTO = ROVER_MODES["AUTO"]


class LinkOutages:
    """Reconnect within the link-loss window, record the outage, resync (see the module docstring)."""

    if TYPE_CHECKING:  # the session's, which this mixin uses (module docstring)
        link: Link
        vehicle: Vehicle
        journal: Journal
        speedup: float
        link_loss_window_s: float
        outages: list[dict]
        rebooted: threading.Event

        def set_speed_again(self, i: int, why: str) -> None: ...
        def _say(self, text: str) -> None: ...

    def _silent_s(self) -> float:
        """Wall seconds since the vehicle was last heard (0 when never: the loss starts now)."""
        s = self.link.seconds_since_heartbeat
        return 0.0 if s == float("inf") else s

    def lost_since(self) -> float:
        """When (the link's clock, wall s) the vehicle was last heard: now when it never was."""
        return self.link.clock.now() - self._silent_s()

    @property
    def window_wall_s(self) -> float:
        """The link-loss window in wall seconds (``link_loss_window_s / speedup``)."""
        return wall_seconds(self.link_loss_window_s, self.speedup)

    def reconnect_within_window(self, i: int, t_lost: float, during: str = "leg") -> dict:
        """Reconnect until the link-loss window, counted from ``t_lost`` (the link's clock, wall s: see
        :meth:`lost_since`), ends: back-off capped, one line per failed attempt. The outage goes to :attr:`outages`
        (``leg``, ``during`` what, UTC lost and back, wall seconds, the vehicle's uptime s last heard and in its
        first position after, and the vehicle seconds between them: readings it sent meanwhile never reached us);
        returns that record. Raises :class:`LinkWindowOver` when the window ends first."""
        link = self.link
        out = {"leg": i, "during": during, "lost_utc": utc_now(), "tb_from_s": link.vehicle_uptime_s()}
        self.outages.append(out)
        left = self.window_wall_s - (link.clock.now() - t_lost)
        link.clear_error()
        try:
            link.reconnect(wait_s=max(left, 0.0), say=lambda s: self._say(f"leg {i + 1}: {s}"))
        except LinkTimeout as exc:
            out.update(wall_s=round(link.clock.now() - t_lost, 3), back_utc=None)
            raise LinkWindowOver(
                f"leg {i + 1}: no link for {link.clock.now() - t_lost:.0f} s wall, the link-loss window "
                f"(vehicle.link_loss_window_s = {self.link_loss_window_s:g} s of vehicle time): {exc}; the vehicle "
                f"flies its uploaded leg on and then holds its last waypoint (Rover MIS_DONE_BEHAVE); continue "
                f"with --resume once it can be reached"
            ) from None
        try:  # the vehicle's clock in its first position after the outage
            gp = link.wait(
                "GLOBAL_POSITION_INT", timeout=wall_seconds(3.0, self.speedup, at_least=1.0) + link.reply_timeout
            )
            tb_to = gp.time_boot_ms / 1000.0
        except LinkTimeout:
            tb_to = None
        tb_from = out["tb_from_s"]
        out.update(
            back_utc=utc_now(),
            wall_s=round(link.clock.now() - t_lost, 3),
            tb_to_s=tb_to,
            vehicle_s=None if tb_from is None or tb_to is None or tb_to < tb_from else round(tb_to - tb_from, 3),
        )
        return out

    def recover_link(self, i: int, items) -> None:
        """The link died mid-leg: reconnect within the link-loss window (:meth:`reconnect_within_window`),
        then resync (unless the autopilot rebooted: :meth:`fly` handles that): position, mode, the stored
        mission (re-uploaded at the current item if it is not ours), the current item. Raises
        :class:`LinkWindowOver` when the window ends first."""
        link = self.link
        why = link.closed_reason or f"{link.seconds_since_heartbeat:.1f} s without heartbeat"
        t_lost = self.lost_since()
        self._say(
            f"leg {i + 1}: link lost ({why}); the vehicle flies its leg on; reconnecting for up to "
            f"{self.link_loss_window_s:g} s (vehicle.link_loss_window_s)"
        )
        self.journal.note("link_lost", f"leg {i + 1}: link lost at {utc_now()} ({why})")
        while True:
            out = self.reconnect_within_window(i, t_lost)
            try:
                cur = self._resync(i, items)
                break
            except MavlinkError:
                if not (link.lost or link.error is not None):
                    raise
                self._say(f"leg {i + 1}: link lost again during the resync; reconnecting")
        self.journal.record.event("link_back", f"leg {i + 1}: link back at {utc_now()}")
        if cur is None:
            out["vehicle_s"] = None  # the autopilot rebooted meanwhile: its clock started again
            return  # fly() handles the reboot (it verifies the mission itself)
        v = self.vehicle
        pos = v.position()
        where = "" if pos is None else f", at {pos[0]:.6f},{pos[1]:.6f}"
        mode = v.mode_name or str(v.mode)
        gone = "" if out["vehicle_s"] is None else f" after {out['vehicle_s']:.0f} s of vehicle time"
        self.journal.events.append(
            f"leg {i + 1}: reconnected{gone}, mission verified, item {cur.seq}/{getattr(cur, 'total', '?')}, mode {mode}"
        )
        self._say(
            f"leg {i + 1}: reconnected{gone}; mission on the vehicle verified, at item "
            f"{cur.seq}/{getattr(cur, 'total', '?')}, mode {mode}{where}"
        )

    def _resync(self, i: int, items):
        """After a reconnect: a reboot check, the stored mission (re-uploaded at the current item if not ours).
        Returns MISSION_CURRENT, or None when the autopilot rebooted."""
        link = self.link
        # a rebooted autopilot also drops its links (its first time stamps were awaited by the reconnect)
        if self.rebooted.wait(0.1):
            return None
        v = self.vehicle
        diff = differences(list(items), v.mission.download(), 0)
        cur = link.wait("MISSION_CURRENT", timeout=max(2.0, link.reply_timeout))
        if diff:
            self._say(f"leg {i + 1}: the vehicle's mission differs after the reconnect ({diff}); re-uploading")
            was_auto = v.mode == AUTO
            if was_auto:
                v.keep_station()
            v.mission.upload_verified(items)
            v.mission.set_current(max(1, min(int(cur.seq), len(items) - 1)))
            if was_auto:
                v.set_mode("AUTO")
                self.set_speed_again(i, "the mission was uploaded again")
        return cur
