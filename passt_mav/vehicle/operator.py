"""The controller's side of the operator's console and of the safety budget (docs/console.md).

A mixin of :class:`~passt_mav.vehicle.controller.MissionController` (as :mod:`~passt_mav.vehicle.resume` is): it
uses the controller's ``rd``, ``link``, ``vehicle``, ``session``, ``journal``, ``config``, ``collector``,
``leg_rec``, ``signals``, ``speed``, ``live_leg``, ``speedup``, ``_leg_once``, ``_archive_attempt``,
``_expected_vehicle_s``, ``_note`` and ``_say``. What it adds to a run:

* the channel to the page (:class:`~passt_mav.runs.commands.CommandReader`), the safety budget
  (:class:`~passt_mav.vehicle.budget.SafetyBudget`) and the vehicle's own alarms
  (:class:`~passt_mav.vehicle.alerts.VehicleAlerts`), attached with the sample collector;
* each leg (:meth:`OperatorLegs._leg`): approve mode before the upload (:meth:`OperatorLegs._approve`), a leg
  planned again when the operator asks (``replan``, or a rejected leg: :class:`Replan`), the budget's end after it;
* the clean stops short of the mission's end (:meth:`OperatorLegs._stop_short`): ``paused`` (a pilot who kept
  the boat, the link-loss window, an approval's timeout; the vehicle to HOLD) and ``ended`` (the operator's
  End or the spent budget; the vehicle already in HOLD or RTL).
"""

from __future__ import annotations

import logging

import numpy as np

from passt_mav.errors import MavlinkError
from passt_mav.vehicle.console import Ended

__all__ = ["OperatorLegs", "Replan"]

log = logging.getLogger(__name__)


class Replan(Exception):  # noqa: N818 - a request, not an error
    """Plan the leg again from where the boat is (:meth:`OperatorLegs._leg`); ``status``: what its attempt is
    called (``replanned by the operator``, ``rejected by the operator``)."""

    def __init__(self, status: str = "replanned by the operator"):
        super().__init__(status)
        self.status = status


class OperatorLegs:
    """The controller's side of the console and the budget (module docstring)."""

    #: the record of the safety budget's shortening of the leg being planned (:meth:`_fit_budget`), None = none
    shortened: dict | None = None

    def _attach_operator(self) -> None:
        """The boat's command channel, budget and alarms on this run's link (with the sample collector)."""
        from passt_mav.runs.commands import CommandReader
        from passt_mav.vehicle.alerts import VehicleAlerts
        from passt_mav.vehicle.budget import SafetyBudget

        self.session.commands = CommandReader(self.rd.root, getattr(self, "boat", 0))
        self.session.budget = SafetyBudget(self.link, self.config.budget)
        self.alerts = VehicleAlerts(self.link, self.journal)
        self.alerts.attach()

    def _keep_operator_streams(self) -> None:
        """The streams the budget and the alarms need, asked for now and after every reboot or reconnect:
        BATTERY_STATUS (with a battery reserve) and FENCE_STATUS."""
        self.session.budget.request_battery()
        self.alerts.request_fence_status()

    def _detach_operator(self) -> None:
        self.alerts.detach()
        self.session.budget.close()

    def _leg(self, i: int, state: np.ndarray, t_state: float) -> tuple[np.ndarray, float]:
        """Leg ``i`` from ``state`` (at field time ``t_state``); planned again from where the boat is, the state
        unchanged, as often as the operator asks (its attempts kept: :class:`Replan`); then, if the safety budget
        was spent during it, the run's end (:meth:`_end_if_budget_spent`)."""
        while True:
            try:
                out = self._leg_once(i, state, t_state)
                break
            except Replan as exc:
                with self.signals.critical():
                    self._archive_attempt(i, status=exc.status)
        self._end_if_budget_spent()
        return out

    def _mark_cut(self, how: str | None) -> None:
        """The leg record of a leg ended by the operator (``skip``/``replan``) or by the budget (``budget``)."""
        if self.leg_rec is None:
            return
        at = int(self.vehicle.progress.current)
        if how in ("skip", "replan"):
            self.leg_rec["operator"] = {"action": how, "at_item": at}
        elif how == "budget":
            self.leg_rec["budget_cut"] = {"reason": self.session.budget.reason, "at_item": at}

    def _fit_budget(self, i: int, planned) -> np.ndarray:
        """Leg ``i``'s planned grid path fitted to what is left of the safety budget before its upload
        (:mod:`passt_mav.vehicle.budget`): the path itself when it fits or no distance/time limit is set; else the
        start of it through its first waypoints that fit, the shortening recorded in :attr:`shortened` (the leg
        record's ``budget_shortened``) and said as an event of kind ``budget``. When not even its first waypoint
        fits, the run ends as at a spent budget (:class:`Ended`)."""
        import geo

        self.shortened, budget = None, self.session.budget
        left_m, left_s = (None, None) if budget is None else budget.left()
        if left_m is None and left_s is None:
            return planned.plan.path
        p, idx = geo.waypoint_indices(self.grid, planned.plan.path)
        wp = geo.path_to_waypoints(self.grid, p)
        here = planned.start_latlon if planned.start_latlon is not None else tuple(wp[0])
        pts = np.vstack([np.asarray(here, float)[None], wp])
        to_wp = np.cumsum(geo.geodesic_distance_m(pts[:-1, 0], pts[:-1, 1], pts[1:, 0], pts[1:, 1]))
        back, home = np.zeros(len(wp)), None
        if self.config.budget.on_spent == "rtl" and (home := budget.home()) is not None:
            back = np.asarray(geo.geodesic_distance_m(wp[:, 0], wp[:, 1], home[0], home[1]), float)
        from passt_mav.vehicle.budget import waypoints_that_fit

        k, n = waypoints_that_fit(to_wp, back, left_m, left_s, self.speed), len(wp)
        if k == n:
            return planned.plan.path
        left = ", ".join(
            x
            for x in (
                None if left_m is None else f"{left_m:.0f} m",
                None if left_s is None else f"{left_s:.0f} s",
            )
            if x
        )
        ret = "" if home is None else " (the way home from each waypoint kept in reserve: on_spent rtl)"
        if k == 0:
            if getattr(self, "sessions", None) and self.sessions[-1]["planned"][-1:] == [i]:
                # never uploaded, so not a leg of the telemetry log: a replay maps the log's legs to the
                # controller's sessions by these lists (--resume plans this leg again in the next one)
                self.sessions[-1]["planned"].pop()
            budget.reason = (
                f"leg {i + 1} does not fit: its first waypoint needs {to_wp[0] + back[0]:.0f} m{ret}, "
                f"budget left {left}"
            )
            self._end_if_budget_spent()
        self.shortened = {
            "kept": k,
            "of": n,
            "distance_m": round(float(to_wp[k - 1]), 1),
            "return_m": round(float(back[k - 1]), 1) if home is not None else None,
            "planned_distance_m": round(float(to_wp[-1]), 1),
            "budget_left_m": None if left_m is None else round(left_m, 1),
            "budget_left_s": None if left_s is None else round(left_s, 1),
            "path": p[: idx[k - 1] + 1].tolist(),
        }
        text = (
            f"leg {i + 1} shortened: {k} of {n} waypoints ({to_wp[k - 1]:.0f} of {to_wp[-1]:.0f} m), "
            f"budget left {left}{ret}"
        )
        self.journal.note("budget", text, level="warn")  # (a notice on the page, not an alarm: nothing is wrong yet)
        self._say(text)
        return p[: idx[k - 1] + 1]

    def _approve(self, i: int, rec: dict, wm) -> None:
        """Approve mode (mission key ``approve``): leg ``i``'s record says ``awaiting_approval`` with its distance
        (m, along its waypoints) and expected duration (vehicle s) for the page, and the controller waits for the
        operator (:meth:`~passt_mav.vehicle.console.OperatorCommands.await_approval`); a rejected leg is planned
        again (:class:`Replan`)."""
        import geo

        wp = wm.waypoints
        dist = (
            float(np.sum(geo.geodesic_distance_m(wp[:-1, 0], wp[:-1, 1], wp[1:, 0], wp[1:, 1]))) if len(wp) > 1 else 0.0
        )
        exp_s = self._expected_vehicle_s(wm)
        ap = self.config.approve
        rec.update(status="awaiting_approval", approval={"distance_m": round(dist, 1), "expected_s": round(exp_s, 1)})
        with self.signals.critical():
            self.rd.write_leg(i, rec)
        what = f"{len(wp)} waypoints, {dist:.0f} m, ~{exp_s / 60:.1f} min at {self.speed:g} m/s"
        # the boat waits in its wait_mode (a wait begun at the last leg's end goes on)
        self.session.waits.begin("approval", i)
        how = self.session.await_approval(i, what, ap.timeout_s, ap.on_timeout)
        rec["status"], rec["approval"]["answer"] = ("rejected" if how == "reject" else "flying"), how
        with self.signals.critical():
            self.rd.write_leg(i, rec)
        if how == "reject":
            raise Replan("rejected by the operator")

    def _end_if_budget_spent(self) -> None:
        """After a leg: if the safety budget is spent (:mod:`passt_mav.vehicle.budget`), the boat to
        ``budget.on_spent`` (RTL, or HOLD; HOLD when the vehicle refuses) and :class:`Ended`."""
        budget = self.session.budget
        if budget is None or budget.reason is None:
            return
        mode = self.config.budget.on_spent.upper()
        try:
            if mode == "HOLD":  # "hold": the boat stops where it is, in its wait_mode (LOITER keeps station)
                mode = self.vehicle.keep_station()
            else:
                self.vehicle.set_mode(mode)
        except MavlinkError as exc:
            self._say(f"WARNING: the vehicle refused {mode} ({exc}); {self.vehicle.wait_mode}")
            self.vehicle.keep_station_if_auto(always=True)
            mode = self.vehicle.wait_mode
        text = f"safety budget spent ({budget.reason}): {mode}; state saved (continue with --resume)"
        self._note("budget", text)
        self._say(text)
        raise Ended(text, mode)

    def _stop_short(self, exc: Exception) -> None:
        """The run stops cleanly before its end: :class:`Ended` (status ``ended``; the vehicle in HOLD or RTL
        already) or :class:`~passt_mav.vehicle.session.Paused` (status ``paused``; the vehicle to HOLD)."""
        from passt_mav.vehicle.controller import close_leg, place_held
        from passt_mav.vehicle.session import utc_now

        if isinstance(exc, Ended):
            self.status = "ended"
            self._note("stopped", f"run ended at {utc_now()}: {exc}")
            close_leg(self.collector)
            place_held(self.collector, None if self.link.lost else self.live_leg[0], self.speedup)
            return
        self.status = "paused"
        self._note("stopped", str(exc))
        self._say(f"stopped: {exc}")
        close_leg(self.collector)
        try:  # the pilot's RC still overrides HOLD; a vehicle left in an unknown mode would not stop
            self.vehicle.keep_station()
        except MavlinkError as e2:
            log.warning("could not switch to HOLD: %s", e2)
