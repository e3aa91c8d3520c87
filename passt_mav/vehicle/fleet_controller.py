"""A fleet: several boats flying one PASST loop, sharing one field estimate.

:class:`FleetController` runs a mission whose ``vehicles:`` lists N boats (``passt-mav
run``). Each boat is a :class:`BoatController` (a :class:`~passt_mav.vehicle.controller.MissionController`
on its own link, with all of its fault handling: reconnects, reboots, a pilot taking over)
working in a thread of its own; what they share is :class:`passt_mav.loop.legstep.FleetStep`
(pure: the replay repeats it), called under one lock:

* **one state**: the field estimate and its field time. Every boat plans from it and
  every boat's samples update it (:meth:`FleetStep.absorb`). The samples of all
  boats go to one :class:`~passt_mav.runs.store.SampleStore` (keyed by the sending
  system id), each boat's frames to its own tlog (``flight_boatN.tlog``).
* **asynchronous legs**: a boat that finishes its leg gets the next one planned from
  the newest estimate at once; it never waits for slower boats. Leg numbers are global
  (``legs/NNN`` in the order legs are planned); each leg record names its ``boat``.
* **joint planning** (:meth:`FleetStep.plan_for`), sequential allocation: a boat
  plans keeping out of every cell of the other boats' current paths (two boats never
  collect the same cells in the same leg interval; its own start cell excepted: it is
  where it is). Boxed in by their paths, it plans with those cells' reward zeroed
  instead and keeps out of any cell another boat's path reaches at the same time
  (within one move's duration; predicted from the paths, the boats' speeds and their
  legs' start times). Every path is checked against the geofence by the boat before
  upload, as for one boat.
* **a boat that drops out** (link lost beyond the reconnect, a pilot who keeps it, a
  failsafe): it is reported (``boats[k].status``, the run's ``events``), its path is
  released and the others go on; the samples it stored stay in the store and those of
  its interrupted leg still update the state. A boat whose link comes back while the
  others still fly rejoins with a new leg.

Absorbing a leg (:meth:`FleetStep.absorb`): the GP prior is the leg's own forecast
(from the state it was planned from, so every sample is compared with the forecast at
its own time), and the GP gets this leg's samples *and* those of every leg absorbed
since this one was planned (their information is not in its forecast). The result
replaces the shared state, at the leg's end or at the state's time if that is later
(the state never goes back in time, and concurrent legs never run it ahead). With one
boat this is exactly :class:`~passt_mav.vehicle.controller.MissionController`'s update.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from passt_mav.errors import MavlinkError, PlannerError, ReconstructionError
from passt_mav.loop.legstep import FleetStep, LegStep, build_loop
from passt_mav.runs.live import RecordWriter
from passt_mav.vehicle.controller import BoatParts, MissionController, StoreWriter
from passt_mav.vehicle.flow import Ended, LinkWindowOver, Paused, utc_now
from passt_mav.vehicle.live_record import live_meta

__all__ = ["FleetController", "BoatController", "SharedState"]

log = logging.getLogger(__name__)


class SharedState:
    """One boat's view of the fleet's one state (:class:`~passt_mav.loop.legstep.FleetStep`), called under the
    fleet's lock: the state keeper a :class:`BoatController` flies with (:class:`~passt_mav.vehicle.controller.OwnState`'s
    methods). Remembers the boat's leg in flight and the fleet steps it was planned and absorbed at."""

    def __init__(self, fleet: FleetController, boat: int, link):
        self.fleet, self.boat, self.link = fleet, int(boat), link
        self.current = None  # the boat's leg in flight (PlannedLeg)
        self.seq_plan: int | None = None
        self.seq_absorb: int | None = None
        self.legs_done = 0

    def plan(self, i: int, state, t_state, start, *, t_now: float, send_clock: Callable[[int], None], **kw):
        """Plan leg ``i`` from the shared state (``state``/``t_state`` are not used: the fleet's is)."""
        with self.fleet.lock:
            shared = self.fleet.shared
            k = shared.step.forecast_steps(t_now, shared.t_state)
            send_clock(k)
            self.current = shared.plan_for(self.boat, i, start, t_now=t_now, k=k, **kw)
            self.seq_plan = shared.seq
        return self.current

    def absorb(self, planned, recs, clock):
        with self.fleet.lock:
            absorbed = self.fleet.shared.absorb(self.boat, planned, recs, clock)
            self.seq_absorb = self.fleet.shared.seq
            return absorbed

    def plan_fields(self) -> dict:
        return {"boat": self.boat, "sysid": int(self.link.target_system)}

    def finish_fields(self) -> dict:
        # the order of the fleet's plans and updates (for a replay): the leg was planned at fleet step
        # seq_plan and absorbed at seq_absorb
        return {**self.plan_fields(), "fleet_seq": self.fleet_seq()}

    def fleet_seq(self) -> dict:
        return {"plan": self.seq_plan, "absorb": self.seq_absorb}

    def leg_done(self) -> None:
        self.legs_done += 1

    def label(self, i: int, n_legs: int) -> str:
        # i counts the fleet's legs; a boat's own count is what the pilot watching it wants
        return f"leg {self.legs_done + 1}/{n_legs} (fleet leg {i + 1})"

    def leg_k(self, leg: int | None, flying: bool) -> int:
        """The boat's own number (1-based) of its leg in flight, or of its last one (the live view)."""
        return self.legs_done + (1 if flying else 0)


class BoatController(MissionController):
    """One boat of a fleet: the one-boat controller flying with the fleet's shared parts (its
    :class:`SharedState`, lock, loop, store, live-view writer and summary), plus a boat's life in a
    fleet (:meth:`fly`: dropping out and rejoining)."""

    share: SharedState  # (the fleet's state, in place of a boat's own OwnState)

    def __init__(self, fleet: FleetController, boat: int, vehicle_config, link, vehicle, **kw):
        cfg = fleet.config.model_copy(update={"vehicle": vehicle_config})
        echo = fleet.echo
        record = fleet.record.for_boat(int(boat))
        super().__init__(
            cfg,
            link,
            fleet.rd,
            field=fleet.field,
            predictor=fleet.predictor,
            predictor_info=fleet.predictor_info,
            vehicle=vehicle,
            legs=fleet.n_legs,
            echo=lambda s: echo(f"boat {boat}: {s}"),
            parts=BoatParts(fleet.step, SharedState(fleet, boat, link), fleet.lock, record, fleet.write_summary),
            **kw,
        )
        self.fleet, self.boat = fleet, int(boat)
        self.store = fleet.store
        self.status = "waiting"

    def _archive_attempt(self, i: int, status: str = "interrupted") -> bool:
        """As one boat's (the operator's re-plan, a rejected leg), the attempt's record also naming the fleet step
        it was planned at (``fleet_seq.plan``): its path was in flight for the other boats' plans until the leg
        was planned again, and a replay plans it at that step too."""
        kept = super()._archive_attempt(i, status)
        if kept and self.share.seq_plan is not None:
            self._attempts[i][-1]["fleet_seq"] = {"plan": int(self.share.seq_plan)}
        return kept

    @property
    def legs_done(self) -> int:
        """Legs this boat completed."""
        return self.share.legs_done

    # -- one boat's mission --------------------------------------------------------------------
    def fly(self) -> None:
        """All of this boat's legs (in its thread); a drop-out is reported and, while the
        others fly, the boat waits for its link to come back and rejoins."""
        self._attach(self.fleet.writer)
        ready = False
        try:
            while self.legs_done < self.n_legs and not self.fleet.stopping.is_set():
                try:
                    if not ready:
                        self.status = "preparing"
                        self._prepare_vehicle()
                        ready = True
                    self.status = "flying"
                    # a fleet's boat plans from the fleet's shared state: no state of its own to hand on
                    self._leg(self.fleet.claim_leg(), None, None)  # type: ignore[arg-type]
                except (
                    Ended
                ) as exc:  # the operator or the budget ended this boat's mission (HOLD/RTL set): others go on
                    self.status = "ended"
                    self.fleet.event(f"boat {self.boat}: ended: {exc}", "stopped", self.boat)
                    return
                except (MavlinkError, PlannerError, Paused) as exc:
                    if isinstance(exc, Paused) and not isinstance(exc, LinkWindowOver):
                        self._stop("paused", exc)
                        return
                    # (the link-loss window over: a drop-out, the others fly on)
                    self._drop(exc)
                    ready = False
                    if not self._rejoin():
                        return
            self.status = "complete" if self.legs_done >= self.n_legs else "stopped"
            if self.status == "complete":
                # the boat loiters or is disarmed (vehicle.on_end), never left armed and drifting
                self.session.waits.finish(self.config.vehicle.on_end, self._note)
        except BaseException as exc:  # noqa: BLE001 - a boat's error must not take the fleet down
            self._stop("aborted", exc)
        finally:
            self.fleet.release(self.boat)
            self._detach()

    def _stop(self, status: str, exc: BaseException) -> None:
        self.status = status
        self.fleet.event(f"boat {self.boat}: {status}: {type(exc).__name__}: {exc}", "stopped", self.boat)
        self._say(f"stopped ({status}): {exc}")
        if not self.link.lost:
            try:
                self.vehicle.keep_station()
            except MavlinkError as e2:
                log.warning("boat %d: could not stop the boat (%s): %s", self.boat, self.vehicle.wait_mode, e2)

    def _drop(self, exc: Exception) -> None:
        """The boat dropped out mid-leg: report, release its path, keep what it sampled."""
        self.status = "lost"
        self.fleet.release(self.boat)
        self.fleet.event(
            f"boat {self.boat} (sysid {self.link.target_system}) dropped out at {utc_now()}: "
            f"{type(exc).__name__}: {exc}",
            "boat_dropped",
            self.boat,
        )
        self._say(f"dropped out ({exc}); the other boats go on")
        self._safe_hold()
        planned, self.share.current = self.share.current, None
        if planned is None:
            return
        self.collector.leg = None
        self.writer.flush()
        recs = self.store.for_leg(planned.index)
        try:  # what it sampled before dropping out still updates the state
            ab = self._update(planned, recs, self._clock_with_boots())
        except ReconstructionError as e2:
            log.info("boat %d: the interrupted leg's %d samples not absorbed: %s", self.boat, len(recs), e2)
            return
        rec = self.leg_rec
        if rec is not None and int(rec["index"]) == planned.index:  # for a replay
            self.rd.write_leg(
                planned.index, {**rec, **ab.record(), "status": "interrupted", "fleet_seq": self.share.fleet_seq()}
            )

    def _rejoin(self) -> bool:
        """Reconnect while any other boat still flies; True when this boat is back."""
        while self.fleet.others_flying(self.boat) and not self.fleet.stopping.is_set():
            try:
                self.link.reconnect(attempts=1)
            except MavlinkError:
                self.link.clock.sleep(0.2)
                continue
            self.fleet.event(f"boat {self.boat} back at {utc_now()}: rejoins", "boat_back", self.boat)
            self._say("link back; rejoining the fleet")
            return True
        return False


class FleetController:
    """Runs a mission on every boat of ``config.fleet`` (module docstring).

    Args:
        config: :class:`~passt_mav.mission.MissionConfig` with ``vehicles``.
        links: one connected :class:`~passt_mav.mavlink.Link` per boat (tlogs set by the caller).
        run_dir: :class:`~passt_mav.runs.RunDir` (created).
        field, predictor, predictor_info: as for :class:`MissionController`.
        vehicles: one :class:`~passt_mav.mavlink.Vehicle` per link (default: defaults).
        legs: legs per boat (default ``config.legs``).
        Other keyword arguments (speedup_hint, pause/ready timeouts, field_time_at_boot,
        truth_known) are passed to every :class:`BoatController`.
    """

    def __init__(
        self,
        config,
        links,
        run_dir,
        *,
        field,
        predictor,
        predictor_info: dict | None = None,
        vehicles=None,
        legs: int | None = None,
        echo: Callable[[str], None] | None = print,
        mission_text: str | None = None,
        extra_summary: dict | None = None,
        truth_known: bool = True,
        **boat_kw,
    ):
        from passt_mav.mavlink import Vehicle
        from passt_mav.runs.store import SampleStore

        fleet = config.fleet
        if len(links) != len(fleet):
            raise ValueError(f"{len(fleet)} vehicles in the mission, {len(links)} links")
        self.config, self.field, self.rd = config, field, run_dir.create()
        self.predictor = predictor
        self.predictor_info = predictor_info or {"requested": config.model, "used": config.model, "fallback": None}
        self.n_legs = int(legs or config.legs)
        self.echo = echo or (lambda s: None)
        self.mission_text, self.extra_summary = mission_text, dict(extra_summary or {})
        # the loop keeps the GP std: estimate.nc u_std/v_std (exports, live view)
        self.loop = build_loop(config, predictor, field.grid, land=field.land_mask)
        self.step = LegStep(config, field, self.loop, truth_known=truth_known)
        self.shared = FleetStep(self.step)  # the one state, the boats' paths in flight
        self.lock = threading.RLock()
        self.stopping = threading.Event()
        self.events: list[str] = []
        self.record = RecordWriter(self.rd.root)  # the live view's files (passt_mav.runs.live)
        self.started_utc = utc_now()
        self.status = "running"
        self._next_leg = 0
        self.store = SampleStore(self.rd.samples_db)
        self.writer = StoreWriter(self.store, field.grid)
        vehicles = vehicles or [Vehicle(link) for link in links]
        self.boats = [
            BoatController(self, k, vc, link, veh, truth_known=truth_known, **boat_kw)
            for k, (vc, link, veh) in enumerate(zip(fleet, links, vehicles))
        ]

    # -- shared state ----------------------------------------------------------------------------
    def claim_leg(self) -> int:
        with self.lock:
            i, self._next_leg = self._next_leg, self._next_leg + 1
            return i

    def event(self, text: str, kind: str = "warning", boat: int | None = None) -> None:
        """A fleet event: summary.json's list and the live view's events.jsonl (``kind``: runs.live.KINDS)."""
        with self.lock:
            self.events.append(text)
        self.record.event(kind, text, boat=boat)
        log.info(text)

    def release(self, boat: int) -> None:
        with self.lock:
            self.shared.release(boat)

    def others_flying(self, boat: int) -> bool:
        return any(b.status in ("waiting", "preparing", "flying") for b in self.boats if b.boat != boat)

    # -- the run ---------------------------------------------------------------------------------
    def run(self) -> dict:
        """Fly every boat's legs; returns the summary (also in ``summary.json``)."""
        if self.mission_text is not None:
            self.rd.mission_file.write_text(self.mission_text)
        cfg = self.config
        self.echo(
            f"mission {cfg.name}: {len(self.boats)} boats x {self.n_legs} legs of {cfg.planner.path_length} "
            f"moves, model {self.predictor_info.get('used')}, planner {cfg.planner.name}; one shared estimate"
        )
        self.record.meta(live_meta(self.boats[0], len(self.boats)))
        self.step.prepare(self.step.initial_state()[0])
        threads = [threading.Thread(target=b.fly, name=f"boat-{b.boat}", daemon=True) for b in self.boats]
        try:
            for t in threads:
                t.start()
            for t in threads:
                while t.is_alive():
                    t.join(0.2)
        except BaseException:
            self.stopping.set()
            for t in threads:
                t.join(30.0)
            raise
        finally:
            done = [b.status == "complete" for b in self.boats]
            self.status = "complete" if all(done) else ("partial" if any(done) else "aborted")
            if all(b.status == "ended" for b in self.boats):  # the operator ended every boat's mission
                self.status = "ended"
            self.writer.close()

            self.write_summary()
            self.store.close()
            self.record.event("run_end", f"fleet {self.status}")
        lost = [b.boat for b in self.boats if b.status != "complete"]
        self.echo(
            f"fleet {self.status}: " + ", ".join(f"boat {b.boat} {b.status} ({b.legs_done} legs)" for b in self.boats)
        )
        if lost:
            self.echo(f"boats that did not finish: {lost} (see events in summary.json)")
        return self.summary()

    def summary(self) -> dict:
        with self.lock:
            legs = sorted((dict(x) for b in self.boats for x in b.leg_records), key=lambda r: int(r["index"]))
            s = self.boats[0].summary()
            truth = s.get("rmse") is not None
            s.update(
                {
                    "status": self.status,
                    "started_utc": self.started_utc,
                    "finished_utc": utc_now() if self.status != "running" else None,
                    "legs": legs,
                    "legs_planned": self.n_legs * len(self.boats),
                    "rmse": {
                        "t": [x.get("t_end") for x in legs],
                        "passt": [x.get("rmse_passt") for x in legs],
                        "model": [x.get("rmse_model") for x in legs],
                    }
                    if truth
                    else None,
                    "config": self.config.model_dump(mode="json"),  # the fleet's (a boat's has its own vehicle:)
                    "connect": [b.link.config.connect for b in self.boats],
                    "boats": [
                        {
                            "boat": b.boat,
                            "sysid": b.link.target_system,
                            "connect": b.link.config.connect,
                            "status": b.status,
                            "legs": b.legs_done,
                            "clock": b._clock_with_boots().describe(),
                            # how this boat ended: loitering or disarmed (vehicle.on_end), None while it flies
                            "end": getattr(getattr(b.session, "waits", None), "end_state", None),
                        }
                        for b in self.boats
                    ],
                    "end": None,  # per boat, in boats[k].end
                    "lost_boats": [
                        b.boat
                        for b in self.boats
                        if b.status not in ("complete", "running", "flying", "waiting", "preparing")
                    ],
                    "events": list(self.events) + [f"boat {b.boat}: {e}" for b in self.boats for e in b.events],
                }
            )
            s.update(self.extra_summary)
            return s

    def write_summary(self) -> None:
        with self.lock:
            self.rd.write_summary(self.summary())
