"""The mission controller: the PASST loop flown by a live vehicle over MAVLink.

One :class:`MissionController` runs one mission (``passt-mav run`` / ``passt-mav
demo``). It reuses :class:`passt_mav.loop.passt.PasstLoop` unchanged; only the sampler
differs: instead of reading the ground-truth field, each leg is uploaded to the
vehicle and flown, and the current samples it streams back are the leg's samples.
Everything between two legs is :class:`passt_mav.loop.legstep.LegStep` (pure, shared with
``passt-mav replay``); this module adds the vehicle, through parts with one job each:

* :class:`~passt_mav.vehicle.session.VehicleSession`: the vehicle side (swap, fly, and the
  faults below: reconnects, reboots, a pilot, another ground station);
* :class:`~passt_mav.vehicle.clock.RunClock`: vehicle time -> field time (below, "Clock");
* a state keeper: :class:`OwnState` for one boat, the fleet's shared state for a fleet's boat
  (:class:`passt_mav.vehicle.fleet_controller.SharedState`);
* :class:`StoreWriter` (samples to the store) and the live view's
  :class:`~passt_mav.runs.live.RecordWriter`.

Per leg ``i`` (:meth:`MissionController._leg`: plan -> check -> upload -> fly -> absorb)::

    _plan:   position -> start cell; clock reading -> STATUSTEXT "PASST leg i tb T b B k K"
             (kept by the tlog and ArduPilot's DataFlash log) -> the state keeper's plan
    _checked_mission: WaypointMission, geofence check of every waypoint (abort before upload)
    _swap:   VehicleSession.swap: wait mode, upload + read-back, set_current(1), arm if needed, AUTO,
             the mission's speed as a command (Rover drops a boat's seq-1 DO_CHANGE_SPEED)
    _fly_leg: VehicleSession.fly: collect samples until the mission completes (faults handled) -> wait mode

"Wait mode" is ``vehicle.wait_mode`` (:meth:`~passt_mav.mavlink.Vehicle.keep_station`): LOITER keeps a boat on
its spot; HOLD stops its motor and it drifts with the current. Every wait is measured
(:class:`~passt_mav.vehicle.waits.WaitLog`: leg.json ``waits``); at the run's end the boat loiters or is
disarmed (``vehicle.on_end``, summary.json ``end``). Below, "HOLD" means the wait mode.
    _absorb: the state keeper's absorb (thin, GP update, RMSE) -> estimate.nc; _finish_leg: records

Clock (vehicle time -> field time). Every sample carries the autopilot's
``time_boot_ms``. Field time is ``t = t_boot0 + time_boot_ms / 1000 / time_scale``,
with ``time_scale`` the mission's ``field.time_scale`` (seconds per field time unit:
1 for geographic fields, e.g. 200 for the scaled cylinder) and ``t_boot0`` the field
time at vehicle boot, chosen once the vehicle is ready (mission ``field.clock``):

* ``utc`` (a real boat): from the vehicle's UTC, SYSTEM_TIME ``time_unix_usec -
  time_boot_ms`` (its GPS clock), as seconds since the field's ``time_origin``: a
  forecast of a date (RTOFS) is sampled at the hour the boat is there;
* ``boot`` (a simulator without a clock): ``--field-time-at-boot`` (``passt-mav demo``
  starts the simulator with exactly that ``--start-time``), default
  ``field.times[config.t0]``: the simulator's own clock rule, so field times agree exactly;
* ``auto``: ``utc`` when the field has a time origin and the vehicle's UTC lies inside
  its snapshots, else ``boot`` (the reason is printed). ``--field-time-at-boot`` forces ``boot``.

A reboot restarts ``time_boot_ms``: each later boot gets its own ``t_boot0`` (from the
vehicle's UTC at that boot when it has one, else continuing from the last time seen
before the reboot, the down time not counted); samples carry their boot (the store's
``boot`` column, counted by :class:`~passt_mav.mavlink.SampleCollector` from this run's start).

Legs in time. The state is the estimate at field time ``t_state``. When a leg
starts at a later ``t_now`` the state is first forecast ``round((t_now -
t_state) / dt)`` snapshots forward. A leg spans the snapshots of its path's time in the
forecast current (``planner.current_aware``: :mod:`passt_mav.planning.transit`; else
``steps_for_leg(L, cell_size, speed, dt * time_scale)``, at least 1); after it the reconstruction is
the state at ``t_start + steps * dt`` (the planned end, as the loop defines it).

Samples. Each sample is appended to the run's :class:`~passt_mav.runs.SampleStore`
as it arrives (a writer thread commits whatever has queued, usually one sample,
in one transaction; duplicates are ignored by the store). The GP gets them
*thinned*: averaged per (nearest grid cell, snapshot-time bin ``round((t -
t_start) / dt)``), position, time and velocity averaged in each group. A sensor
at 1 Hz on an ocean leg of hours would otherwise hand the GP thousands of points
of which all but a few per cell and snapshot are redundant (the GP's cost is
cubic in their number). Velocities are converted from m/s east/north to field
units (divided by ``field.velocity_scale``, rotated into a metric grid's frame).

Faults (docs/resilience.md). Link loss during a leg: the link is reconnected with capped back-off
within the link-loss window (``vehicle.link_loss_window_s``, :mod:`passt_mav.vehicle.outages`; past it
the run stops, status ``paused``), the mission is downloaded and compared with the one
uploaded (re-uploaded if it differs) and the leg goes on from MISSION_CURRENT;
samples keep flowing into the store (the collector listens on the same link
object); the outage is recorded. A stop signal (:mod:`passt_mav.vehicle.signals`): HOLD (or AUTO left
with ``vehicle.on_signal: auto``), store flushed, status ``stopped``. A leg past ``vehicle.overrun_factor``
x its expected vehicle time is cut (``vehicle.on_overrun``). Link loss during the leg swap (HOLD, upload, set-current, arm, AUTO): the
link is reconnected and the swap is done again from HOLD (the upload is verified by
reading back, the other steps are idempotent), up to 3 times. A reboot of the
autopilot (``time_boot_ms`` going back; the vehicle comes back disarmed in
INITIALISING/MANUAL, which is not a pilot's doing): wait for the EKF, verify the
stored mission (re-upload if lost), re-arm, set the interrupted item current and
AUTO; or, with ``vehicle.on_reboot: hold``, HOLD and stop (status ``paused``).
The vehicle leaving AUTO while armed (a pilot takes over): the controller says so and
waits until AUTO comes back or ``pause_timeout_s`` passes, then switches to HOLD
and stops cleanly (status ``paused``). Another ground station on the vehicle (QGroundControl
beside us): the mission is read back once AUTO is entered after every swap and whenever
:class:`~passt_mav.mavlink.mission_client.MissionWatch` sees signs of another upload; a mission
not ours is uploaded again (HOLD, resume at the item, AUTO), a third time in one leg stops in
HOLD (``paused``); an upload DENIED while the other station transfers is waited out.
``resume=True`` continues a run directory
after the controller was killed: completed legs come from their leg records,
samples from the store, the state from the last leg's ``estimate.nc``; the leg
that was in flight is re-planned from the current position, its interrupted attempt kept
(:mod:`passt_mav.vehicle.resume`).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from passt_mav.errors import LinkTimeout, MavlinkError, PlannerError, ReconstructionError, UserError
from passt_mav.loop.legstep import (  # noqa: F401 - the between-leg step's building blocks, re-exported
    THINNING,
    FieldClock,
    LegStep,
    build_loop,
    build_predictor,
    extend_leg_to_end,
    leg_steps,
    pure_model_at,
    rmse,
    thin_samples,
    to_field_units,
    truth_at,
    utc_epoch,
)
from passt_mav.mavlink.clock import SYSTEM_CLOCK, Clock
from passt_mav.runs.legs import clock_statustext
from passt_mav.runs.live import RecordWriter
from passt_mav.units import SpeedUnit, speed_unit
from passt_mav.vehicle.clock import RunClock
from passt_mav.vehicle.flow import Ended, Paused, Replan, Stopped, utc_now
from passt_mav.vehicle.leg_marks import close_leg
from passt_mav.vehicle.live_record import live_meta, live_status
from passt_mav.vehicle.machine_faults import machine_faults_record
from passt_mav.vehicle.operator import OperatorLegs, place_held
from passt_mav.vehicle.resume import ResumeRecord
from passt_mav.vehicle.session import Deadline as _Deadline  # noqa: F401 - tests import it from here
from passt_mav.vehicle.session import Journal, VehicleSession, expected_vehicle_s
from passt_mav.vehicle.signals import NO_SIGNALS

__all__ = [
    "FieldClock",
    "MissionController",
    "OwnState",
    "preflight",
    "StoreWriter",
    "thin_samples",
    "build_predictor",
    "build_loop",
    "rmse",
    "THINNING",
]

log = logging.getLogger(__name__)


class StoreWriter:
    """Appends samples to the store from a thread of its own: the link's reader thread only queues them.
    ``clock``: the wall clock :meth:`flush` waits on. A store the machine fails (disk full, read-only, removed)
    is said by :attr:`guard` (:class:`~passt_mav.runs.store_guard.StoreGuard`), which keeps the readings."""

    def __init__(self, store, grid, clock: Clock = SYSTEM_CLOCK):
        from passt_mav.runs.store_guard import StoreGuard

        self.store, self.grid, self.clock = store, grid, clock
        self.guard = StoreGuard(store)
        self.q: queue.Queue = queue.Queue()
        self.new = 0
        # samples queued and samples committed (or failed) so far: flush() waits for the second to reach the first
        self._queued = self._committed = 0
        self._progress = threading.Condition()
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._loop, name="sample-store", daemon=True)
        self._th.start()

    def __call__(self, rec: dict) -> None:
        with self._progress:
            self._queued += 1
            self.q.put(rec)

    def _loop(self) -> None:
        while not (self._stop.is_set() and self.q.empty()):
            try:
                first = self.q.get(timeout=0.05)
            except queue.Empty:
                continue
            batch = [first]
            while True:
                try:
                    batch.append(self.q.get_nowait())
                except queue.Empty:
                    break
            try:
                self.new += self.guard.append_many([self._row(rec) for rec in batch])
            except Exception:  # noqa: BLE001 - a store failure must be seen, but must not kill the thread
                log.exception("could not store %d samples", len(batch))
            with self._progress:
                self._committed += len(batch)
                self._progress.notify_all()

    def _row(self, rec: dict) -> dict:
        r, c = self.grid.latlon_to_cell(rec["lat"], rec["lon"], clip=True)
        return {
            "time_boot_ms": int(rec["time_boot_ms"]),
            "utc": float(rec["utc"]),
            "lat": rec["lat"],
            "lon": rec["lon"],
            "u": rec["u"],
            "v": rec["v"],
            "leg": int(rec.get("leg", -1)),
            "source": rec.get("source", "mavlink"),
            "row": int(r),
            "col": int(c),
            "boot": int(rec.get("boot", 0)),
            "gap_ms": rec.get("gap_ms"),
        }

    def flush(self, timeout: float = 5.0) -> None:
        """Wait (up to ``timeout`` wall s) until every sample queued before this call is committed.

        Samples queued meanwhile (a fleet's other boats) are not waited for: a time-based wait for an
        empty queue could return while the last batch was still being committed, and a leg absorbed
        its samples without that batch (its replay, reading the store later, then had more)."""
        end = self.clock.now() + timeout
        with self._progress:
            target = self._queued
            while self._committed < target:
                left = end - self.clock.now()
                if left <= 0:
                    log.warning(
                        "sample store: %d samples not committed after %.1f s", target - self._committed, timeout
                    )
                    return
                self._progress.wait(left)

    def close(self) -> None:
        self.flush()
        self._stop.set()
        self._th.join(timeout=5.0)


class OwnState:
    """How one boat plans from and updates the estimate: the state travels through its own legs
    (:class:`~passt_mav.loop.legstep.LegStep`). A fleet's boat gets the fleet's shared state instead
    (:class:`passt_mav.vehicle.fleet_controller.SharedState`, the same methods)."""

    def __init__(self, step: LegStep):
        self.step = step

    def plan(self, i: int, state, t_state: float, start, *, t_now: float, send_clock: Callable[[int], None], **kw):
        """Forecast ``round((t_now - t_state) / dt)`` steps (``send_clock(k)`` first), then plan leg ``i``."""
        k = self.step.forecast_steps(t_now, t_state)
        send_clock(k)
        return self.step.plan(i, state, t_state, start, t_now=t_now, k=k, **kw)

    def absorb(self, planned, recs, clock):
        """The leg's samples into the state (:meth:`LegStep.absorb`)."""
        return self.step.absorb(planned, recs, clock)

    def plan_fields(self) -> dict:
        """Keys a planned leg's record gets besides the step's own (none for one boat)."""
        return {}

    def finish_fields(self) -> dict:
        """Keys a completed leg's record gets besides the step's own (none for one boat)."""
        return {}

    def leg_done(self) -> None:
        """A leg of this boat is complete."""

    def label(self, i: int, n_legs: int) -> str:
        """How leg ``i`` (0-based) is named in progress lines."""
        return f"leg {i + 1}/{n_legs}"

    def leg_k(self, leg: int | None, flying: bool) -> int | None:
        """The number (1-based) the live view shows for leg ``leg`` (in flight or the last one)."""
        return None if leg is None else leg + 1


@dataclass(frozen=True)
class BoatParts:
    """What a fleet's boat shares with the fleet instead of owning it (each None = the controller's own):
    its :class:`~passt_mav.loop.legstep.LegStep`, state keeper (:class:`OwnState`'s methods), lock, live-view
    writer and summary writer."""

    step: LegStep | None = None
    share: Any = None
    lock: Any = None
    record: RecordWriter | None = None
    write_summary: Callable[[], None] | None = None


def _check_field(config, field) -> None:
    """The mission's field can carry a run: two snapshots at least (dt), and t0 inside it."""
    if field.n_times < 2:
        raise UserError("the mission's field needs at least 2 snapshots (dt)")
    if not 0 <= config.t0 < field.n_times - 1:
        raise UserError(f"t0={config.t0} lies outside the field's {field.n_times} snapshots")


def preflight(config, field, predictor) -> None:
    """What can be checked of a mission before the vehicle is touched (``passt-mav run`` calls it before
    connecting): the field carries a run (two snapshots, ``t0`` inside), it has water, and the predictor
    forecasts the start state (:meth:`~passt_mav.fields.FlowField.state_at`, land masked as the loop masks
    it) one snapshot ahead to finite values. Raises :class:`UserError` naming the problem."""
    from passt_mav.errors import FieldError, ModelError

    _check_field(config, field)
    land = field.land_mask
    if land.all():
        raise FieldError("the mission's field has no water cell in its region (all NaN)")
    state = field.state_at(config.t0)
    if predictor is None:
        return
    try:
        pred = np.asarray(predictor.predict(np.where(land, np.float32(0), state), 1))
    except (ModelError, ValueError) as exc:
        raise ModelError(f"the mission's model cannot forecast the field's state at t0: {exc}") from None
    if not np.isfinite(pred[..., ~land]).all():
        raise ModelError("the mission's model forecasts NaN/inf from the field's state at t0; check the model")


class MissionController(ResumeRecord, OperatorLegs):
    """Runs a mission config on a connected vehicle, writing a run directory.

    Args:
        config: :class:`~passt_mav.mission.MissionConfig`.
        link: a connected :class:`~passt_mav.mavlink.Link` (tlog set by the caller).
        run_dir: :class:`~passt_mav.runs.RunDir` (created).
        field: the mission's field (initial state, dt, and the truth for RMSE).
        predictor / predictor_info: from :func:`build_predictor`.
        vehicle: a :class:`~passt_mav.mavlink.Vehicle` on ``link`` (default: one with defaults).
        legs: number of legs (default ``config.legs``).
        field_time_at_boot: field time at vehicle boot (default ``field.times[config.t0]``).
        speedup_hint: simulated / wall seconds of the vehicle (1 for a real boat); scales wall timeouts.
        pause_timeout_s: wall seconds to wait for AUTO to come back after a pilot took over.
        ready_timeout_s: wall seconds to wait for EKF/GPS readiness.
        resume: continue the run in ``run_dir`` (see module docstring).
        truth_known: compute RMSE vs ``field`` (it is what the vehicle's sensor measures).
        echo: where one-line progress goes (print; None = silent).
        mission_text: text of the mission file as run (written to the run directory).
        extra_summary: merged into summary.json (e.g. the demo's simulator settings).
        parts: a fleet's boat's shared parts (:class:`BoatParts`); default: this controller's own.
        signals: the command's :class:`~passt_mav.vehicle.signals.StopSignals` (run files are written inside
            its ``critical()``; a stop signal ends the run with status ``stopped``); default: none.
    """

    def __init__(
        self,
        config,
        link,
        run_dir,
        *,
        field,
        predictor,
        predictor_info: dict | None = None,
        vehicle=None,
        legs: int | None = None,
        field_time_at_boot: float | None = None,
        speedup_hint: float = 1.0,
        pause_timeout_s: float = 300.0,
        ready_timeout_s: float = 120.0,
        resume: bool = False,
        truth_known: bool = True,
        echo: Callable[[str], None] | None = print,
        mission_text: str | None = None,
        extra_summary: dict | None = None,
        parts: BoatParts | None = None,
        signals=None,
    ):
        from passt_mav.mavlink import Vehicle

        self.config, self.link, self.rd, self.field, self.grid = config, link, run_dir, field, field.grid
        self.predictor = predictor
        self.predictor_info = predictor_info or {"requested": config.model, "used": config.model, "fallback": None}
        self.vehicle = vehicle or Vehicle(link)
        self.n_legs = int(legs or config.legs)
        _check_field(config, field)
        self.dt = float(field.dt)
        self.speedup = max(float(speedup_hint), 1e-6)
        self.resume, self.truth_known, self.mission_text = resume, truth_known, mission_text
        self.signals, self.stopped_by = signals or NO_SIGNALS, None  # (stopped_by: the signal's name)
        self.extra_summary = dict(extra_summary or {})
        self.land = field.land_mask
        parts = parts or BoatParts()
        # the loop keeps the GP std: estimate.nc u_std/v_std (exports, live view)
        step = parts.step or LegStep(
            config, field, build_loop(config, predictor, self.grid, land=self.land), truth_known
        )
        self.step, self.loop = step, step.loop
        self.share = parts.share or OwnState(step)
        #: held while writing netCDF/HDF5 files and running the predictor (neither is thread-safe: a fleet's boats)
        self.lock = parts.lock or threading.RLock()
        self.leg_records: list[dict] = []
        self.leg_rec: dict | None = None  # the record of the leg in flight
        self.status, self.started_utc = "running", utc_now()
        self.store = self.collector = self.writer = None  # type: ignore[assignment]  # set by run() before any use
        self.record = parts.record or RecordWriter(run_dir.root)  # the live view's files (passt_mav.runs.live)
        self.journal = Journal(echo or (lambda s: None), self.record)
        self.run_clock = self._make_clock(field_time_at_boot)
        self.record.field_time = self.run_clock.field_time_now
        self.session = self._make_session(ready_timeout_s, pause_timeout_s)
        self._write_summary = parts.write_summary or self._write_own_summary
        self._n_stored: int | None = None  # the store's count when last read
        self._last_clock: tuple[int, int, int, int] | None = None  # (leg, time_boot_ms, boot, k) last sent
        self._init_resume_record()
        self.live_leg: tuple[int | None, float | None] = (None, None)  # (leg in flight, uptime s it should end)

    def _make_clock(self, field_time_at_boot: float | None) -> RunClock:
        """The run's clock (vehicle time -> field time); ``field_time_at_boot`` forces the boot anchor."""
        t0 = float(self.field.times[self.config.t0]) if field_time_at_boot is None else float(field_time_at_boot)
        forced = field_time_at_boot is not None
        return RunClock(
            self.field, self.config.field, self.link, self.journal, forced=forced, t_boot0=t0, speedup=self.speedup
        )

    def _make_session(self, ready_timeout_s: float, pause_timeout_s: float) -> VehicleSession:
        """The vehicle side of this controller's legs (timeouts in wall seconds), with the boat's waits."""
        self.vehicle.wait_mode = self.config.vehicle.wait_mode.upper()
        return VehicleSession(
            self.link,
            self.vehicle,
            self.journal,
            speed_mps=self.speed,
            on_reboot=self.config.vehicle.on_reboot,
            speedup=self.speedup,
            ready_timeout_s=ready_timeout_s,
            pause_timeout_s=pause_timeout_s,
            link_loss_window_s=self.config.vehicle.link_loss_window_s,
            overrun_factor=self.config.vehicle.overrun_factor,
            on_overrun=self.config.vehicle.on_overrun,
            wp_radius_m=self.config.vehicle.wp_radius_m,
        )

    # -- helpers --------------------------------------------------------------------------
    @property
    def events(self) -> list[str]:
        """The run's events (summary.json)."""
        return self.journal.events

    @property
    def clock(self) -> FieldClock:
        """Vehicle time -> field time of the vehicle's first boot in this session."""
        return self.run_clock.clock

    def _say(self, s: str) -> None:
        self.journal.say(s)

    def _note(self, kind: str, text: str) -> None:
        """An event: the run's list (summary.json) and the live view's events.jsonl (kind: runs.live.KINDS)."""
        self.journal.note(kind, text)

    @property
    def speed(self) -> float:
        return float(self.config.vehicle.speed_mps)

    def _clock_with_boots(self) -> FieldClock:
        """The clock with a ``t_boot0`` for every boot (:meth:`RunClock.with_boots`)."""
        return self.run_clock.with_boots()

    # -- summary ------------------------------------------------------------------------------
    def summary(self) -> dict:
        """summary.json's content now (see :mod:`passt_mav.runs.rundir`)."""
        return run_summary(self)

    def _n_samples(self) -> int:
        try:
            self._n_stored = self.store.count()
        except Exception:  # noqa: BLE001, S110 - closed at the end of run(): the last count stands
            pass
        if self._n_stored is None:
            return sum(int(x.get("n_samples", 0)) for x in self.leg_records)
        return int(self._n_stored)

    def _write_own_summary(self) -> None:
        self.rd.write_summary(self.summary())

    def _on_reboot(self, boot: int, last_tb: int, first_tb: int) -> None:
        """From the reader thread (SampleCollector): the vehicle's time since boot went back."""
        if self.collector is not None and self.collector.boots:
            self.collector.boots[-1].setdefault("first_tb", first_tb)
        self.session.rebooted_signal((boot, last_tb, first_tb))

    # -- the mission -----------------------------------------------------------------------------
    def run(self) -> dict:
        """Fly every leg; returns the summary (also in ``summary.json``)."""
        from passt_mav.runs.store import SampleStore

        rd = self.rd.create()
        if self.mission_text is not None and not (self.resume and rd.mission_file.exists()):
            rd.mission_file.write_text(self.mission_text)
        self.store = SampleStore(rd.samples_db)
        if self.resume:
            self.run_clock.resume_boots(self.store.all(), (self._old_summary() or {}).get("clock") or {})
        self.record.meta(live_meta(self))
        self._attach(StoreWriter(self.store, self.grid, self.link.clock))
        try:
            state, t_state, first = self._initial_state()
            self._say(
                f"mission {self.config.name}: {self.n_legs} legs of {self.config.planner.path_length} moves, "
                f"model {self.predictor_info.get('used')}, planner {self.config.planner.name}; "
                "waiting for the vehicle"
            )
            self.step.prepare(state)
            self._prepare_vehicle()
            for i in range(first, self.n_legs):
                state, t_state = self._leg(i, state, t_state)
            self.status = "complete"
            self.session.waits.finish(self.config.vehicle.on_end, self._note)
        except Stopped as exc:
            stop_by_signal(self, exc.name)
        except (Ended, Paused) as exc:  # a clean stop short of the end (passt_mav.vehicle.operator)
            self._stop_short(exc)
        except BaseException as exc:
            self.status = "aborted"
            if isinstance(exc, LinkTimeout) and "signing" not in str(exc) and "signing" in self.link.signing_hint():
                # a vehicle that requires signing ignores a keyless controller: say so, not just "timed out"
                exc = LinkTimeout(f"{exc}{self.link.signing_hint()}")
            self._note("stopped", f"aborted: {type(exc).__name__}: {exc}")
            self._safe_hold()
            raise exc  # noqa: TRY201 - exc may be the reworded LinkTimeout above
        finally:
            self.signals.disarm()  # the clean-up below must finish: later signals are only acknowledged
            self._detach()
            self.writer.close()
            self._write_summary()
            self.store.close()
            self.record.event("run_end", f"run {self.status}")
        return self.summary()

    def _attach(self, writer) -> None:
        """A :class:`SampleCollector` on this link, feeding ``writer`` (samples keyed by the vehicle's system id)."""
        from passt_mav.mavlink import SampleCollector

        self.writer = writer
        sens = self.config.sensors
        self.collector = SampleCollector(
            writer,
            u_name=sens.u,
            v_name=sens.v,
            source=f"mav:{self.link.target_system}/{self.link.target_component}",
            on_reboot=self._on_reboot,
            boot_base=self.run_clock.boot_base,
        )
        self.collector.attach(self.link)
        self.run_clock.collector = self.collector
        self._attach_operator()  # commands, budget, the vehicle's alarms (passt_mav.vehicle.operator)
        self.record.start_status(lambda: live_status(self))

    def _prepare_vehicle(self) -> None:
        """Wait for the EKF, choose the clock, set WP_RADIUS (put back by :meth:`_detach`)."""
        self.session.wait_ready(new_run=not self.resume)  # (a vehicle flying a mission already: refused)
        self.run_clock.choose()
        if self.config.vehicle.wp_radius_m > 0:
            # a Rover's acceptance radius is WP_RADIUS (it drops a waypoint's param2); put back at the end
            self.vehicle.set_wp_radius(self.config.vehicle.wp_radius_m)
        self._keep_operator_streams()  # BATTERY_STATUS, FENCE_STATUS (passt_mav.vehicle.operator)

    def _detach(self) -> None:
        """Put back the parameters we changed; stop collecting."""
        if self.vehicle.changed_params and not self.link.lost:
            try:
                restored = self.vehicle.restore_params()
            except MavlinkError as exc:
                log.warning("parameters not restored: %s", exc)
                restored = {}
            if restored:
                self._say("restored " + ", ".join(f"{k} = {v:g}" for k, v in restored.items()))
        self.collector.detach()
        self._detach_operator()
        self.record.stop_status(lambda: live_status(self))

    def _safe_hold(self) -> None:
        """HOLD if in AUTO (never raises), the leg closed first (:func:`close_leg`)."""
        close_leg(self.collector, self.link)
        self.vehicle.keep_station_if_auto()

    # -- one leg: plan -> check -> upload (transactional) -> fly -> absorb ---------------------------
    def _leg_once(self, i: int, state: np.ndarray, t_state: float) -> tuple[np.ndarray, float]:
        planned = self._plan(i, state, t_state)
        path = self._fit_budget(i, planned)  # the path, or its start that fits the safety budget (may end the run)
        with self.lock, self.signals.critical():
            wm = self._checked_mission(i, path)
            rec = self._write_plan(i, planned, wm)
        if self.config.approve.enabled:
            self._approve(i, rec, wm)
        link0, store0 = self.session.link_snapshot(), self.store.count(i)
        items = wm.items()
        upload_tries, upload_s, t_fly, tb_fly = self._swap(i, items, self.link.clock.now())
        with self.lock, self.signals.critical():
            self._write_prediction(i, planned)  # (the boat is underway meanwhile)
        duration_s, tb_end, cut = self._fly_leg(i, wm, items, t_fly)
        with self.signals.critical():  # estimate.nc, leg.json, summary.json: written whole or not begun
            times = (upload_tries, upload_s, duration_s, tb_fly, tb_end)
            absorbed = self._complete_leg(i, rec, planned, link0, store0, times, cut)
        return absorbed.state, absorbed.t_state

    def _complete_leg(self, i: int, rec: dict, planned, link0, store0, times: tuple, cut: dict | None):
        """Absorb leg ``i``'s samples and write its records (``times``: upload tries, upload s, wall s, vehicle
        uptime s at AUTO and at the end; ``cut``: the overrun record of a leg cut short, else None). Returns
        the absorbed state (:meth:`OwnState.absorb`)."""
        upload_tries, upload_s, duration_s, tb_fly, tb_end = times
        with self.lock:
            absorbed = self._absorb(i, planned)
        rec.update(absorbed.record())
        flown = (tb_end - tb_fly) if (tb_end is not None and tb_fly is not None and tb_end >= tb_fly) else None
        outages = [o for o in self.session.outages if o["leg"] == i]
        rec.update(
            {
                "status": "complete",
                "t_end": absorbed.t_state,
                "upload_s": upload_s,
                "upload_tries": upload_tries,
                "duration_s": duration_s,
                "duration_vehicle_s": flown,
                "planned_duration_vehicle_s": planned.planned_duration_vehicle_s,  # the overrun rule's expectation
                "n_samples_new": self.store.count(i) - store0,
                "link": self.session.link_record(link0),
                "readings": readings_record(self.collector, self.store.for_leg(i), i, outages),
                "outages": outages,
                "overrun": cut,
                "waits": self.session.waits.for_leg(i),
            }
        )
        self._finish_leg(i, rec, planned)
        return absorbed

    def _plan(self, i: int, state: np.ndarray, t_state: float):
        """Position -> start cell; the vehicle's clock -> forecast the state to now; plan the leg.

        The clock reading is sent to the vehicle as a STATUSTEXT first (:func:`clock_statustext`):
        the telemetry log and ArduPilot's DataFlash log keep it for a replay.
        """
        lat, lon = self.session.position()
        start = self.step.start_cell(lat, lon)
        if not self.leg_records:
            check_start_cell(self, i, start, (lat, lon))
        if self.sessions:
            self.sessions[-1]["planned"].append(i)
        tb, boot = self.run_clock.reading()
        t_now = float(self._clock_with_boots().field_time(tb, boot))
        return self.share.plan(
            i,
            state,
            t_state,
            start,
            t_now=t_now,
            send_clock=lambda k: self._send_clock(i, tb, boot, k),
            start_latlon=(lat, lon),
            clock_reading=(tb, boot),
        )

    def _send_clock(self, i: int, tb: int, boot: int, k: int) -> None:
        """The clock reading leg ``i`` is planned from, as a STATUSTEXT (:func:`clock_statustext`)."""
        self._last_clock = (i, tb, boot, k)
        try:
            self.link.statustext(clock_statustext(i, tb, boot, k))
        except MavlinkError as exc:  # a log record, not a command: a dead link shows up at the upload
            log.warning("clock STATUSTEXT not sent: %s", exc)

    def _checked_mission(self, i: int, path):
        """The :class:`WaypointMission` of leg ``i``'s grid ``path``; raises before anything is uploaded when the
        path or a waypoint leaves the grid or the geofence (region + ``geofence_margin_m``)."""
        import geo
        from passt_mav.mission.waypoints import WaypointMission

        grid, margin = self.grid, float(self.config.geofence_margin_m)
        geo.validate_path(grid, path)
        wm = WaypointMission.from_path(
            grid,
            path,
            speed=self.speed,
            wp_radius_m=self.config.vehicle.wp_radius_m,
            fence_margin_m=margin,
        )
        inside = np.asarray(grid.contains(wm.waypoints[:, 0], wm.waypoints[:, 1], margin), bool)
        if not inside.all():
            bad = int(np.flatnonzero(~inside)[0])
            self.record.event("fence_refused", f"leg {i + 1}: waypoint {bad} outside the geofence; not uploaded")
            raise PlannerError(
                f"leg {i + 1}: waypoint {bad} at {wm.waypoints[bad, 0]:.6f},{wm.waypoints[bad, 1]:.6f} "
                f"lies outside the geofence (region + {margin:g} m); nothing uploaded"
            )
        return wm

    def _write_plan(self, i: int, planned, wm) -> dict:
        """Waypoints (.waypoints, .plan) and leg.json (status flying; the budget's shortening, if any)."""
        rd = self.rd
        rd.leg_dir(i)
        wm.to_wpl(rd.waypoints_file(i))
        wm.to_plan(rd.plan_file(i))
        rec = {
            **planned.record(self.dt),
            "status": "flying",
            "waypoints": wm.waypoints.tolist(),
            "waypoint_seqs": wm.waypoint_seqs(),
            "t_now": planned.t_now,
            **({"budget_shortened": self.shortened} if self.shortened else {}),
        }
        if self._attempts.get(i):
            rec["attempts"] = self._attempts[i]
        rd.write_leg(i, rec)
        rec.update(self.share.plan_fields())
        self.leg_rec = rec
        return rec

    def _write_prediction(self, i: int, planned) -> None:
        """The model's forecast over the leg (:meth:`LegStep.forecast_leg`) to prediction.nc."""
        from passt_mav.fields.field import FlowField

        fc = self.step.forecast_leg(planned)
        times = planned.t_start + self.dt * np.arange(fc.shape[0])
        FlowField(fc, self.grid, times, self.field.time_origin, self.field.units).to_netcdf(self.rd.prediction_file(i))

    def _swap(self, i: int, items, t0w: float) -> tuple[int, float, float, float | None]:
        """The transactional leg swap (:meth:`VehicleSession.swap`)."""

        def on_armed():
            if self._last_clock is not None and self._last_clock[0] == i:
                # again: ArduPilot starts its DataFlash log at arming (LOG_DISARMED 0), after the
                # first one; a replay of the .bin then finds this leg's clock reading too
                self._send_clock(*self._last_clock)

        def on_start():
            self.session.waits.end()  # (the wait since the last leg's end, or the approval's: its drift in leg.json)
            self.collector.leg = i

        return self.session.swap(i, items, t0w, on_armed=on_armed, on_start=on_start)

    def _fly_leg(self, i: int, wm, items, t_fly: float) -> tuple[float, float | None, dict | None]:
        """Fly until the mission completes (or the leg is cut for an overrun), then HOLD; returns (wall s,
        vehicle uptime s at the end, the overrun record of a cut leg or None)."""
        expected = self._expected_vehicle_s(wm)
        tb0 = self.link.vehicle_uptime_s()
        self.live_leg = (i, (tb0 or 0.0) + expected)
        self.record.event("leg_start", f"{self._leg_label(i)} started ({len(wm.waypoints)} waypoints)")
        try:
            how = self._fly(i, wm, items, len(items) - 1)  # MISSION_CURRENT.total excludes home
        except BaseException:
            close_leg(self.collector, self.link)  # (a stop, an end, a pause: their own paths command the vehicle)
            raise
        end_leg_at_wait(self.link, self.vehicle, self.collector)
        self.vehicle.keep_station()
        self.session.waits.begin("between legs", i + 1)
        cut = None if how != "cut" else overrun_record(expected, self.config.vehicle, self.vehicle.progress, items)
        self._mark_cut(how)  # the operator's skip/replan, the budget's cut: in the leg record
        duration_s = self.link.clock.now() - t_fly
        tb_end = self.link.vehicle_uptime_s()
        # the leg's last readings wait for the fix after them (<= the gap bound of vehicle time)
        place_held(self.collector, i, self.speedup)
        self.writer.flush()
        if how == "replan":
            raise Replan()
        return duration_s, tb_end, cut

    def _expected_vehicle_s(self, wm) -> float:
        """Vehicle seconds the leg should take (:meth:`LegStep.expected_vehicle_s`: in the forecast current); in
        still water (``planner.current_aware`` false, or a move the forecast makes impossible: infinite) else."""
        still = expected_vehicle_s(self.grid, wm, self.speed)
        out = self.step.expected_vehicle_s((self.leg_rec or {}).get("index"), wm.meta.get("cells"), self.speed, still)
        return out if np.isfinite(out) and out > 0 else still

    def _fly(self, i: int, wm, items, n_items: int) -> str | None:
        """Wait for the leg to complete, its faults handled (:meth:`VehicleSession.fly`; ``"cut"``: an overrun)."""
        return self.session.fly(i, items, n_items, self._expected_vehicle_s(wm))

    def _absorb(self, i: int, planned):
        """The leg's stored samples through the state keeper (:meth:`OwnState.absorb`); the estimate to estimate.nc."""
        from passt_mav.fields.field import FlowField

        recs, clock = self.store.for_leg(i), self._clock_with_boots()
        try:
            absorbed = self._update(planned, recs, clock)
        except ReconstructionError as exc:
            heard = self.collector.leg_counts(i)["readings"] > 0 or any(o["leg"] == i for o in self.session.outages)
            if isinstance(self.share, OwnState) and heard:
                # the sensor works but the link lost most of the leg's readings: the few left cannot update the
                # state, the forecast carries it on (as a replay of the log does) and the mission goes on
                absorbed = self.step.absorb(planned, recs, clock, strict=False)
                self._note("warning", f"leg {i + 1}: only {len(recs)} samples (link outage or loss): {absorbed.note}")
                self._say(f"{self._leg_label(i)}: only {len(recs)} samples (link outage or loss); {absorbed.note}")
            else:
                raise MavlinkError(
                    f"leg {i + 1}: no current samples arrived (is the sensor sending "
                    f"{self.config.sensors.u}/{self.config.sensors.v}?): {exc}"
                ) from None
        std = None if absorbed.std is None else absorbed.std[None]
        FlowField(
            absorbed.state[None], self.grid, np.array([absorbed.t_state]), self.field.time_origin, self.field.units
        ).to_netcdf(self.rd.estimate_file(i), std=std)
        return absorbed

    def _update(self, planned, recs, clock):
        """The state update of a leg (:meth:`OwnState.absorb`; a fleet's boat shares one state)."""
        return self.share.absorb(planned, recs, clock)

    def _finish_leg(self, i: int, rec: dict, planned) -> None:
        """leg.json (complete), timings.json, summary.json, and one line of progress."""
        rec.update(self.share.finish_fields())
        self.rd.write_leg(i, rec)
        self.rd.write_timings(
            i,
            {
                "planning_s": rec["planning_s"],
                **{f"{k}_s": x for k, x in planned.plan.timings.items()},
                "upload_s": rec["upload_s"],
                "leg_s": rec["duration_s"],
            },
        )
        self.leg_records = [x for x in self.leg_records if int(x["index"]) != i] + [rec]
        self._write_summary()
        self.record.event("leg_end", f"{self._leg_label(i)} done: {rec['n_samples']} samples")
        self._say(f"{self._leg_label(i)}: {_progress_line(rec, speed_unit(self.config.field.velocity_scale))}")
        unit = speed_unit(self.config.field.velocity_scale)
        for kind, level, text in leg_warnings(rec, self._leg_label(i), unit, self.speed):
            self.record.event(kind, text, level=level)
            self._say(("WARNING: " if level == "warn" else "") + text)
        self.share.leg_done()

    def _leg_label(self, i: int) -> str:
        """How leg ``i`` (0-based) is named in progress lines."""
        return self.share.label(i, self.n_legs)


def readings_record(collector, recs, i: int, outages=()) -> dict:
    """Sensor readings of leg ``i`` (``recs``: its stored samples): received (u/v pairs), used (placed on the
    track), dropped (gap); ``missing``: readings the sensor sent in the leg's span that are not in the store
    (:func:`missing_readings`, per boot: lost on the link, in an outage or to a position gap); and the vehicle
    seconds without a link (``outages``: :attr:`VehicleSession.outages` of the leg)."""
    c = collector.leg_counts(i)
    by_boot: dict[int, list[int]] = {}
    for r in recs:
        by_boot.setdefault(int(r.boot), []).append(int(r.time_boot_ms))
    return {
        "missing": int(sum(missing_readings(np.asarray(v)) for v in by_boot.values())),
        "lost_in_outages_vehicle_s": round(sum(float(o.get("vehicle_s") or 0.0) for o in outages), 3),
        "received": c["readings"],
        "used": c["emitted"],
        "dropped_gap": c["gap"],
        "fraction_used": (c["emitted"] / c["readings"]) if c["readings"] else None,
        "max_gap_ms": collector.track.max_gap_ms,
    }


def overrun_record(expected_s: float, vehicle_cfg, progress, items) -> dict:
    """The record of a leg cut for an overrun: its expected vehicle seconds, the mission's factor, the item it
    was cut at and the leg's items (home excluded)."""
    return {
        "expected_vehicle_s": round(expected_s, 3),
        "factor": vehicle_cfg.overrun_factor,
        "cut_at_item": int(progress.current),
        "items": len(items) - 1,
    }


def stop_by_signal(ctl, name: str) -> None:
    """Controller ``ctl`` stopped by signal ``name`` (SIGINT, SIGTERM): status ``stopped``, the vehicle held (or
    left in AUTO with ``vehicle.on_signal: auto``), the leg's last readings placed; ``--resume`` continues."""
    ctl.signals.disarm()
    ctl.status, ctl.stopped_by = "stopped", name
    leave = ctl.config.vehicle.on_signal == "auto"
    what = "the vehicle left flying its leg in AUTO (vehicle.on_signal: auto)" if leave else ctl.vehicle.wait_mode
    ctl._note("stopped", f"stopped by {name} at {utc_now()}: {what}; continue with --resume")
    ctl._say(f"stopped by {name}: {what}; store flushed, summary written; continue with --resume")
    if leave:
        close_leg(ctl.collector, ctl.link)
    else:  # HOLD whatever the mode seen last: a stop during the swap may precede AUTO's heartbeat
        # the leg closes and the first HOLD is sent under the reader's dispatch lock, as at a leg's end, so no
        # reading is logged before that HOLD but kept out of the leg (a replay ends the leg there)
        end_leg_at_wait(ctl.link, ctl.vehicle, ctl.collector)
        ctl.vehicle.keep_station_if_auto(always=True)
    place_held(ctl.collector, None if ctl.link.lost else ctl.live_leg[0], ctl.speedup)


def end_leg_at_wait(link, vehicle, collector) -> None:
    """The leg's readings end where the telemetry log shows it: no reading is logged and routed between the
    collector's leg closing, its ``end`` mark (:func:`~passt_mav.vehicle.leg_marks.close_leg`) and the first mode
    command sent (the vehicle's :attr:`~Vehicle.wait_mode`: LOITER or HOLD; the reader's dispatch lock held over
    all three), so a replay, which ends the leg at the mark (in older logs at that command), assigns every reading
    as the store did. :meth:`Vehicle.keep_station` confirms the mode afterwards. A failed send (the link down)
    leaves the mode change to that call."""
    with link.dispatch_lock:
        close_leg(collector, link)
        try:
            vehicle.request_mode(vehicle.wait_mode)
        except Exception as exc:  # noqa: BLE001 - the confirming keep_station() reports and handles it
            log.debug("%s request at the leg's end not sent: %s", vehicle.wait_mode, exc)


def missing_readings(tb_ms: np.ndarray) -> int:
    """Readings a regular sensor sent within the span of ``tb_ms`` (one boot's ``time_boot_ms`` of the readings
    kept, ms) that are not among them: the spacing is the median step, and each step longer than 1.5 x it
    holds ``round(step / spacing) - 1`` readings that never arrived (or were not placed). 0 below 3 readings."""
    t = np.unique(np.asarray(tb_ms, np.int64))
    if t.size < 3:
        return 0
    d = np.diff(t)
    period = float(np.median(d))
    if period <= 0:
        return 0
    big = d[d > 1.5 * period]
    return int(np.sum(np.round(big / period) - 1))


def _planned_s(rec: dict) -> str:
    """``", planned N s"``: the vehicle seconds the leg was expected to take (empty when not recorded)."""
    p = rec.get("planned_duration_vehicle_s")
    return "" if p is None else f", planned {p:.0f} s"


#: a leg whose flown vehicle time is off its planned time by more than this factor (either way) is said
TIMING_WARN_FACTOR = 1.25


def leg_warnings(rec: dict, label: str, unit: SpeedUnit, speed_mps: float) -> list[tuple[str, str, str]]:
    """What a completed leg's record ``rec`` gives to warn about, as (event kind, level, line): the guard (the
    forecast alone fitted the samples better: :mod:`passt_mav.loop.guard`); a map that does not beat the trivial
    maps (no current, the forecast's time mean: :func:`passt_mav.loop.scoring.beaten_message`; truth known); a
    leg flown in a time off its planned one by more than :data:`TIMING_WARN_FACTOR` (the plan is timed in the
    forecast current at ``speed_mps`` over ground, so the current explains the rest: the speed asked was not
    flown, or the current was not the forecast's; a leg cut for an overrun, or whose end was seen late through a
    link outage, is said elsewhere)."""
    from passt_mav.loop.scoring import beaten_message

    out = []
    guard = rec.get("guard") or {}
    if guard.get("message"):
        out.append(("guard", "warn" if guard.get("alarm") else "info", guard["message"]))
    beaten = beaten_message(rec.get("baselines"), label, unit.text)
    if beaten:
        out.append(("warning", "warn", beaten))
    flown, planned = rec.get("duration_vehicle_s") or 0.0, rec.get("planned_duration_vehicle_s") or 0.0
    off = bool(flown and planned) and not 1 / TIMING_WARN_FACTOR <= flown / planned <= TIMING_WARN_FACTOR
    if off and not (rec.get("overrun") or rec.get("outages")):
        text = (
            f"{label}: flown in {flown:.0f} s of vehicle time, planned {planned:.0f} s in the forecast current "
            f"(x {flown / planned:.2f}): the boat did not make the speed asked ({speed_mps:g} m/s "
            "over ground; check WP_SPEED, vehicle.max_water_speed_mps) or the current was not the forecast's"
        )
        out.append(("warning", "warn", text))
    return out


def _progress_line(rec: dict, unit: SpeedUnit) -> str:
    """A completed leg's figures in one line of progress (after its label); RMSEs (recorded in field units)
    in ``unit`` (m/s for a mission: :mod:`passt_mav.units`)."""
    r_p, r_m, link = rec["rmse_passt"], rec["rmse_model"], rec["link"]
    rm = "" if r_p is None else f", RMSE passt {unit.text(r_p)} model {unit.text(r_m)}"
    cal = rec.get("calibration") or {}
    if cal.get("coverage95") is not None:  # the map's std against the truth (passt_mav.loop.scoring)
        rm += f", 95 % interval holds {100 * cal['coverage95']:.0f} % (NLPD {cal['nlpd']:.2f})"
    rtt = "-" if link["rtt_ms"] is None else f"{link['rtt_ms']:.1f} ms"
    rd = rec.get("readings") or {}
    used = "" if not rd.get("received") else f" of {rd['received']} readings ({100 * rd['fraction_used']:.0f} % used)"
    return (
        f"{rec['n_samples']} samples{used} ({rec['n_gp_points']} to the GP), "
        f"{rec['duration_s']:.1f} s wall ({rec['duration_vehicle_s'] or 0:.0f} s vehicle{_planned_s(rec)}), planning "
        f"{rec['planning_s'] * 1000:.0f} ms, upload {rec['upload_s']:.2f} s{rm}, link RTT {rtt} "
        f"loss {100 * link['loss']:.1f} %"
        + ("" if link.get("vehicle_bytes_per_s") is None else f", vehicle sends {link['vehicle_bytes_per_s']:.0f} B/s")
    )


def check_start_cell(ctl, i: int, start: tuple[int, int], latlon: tuple[float, float]) -> None:
    """One line (console and event) when controller ``ctl``'s first leg ``i`` cannot start at the mission's
    ``start_cell`` (a fleet's boat: its ``vehicles[k].start_cell``) because the boat, at ``latlon`` (deg),
    is in cell ``start`` (row, col): a leg starts where the boat is, and the controller does not drive it
    to that cell first."""
    import geo

    cfg = ctl.config
    wanted = cfg.vehicle.start_cell
    if wanted is None and cfg.vehicles is None:
        wanted = cfg.start_cell
    if wanted is None or tuple(int(x) for x in wanted) == tuple(start):
        return
    key = "start_cell" if cfg.vehicles is None else "vehicles[].start_cell"
    w_lat, w_lon = (float(x) for x in ctl.grid.cell_to_latlon(int(wanted[0]), int(wanted[1])))
    far = float(geo.geodesic_distance_m(latlon[0], latlon[1], w_lat, w_lon))
    text = (
        f"{key} {list(wanted)} not honoured: leg {i + 1} starts at cell {list(start)} "
        f"({latlon[0]:.5f},{latlon[1]:.5f}), where the boat is, {far:.0f} m from {list(wanted)}: a leg "
        f"starts at the boat's position (a simulator: vehicle-sim --start-cell {wanted[0]},{wanted[1]}; "
        "a boat: bring it there before the run)"
    )
    ctl._say(f"WARNING: {text}")
    ctl._note("warning", text)


def _budget_record(ctl) -> dict | None:
    """The safety budget's figures (:meth:`SafetyBudget.record`), None when no limit is set."""
    b = getattr(getattr(ctl, "session", None), "budget", None)
    return b.record() if b is not None and b.watched else None


def run_summary(ctl) -> dict:
    """summary.json of controller ``ctl`` now: the mission, its settings, every leg record, RMSE over time
    (field units) where the truth is known, the clock, the events (keys: :mod:`passt_mav.runs.rundir`)."""
    cfg = ctl.config
    legs = [dict(x) for x in ctl.leg_records]
    rm = {
        "t": [x.get("t_end") for x in legs],
        "passt": [x.get("rmse_passt") for x in legs],
        "model": [x.get("rmse_model") for x in legs],
    }
    s = {
        "mission": cfg.name,
        "status": ctl.status,
        "started_utc": ctl.started_utc,
        "finished_utc": utc_now() if ctl.status != "running" else None,
        "field": cfg.field.source,
        "field_time_origin": ctl.field.time_origin,
        "grid": ctl.grid.describe(),
        "model": ctl.predictor_info.get("used"),
        "model_requested": ctl.predictor_info.get("requested"),
        "model_fallback": ctl.predictor_info.get("fallback"),
        "planner": cfg.planner.name,
        "reward": cfg.planner.reward,
        "path_length": cfg.planner.path_length,
        "seeds": cfg.seeds.model_dump(),
        "config": cfg.model_dump(mode="json"),
        "legs_planned": ctl.n_legs,
        "legs": legs,
        "n_samples": ctl._n_samples(),
        "readings_used": [(x.get("readings") or {}).get("fraction_used") for x in legs],
        "stopped_by": getattr(ctl, "stopped_by", None),
        "machine_faults": machine_faults_record(ctl),  # a store or telemetry log the machine failed
        "sessions": list(getattr(ctl, "sessions", None) or []),
        "outages": list(getattr(getattr(ctl, "session", None), "outages", None) or []),
        "budget": _budget_record(ctl),
        "end": getattr(getattr(getattr(ctl, "session", None), "waits", None), "end_state", None),
        "link_vehicle_bytes_per_s": [(x.get("link") or {}).get("vehicle_bytes_per_s") for x in legs],
        "rmse": rm if ctl.truth_known else None,
        "rmse_note": "RMSE over water cells vs the mission's field at the state time; 'model' = the predictor "
        "alone from the true state at t0, never re-initialised"
        if ctl.truth_known
        else None,
        # what programs read stays in the loop's units; people read m/s (passt_mav.units)
        "rmse_units": "field units (times config.field.velocity_scale = m/s), as leg.json's rmse_passt/rmse_model"
        if ctl.truth_known
        else None,
        "clock": ctl._clock_with_boots().describe(),
        "thinning": THINNING,
        "dt": ctl.dt,
        "connect": ctl.link.config.connect,
        "events": list(ctl.events),
    }
    s.update(ctl.extra_summary)
    return s
