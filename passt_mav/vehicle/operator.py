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
from typing import TYPE_CHECKING, Any

import numpy as np

from passt_mav.errors import MavlinkError
from passt_mav.mavlink.clock import wall_seconds
from passt_mav.vehicle.flow import Ended, MachineFault, Replan, utc_now
from passt_mav.vehicle.machine_faults import (
    check_store,
    disk_fault,
    import_kept,
    say_tlog_loss,
    stop_for_store,
    summary_or_spare,
)

if TYPE_CHECKING:
    from collections.abc import Callable

    from passt_mav.mavlink.link import Link
    from passt_mav.mavlink.samples import SampleCollector
    from passt_mav.mavlink.vehicle import Vehicle
    from passt_mav.mission.config import MissionConfig
    from passt_mav.runs.rundir import RunDir
    from passt_mav.vehicle.budget import SafetyBudget
    from passt_mav.vehicle.controller import StoreWriter
    from passt_mav.vehicle.session import Journal, VehicleSession

__all__ = ["OperatorLegs", "Replan", "place_held"]

log = logging.getLogger(__name__)


#: a leg approved after the boat drifted out of its start cell is planned again from where it is at most
#: this many times; then it is flown, its approach from where the boat is to the start cell timed
DRIFT_REPLANS = 3


def place_held(collector, leg: int | None, speedup: float) -> None:
    """Leg ``leg``'s last readings wait for the fix after them (as at a leg's end), up to the gap bound of
    vehicle time in wall seconds at ``speedup``."""
    if leg is not None and collector is not None:
        collector.wait_placed(leg, wall_seconds(collector.track.max_gap_ms / 1000.0, max(speedup, 1.0)) + 0.5)


class OperatorLegs:
    """The controller's side of the console and the budget (module docstring)."""

    if TYPE_CHECKING:  # the controller's, which this mixin uses (module docstring)
        rd: RunDir
        link: Link
        vehicle: Vehicle
        session: VehicleSession
        journal: Journal
        config: MissionConfig
        collector: SampleCollector  # (run() makes it and the writer)
        writer: StoreWriter
        leg_rec: dict | None
        signals: Any  # a StopSignals, or NO_SIGNALS
        grid: Any  # the field's grid (geo)
        live_leg: tuple[int | None, float | None]
        speedup: float
        resume: bool
        sessions: list[dict]
        _write_summary: Callable[[], None]

        @property
        def speed(self) -> float: ...
        def _say(self, s: str) -> None: ...
        def _note(self, kind: str, text: str) -> None: ...
        def _leg_once(self, i: int, state: np.ndarray, t_state: float) -> tuple[np.ndarray, float]: ...
        def _archive_attempt(self, i: int, status: str = "interrupted") -> bool: ...
        def _expected_vehicle_s(self, wm) -> float: ...
        def _leg_label(self, i: int) -> str: ...
        def _old_summary(self) -> dict | None: ...

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
        # a store the machine fails stops the run between steps (passt_mav.vehicle.machine_faults)
        self.session.store_guard = getattr(self.writer, "guard", None)
        self._write_summary = summary_or_spare(self, self._write_summary)  # (a full disk refuses summary.json too)
        if self.resume:
            import_kept(self)

    def _budget(self) -> SafetyBudget:
        """The session's safety budget (:meth:`_attach_operator` attached it, for the whole run)."""
        budget = self.session.budget
        assert budget is not None, "the safety budget is attached with the sample collector"
        return budget

    def _keep_operator_streams(self) -> None:
        """The streams the budget and the alarms need, asked for now and after every reboot or reconnect:
        BATTERY_STATUS (with a battery reserve) and FENCE_STATUS."""
        self._budget().request_battery()
        self.alerts.request_fence_status()

    def _detach_operator(self) -> None:
        self.alerts.detach()
        self._budget().close()
        say_tlog_loss(self)

    def _leg(self, i: int, state: np.ndarray, t_state: float) -> tuple[np.ndarray, float]:
        """Leg ``i`` from ``state`` (at field time ``t_state``); planned again from where the boat is, the state
        unchanged, as often as the operator asks (its attempts kept: :class:`Replan`); then, if the safety budget
        was spent during it, the run's end (:meth:`_end_if_budget_spent`). A store the machine failed stops the run
        before the leg and after it (:func:`~passt_mav.vehicle.machine_faults.check_store`)."""
        while True:
            check_store(getattr(self.session, "store_guard", None))
            try:
                out = self._leg_once(i, state, t_state)
                break
            except Replan as exc:
                with self.signals.critical():
                    self._archive_attempt(i, status=exc.status)
            except OSError as exc:  # a run file the disk refused: stopped as for the store, else as it was
                disk_fault(exc)
                raise
        self._end_if_budget_spent()
        check_store(getattr(self.session, "store_guard", None))
        return out

    def _mark_cut(self, how: str | None) -> None:
        """The leg record of a leg ended by the operator (``skip``/``replan``) or by the budget (``budget``)."""
        if self.leg_rec is None:
            return
        at = int(self.vehicle.progress.current)
        if how in ("skip", "replan"):
            self.leg_rec["operator"] = {"action": how, "at_item": at}
        elif how == "budget":
            self.leg_rec["budget_cut"] = {"reason": self._budget().reason, "at_item": at}

    def _fit_budget(self, i: int, planned) -> np.ndarray:
        """Leg ``i``'s planned grid path fitted to what is left of the safety budget before its upload
        (:mod:`passt_mav.vehicle.budget`): the path itself when it fits or no distance/time limit is set; else the
        start of it through its first waypoints that fit, the shortening recorded in :attr:`shortened` (the leg
        record's ``budget_shortened``) and said as an event of kind ``budget``. When not even its first waypoint
        fits, the run ends as at a spent budget (:class:`Ended`)."""
        import geo

        self.shortened, budget = None, self.session.budget
        left_m, left_s = (None, None) if budget is None else budget.left()
        if budget is None or (left_m is None and left_s is None):
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
        moved = None if how == "reject" else self._drifted_from_start(i, wm)
        if moved is not None:
            rec["status"], rec["approval"]["drifted_to_cell"] = "drifted", moved
        with self.signals.critical():
            self.rd.write_leg(i, rec)
        if how == "reject":
            raise Replan("rejected by the operator")
        if moved is not None:
            text = (
                f"{self._leg_label(i)}: the boat drifted to cell {tuple(moved)} while awaiting approval; planned again"
            )
            self._say(text)
            raise Replan("drifted while awaiting approval")

    def _drifted_from_start(self, i: int, wm) -> list[int] | None:
        """The grid cell the boat is in when it is no longer the cell leg ``i`` was planned from (``wm``'s first
        cell; a boat in HOLD drifts with the current while the operator decides), at most
        :data:`DRIFT_REPLANS` times a leg; else None (the leg is flown from where the boat is)."""
        cells = (wm.meta or {}).get("cells")
        pos = self.vehicle.position()
        if not cells or pos is None:
            return None
        now = [int(x) for x in self.grid.latlon_to_cell(*pos, clip=True)]
        counts = self.__dict__.setdefault("_drift_replans", {})
        if now == [int(x) for x in cells[0]] or counts.get(i, 0) >= DRIFT_REPLANS:
            return None
        counts[i] = counts.get(i, 0) + 1
        return now

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
        already), :class:`~passt_mav.vehicle.flow.Paused` (status ``paused``; the vehicle to HOLD) or its
        :class:`~passt_mav.vehicle.flow.MachineFault` (status ``stopped`` by what failed; the vehicle to HOLD)."""
        from passt_mav.vehicle.leg_marks import close_leg

        if isinstance(exc, Ended):
            self.status = "ended"
            self._note("stopped", f"run ended at {utc_now()}: {exc}")
            close_leg(self.collector, self.link)
            place_held(self.collector, None if self.link.lost else self.live_leg[0], self.speedup)
            return
        if isinstance(exc, MachineFault):
            stop_for_store(self, exc)
        else:
            self.status = "paused"
            self._note("stopped", str(exc))
            self._say(f"stopped: {exc}")
        close_leg(self.collector, self.link)
        try:  # the pilot's RC still overrides HOLD; a vehicle left in an unknown mode would not stop
            self.vehicle.keep_station()
        except MavlinkError as e2:
            log.warning("could not switch to HOLD: %s", e2)
