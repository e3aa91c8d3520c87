"""The mission controller: the PASST loop flown by a live vehicle over MAVLink.

One :class:`MissionController` runs one mission (``passt-mav run`` / ``passt-mav
demo``). It reuses :class:`passt_mav.passt.PasstLoop` unchanged; only the sampler
differs: instead of reading the ground-truth field, each leg is uploaded to the
vehicle and flown, and the current samples it streams back are the leg's samples.
Everything between two legs is :class:`passt_mav.legstep.LegStep` (pure, shared with
``passt-mav replay``); this module adds the vehicle.

Per leg ``i`` (:meth:`MissionController._leg`: plan -> check -> upload -> fly -> absorb)::

    _plan:   position -> start cell; clock reading -> STATUSTEXT "PASST leg i tb T b B k K"
             (kept by the tlog and ArduPilot's DataFlash log) -> LegStep.plan
    _checked_mission: WaypointMission, geofence check of every waypoint (abort before upload)
    _swap:   HOLD, upload + read-back, set_current(1), arm if needed, AUTO (transactional)
    _fly_leg: collect samples until the mission completes (faults handled, see below) -> HOLD
    _absorb: LegStep.absorb (thin, GP update, RMSE) -> estimate.nc; _finish_leg: records

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
t_state) / dt)`` snapshots forward. A leg spans ``steps_for_leg(L, cell_size,
speed, dt * time_scale)`` snapshots (at least 1); after it the reconstruction is
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

Faults. Link loss during a leg: the link is reconnected with back-off
(:meth:`Link.reconnect`), the mission is downloaded and compared with the one
uploaded (re-uploaded if it differs) and the leg goes on from MISSION_CURRENT;
samples keep flowing into the store (the collector listens on the same link
object). Link loss during the leg swap (HOLD, upload, set-current, arm, AUTO): the
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
that was in flight is re-planned from the current position.
"""

from __future__ import annotations

import datetime as _dt
import logging
import queue
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np

from passt_mav.errors import LinkTimeout, MavlinkError, PlannerError, ReconstructionError, UserError
from passt_mav.live_record import field_time_now, live_meta, live_status
from passt_mav.runs.legs import clock_statustext
from passt_mav.runs.live import RecordWriter
from passt_mav.legstep import (  # noqa: F401 - the between-leg step's building blocks, re-exported
    THINNING, FieldClock, LegStep, build_loop, build_predictor, extend_leg_to_end, leg_steps, pure_model_at, rmse,
    thin_samples, to_field_units, truth_at, utc_epoch)

__all__ = [
    "FieldClock",
    "MissionController",
    "thin_samples",
    "build_predictor",
    "build_loop",
    "rmse",
    "THINNING",
]

log = logging.getLogger(__name__)

def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")


class _StoreWriter:
    """Appends samples to the store from a thread of its own: the link's reader thread only queues them."""

    def __init__(self, store, grid):
        self.store, self.grid = store, grid
        self.q: queue.Queue = queue.Queue()
        self.new = 0
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._loop, name="sample-store", daemon=True)
        self._th.start()

    def __call__(self, rec: dict) -> None:
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
            rows = []
            for rec in batch:
                r, c = self.grid.latlon_to_cell(rec["lat"], rec["lon"], clip=True)
                rows.append({"time_boot_ms": int(rec["time_boot_ms"]), "utc": float(rec["utc"]), "lat": rec["lat"],
                             "lon": rec["lon"], "u": rec["u"], "v": rec["v"], "leg": int(rec.get("leg", -1)),
                             "source": rec.get("source", "mavlink"), "row": int(r), "col": int(c),
                             "boot": int(rec.get("boot", 0)), "gap_ms": rec.get("gap_ms")})
            try:
                self.new += self.store.append_many(rows)
            except Exception:  # noqa: BLE001 - a store failure must be seen, but must not kill the thread
                log.exception("could not store %d samples", len(rows))

    def flush(self, timeout: float = 5.0) -> None:
        end = time.monotonic() + timeout
        while (not self.q.empty()) and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(0.02)  # the batch taken last is being committed

    def close(self) -> None:
        self.flush()
        self._stop.set()
        self._th.join(timeout=5.0)


class _Paused(Exception):
    """The vehicle left AUTO and did not come back in time (or rebooted with on_reboot: hold)."""


class _Rebooted(Exception):
    """The autopilot rebooted: handled by the leg in flight."""


# -- the controller ---------------------------------------------------------------------------
class _Deadline:
    """A leg's time limit, kept in the vehicle's time: ``budget_s`` vehicle seconds from now.

    A sped-up simulator starved of CPU runs slower than its nominal speed-up; a wall-clock
    limit would then fail legs that are fine. The wall clock only backs it up, ten times more
    generous (a vehicle whose clock stops: a frozen simulator, a dead link)."""

    def __init__(self, link, budget_s: float, speedup: float):
        self.link, self.speedup = link, max(float(speedup), 1e-6)
        self.last_up = link.vehicle_uptime_s()
        self.vehicle = None if self.last_up is None else self.last_up + budget_s
        self.wall = time.monotonic() + 10.0 * budget_s / self.speedup + 60.0

    def extend(self, wall_s: float, *, rebooted: bool = False) -> None:
        """Add ``wall_s`` of waiting (reconnect, reboot, pilot). After a reboot the vehicle's clock
        started again: what was left of the budget counts from its new time."""
        self.wall += wall_s
        if self.vehicle is None:
            return
        if rebooted:
            left = self.vehicle - (self.last_up or 0.0)
            up = self.last_up = self.link.vehicle_uptime_s()
            self.vehicle = None if up is None else up + left
        else:
            self.vehicle += wall_s * self.speedup

    def passed(self) -> bool:
        up = self.link.vehicle_uptime_s()
        if up is not None and (self.last_up is None or up >= self.last_up):  # (a reboot's restart: see extend)
            self.last_up = up
        return time.monotonic() > self.wall or (self.vehicle is not None and up is not None and up > self.vehicle)


class MissionController:
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
    """

    def __init__(self, config, link, run_dir, *, field, predictor, predictor_info: dict | None = None, vehicle=None,
                 legs: int | None = None, field_time_at_boot: float | None = None, speedup_hint: float = 1.0,
                 pause_timeout_s: float = 300.0, ready_timeout_s: float = 120.0, resume: bool = False,
                 truth_known: bool = True, echo: Callable[[str], None] | None = print, mission_text: str | None = None,
                 extra_summary: dict | None = None):
        from passt_mav.mavlink import Vehicle

        self.config = config
        self.link = link
        self.rd = run_dir
        self.field = field
        self.grid = field.grid
        self.predictor = predictor
        self.predictor_info = predictor_info or {"requested": config.model, "used": config.model, "fallback": None}
        self.vehicle = vehicle or Vehicle(link)
        self.n_legs = int(legs or config.legs)
        if field.n_times < 2:
            raise UserError("the mission's field needs at least 2 snapshots (dt)")
        if not 0 <= config.t0 < field.n_times - 1:
            raise UserError(f"t0={config.t0} lies outside the field's {field.n_times} snapshots")
        self.dt = float(field.dt)
        self.clock = FieldClock(float(field.times[config.t0]) if field_time_at_boot is None else float(field_time_at_boot),
                                float(config.field.time_scale))
        self.speedup = max(float(speedup_hint), 1e-6)
        self.pause_timeout_s = float(pause_timeout_s)
        self.ready_timeout_s = float(ready_timeout_s)
        self.resume = resume
        self.truth_known = truth_known
        self.echo = echo or (lambda s: None)
        self.mission_text = mission_text
        self.extra_summary = dict(extra_summary or {})
        self.land = field.land_mask
        self.loop = build_loop(config, predictor, self.grid, land=self.land)  # keeps the GP std: estimate.nc u_std/v_std (exports, live view)
        self.step = LegStep(config, field, self.loop, truth_known=truth_known)
        self.leg_records: list[dict] = []
        self.status = "running"
        self.started_utc = _utc_now()
        self.store = None
        self.collector = None
        self.writer = None
        self.events: list[str] = []
        self.record = RecordWriter(run_dir.root)  # the live view's files (passt_mav.runs.live)
        self.record.field_time = lambda: field_time_now(self)
        self._time_at_boot_arg = field_time_at_boot
        self._rebooted = threading.Event()
        self._reboot_info: tuple[int, int, int] | None = None
        self._resume_seq = 1
        # resume: samples of earlier sessions keep their boot numbers; this session's boots count from
        # _boot_base (so a vehicle rebooted while we were away cannot reuse their keys), and
        # _old_anchors holds t_boot0 of boots 0.._boot_base-1 (from the old summary)
        self._boot_base = 0
        self._old_anchors: list[float] = []

    # -- helpers --------------------------------------------------------------------------
    def _say(self, s: str) -> None:
        self.echo(s)
        log.info(s)

    def _note(self, kind: str, text: str) -> None:
        """An event: the run's list (summary.json) and the live view's events.jsonl (kind: runs.live.KINDS)."""
        self.events.append(text)
        self.record.event(kind, text)

    @property
    def speed(self) -> float:
        return float(self.config.vehicle.speed_mps)

    def _position(self, timeout: float = 10.0) -> tuple[float, float]:
        end = time.monotonic() + timeout
        while (p := self.vehicle.position()) is None:
            if time.monotonic() > end:
                raise MavlinkError("no GPS position from the vehicle")
            time.sleep(0.02)
        return p

    def _link_snapshot(self) -> tuple:
        st = self.link.stats
        return st.received, st.drops, st.vehicle_bytes, self.link.vehicle_uptime_s()

    def _link_record(self, before: tuple) -> dict:
        """Link figures since ``before``; ``vehicle_bytes_per_s``: bytes the vehicle sent us per second of its
        own clock (the telemetry radio's budget: baud / 10 bytes/s each way), None without a vehicle clock."""
        st = self.link.stats
        rec, drops = st.received - before[0], st.drops - before[1]
        nbytes, t1 = st.vehicle_bytes - before[2], self.link.vehicle_uptime_s()
        rtt = self.link.rtt
        bps = nbytes / (t1 - before[3]) if t1 is not None and before[3] is not None and t1 - before[3] > 1.0 else None
        return {"rtt_ms": None if rtt is None else round(rtt * 1000.0, 3),
                "loss": (drops / (rec + drops)) if rec + drops else 0.0, "messages": int(rec), "drops": int(drops),
                "vehicle_bytes": int(nbytes), "vehicle_bytes_per_s": None if bps is None else round(bps, 1)}

    def _readings_record(self, i: int) -> dict:
        """Sensor readings of leg ``i``: received (u/v pairs), used (placed on the track), dropped (gap)."""
        c = self.collector.leg_counts(i)
        return {"received": c["readings"], "used": c["emitted"], "dropped_gap": c["gap"],
                "fraction_used": (c["emitted"] / c["readings"]) if c["readings"] else None,
                "max_gap_ms": self.collector.track.max_gap_ms}

    # -- summary ------------------------------------------------------------------------------
    def summary(self) -> dict:
        cfg = self.config
        legs = [dict(x) for x in self.leg_records]
        rm = {"t": [x.get("t_end") for x in legs], "passt": [x.get("rmse_passt") for x in legs],
              "model": [x.get("rmse_model") for x in legs]}
        s = {
            "mission": cfg.name, "status": self.status, "started_utc": self.started_utc,
            "finished_utc": _utc_now() if self.status != "running" else None,
            "field": cfg.field.source, "field_time_origin": self.field.time_origin, "grid": self.grid.describe(),
            "model": self.predictor_info.get("used"), "model_requested": self.predictor_info.get("requested"),
            "model_fallback": self.predictor_info.get("fallback"), "planner": cfg.planner.name,
            "reward": cfg.planner.reward, "path_length": cfg.planner.path_length,
            "seeds": cfg.seeds.model_dump(), "config": cfg.model_dump(mode="json"),
            "legs_planned": self.n_legs, "legs": legs,
            "n_samples": self._n_samples(),
            "readings_used": [(x.get("readings") or {}).get("fraction_used") for x in legs],
            "link_vehicle_bytes_per_s": [(x.get("link") or {}).get("vehicle_bytes_per_s") for x in legs],
            "rmse": rm if self.truth_known else None,
            "rmse_note": "RMSE over water cells vs the mission's field at the state time; 'model' = the predictor "
                         "alone from the true state at t0, never re-initialised" if self.truth_known else None,
            "clock": self._clock_with_boots().describe(),
            "thinning": THINNING, "dt": self.dt, "connect": self.link.config.connect,
            "events": list(self.events),
        }
        s.update(self.extra_summary)
        return s

    def _n_samples(self) -> int:
        try:
            self._n_stored = self.store.count()
        except Exception:  # noqa: BLE001 - closed at the end of run(): the last count stands
            pass
        return int(getattr(self, "_n_stored", sum(int(x.get("n_samples", 0)) for x in self.leg_records)))

    def _write_summary(self) -> None:
        self.rd.write_summary(self.summary())

    # -- resume ------------------------------------------------------------------------------------
    def _initial_state(self) -> tuple[np.ndarray, float, int]:
        """(state, t_state, first leg index)."""
        state, t_state = self.step.initial_state()
        if not self.resume:
            return state, t_state, 0
        from passt_mav.fields.field import load_field

        done = [r for r in self.rd.read_legs() if r.get("status") == "complete"]
        done.sort(key=lambda r: int(r["index"]))
        # legs must be contiguous from 0: a gap means the directory is not one run
        done = [r for k, r in enumerate(done) if int(r["index"]) == k]
        if self.rd.summary_file.exists():
            old = self.rd.read_summary()
            clk = old.get("clock") or {}
            if "t_boot0" in clk and clk.get("source", "boot") == "boot":
                # a boot clock cannot be re-read from the vehicle: keep the run's own (a UTC clock is read
                # again), for the boot the vehicle was on when the run stopped (see _resume_boots)
                t_boot0 = self._old_anchors[-1] if self._old_anchors else float(clk["t_boot0"])
                if getattr(self, "_rebooted_since", None) is not None:
                    tb_last, up_now = self._rebooted_since
                    # no clock to tell how long it was off: continue from the last sample (the gap is not counted)
                    t_boot0 += tb_last / 1000.0 / self.clock.time_scale
                    self._say(f"WARNING: the vehicle rebooted since the run stopped and the mission maps time since "
                              f"boot: field time continues from the last sample ({t_boot0:.1f}); the time it was "
                              "off is not counted")
                self.clock = FieldClock(t_boot0, float(clk.get("time_scale", self.clock.time_scale)))
                self._clock_fixed = True
            self.started_utc = old.get("started_utc") or self.started_utc
            self.events = list(old.get("events") or []) + self.events  # (+ what _resume_boots found)
        self.leg_records = done
        if not done:
            # killed during leg 0: still say so (the store keeps that leg's samples; it is re-planned)
            self._say(f"resuming {self.rd.root}: no leg completed yet; leg 0 is re-planned from here")
            self.events.append(f"resumed before leg 0 completed at {_utc_now()}")
            return state, t_state, 0
        last = done[-1]
        est = self.rd.estimate_file(int(last["index"]))
        if not est.exists():
            raise UserError(f"cannot resume: {est} is missing")
        fld = load_field(est)
        self.loop.leg_index = len(done)
        self._say(f"resuming {self.rd.root}: {len(done)} leg(s) done, state at field time {last['t_state']:.1f}")
        self.events.append(f"resumed after leg {len(done) - 1} at {_utc_now()}")
        return np.array(fld.data[0], dtype=np.float32), float(last["t_state"]), len(done)

    # -- clock -------------------------------------------------------------------------------------
    def _vehicle_utc_boot(self, timeout: float) -> float | None:
        """The vehicle's UTC at boot (SYSTEM_TIME ``time_unix_usec/1e6 - time_boot_ms/1e3``), None without one."""
        end = time.monotonic() + timeout
        while True:
            st = self.link.latest("SYSTEM_TIME")
            if st is not None and st.time_unix_usec > 0:
                return st.time_unix_usec / 1e6 - st.time_boot_ms / 1e3
            if time.monotonic() >= end:
                return None
            time.sleep(0.02)

    def _choose_clock(self) -> None:
        """Set :attr:`clock` (module docstring, "Clock") once the vehicle is ready."""
        mode = getattr(self.config.field, "clock", "auto")
        scale = float(self.config.field.time_scale)
        if self._time_at_boot_arg is not None or getattr(self, "_clock_fixed", False):
            self._say_clock()
            return
        if mode == "boot":
            self._say_clock()
            return
        origin = self.field.time_origin
        why = None
        utc_boot = None
        if origin is None:
            why = "the field has no UTC time origin"
        else:
            # SYSTEM_TIME comes at 1 Hz of vehicle time by default (0.2 Hz in LEAN_STREAMS)
            utc_boot = self._vehicle_utc_boot(max(1.0, 6.0 / self.speedup))
            if utc_boot is None:
                why = "the vehicle sends no UTC (SYSTEM_TIME time_unix_usec = 0)"
        if why is None:
            t_boot0 = (utc_boot - utc_epoch(origin)) / scale
            up = self.link.vehicle_uptime_s() or 0.0
            t_now = t_boot0 + up / scale
            times = self.field.times
            if not times[0] <= t_now <= times[-1]:
                when = _dt.datetime.fromtimestamp(utc_boot + up, _dt.timezone.utc).isoformat(timespec="seconds")
                why = f"the vehicle's UTC {when} lies outside the field's snapshots ({origin} + {times[0]:g}..{times[-1]:g} s)"
            else:
                self.clock = FieldClock(float(t_boot0), scale, source="utc")
                self._say_clock()
                return
        if mode == "utc":
            raise UserError(f"field.clock is utc but {why}; set field.clock: boot (or give --field-time-at-boot) "
                            "to map the vehicle's time since boot instead")
        self._say(f"clock: {why}; field time at vehicle boot = snapshot t0 ({self.clock.t_boot0:g})")
        self.events.append(f"clock: boot ({why})")

    def _say_clock(self) -> None:
        c = self.clock
        up = self.link.vehicle_uptime_s()
        now = "" if up is None else f", now {float(c.field_time(up * 1000.0)):.1f}"
        self._say(f"clock: {c.source}; field time at vehicle boot {c.t_boot0:.1f}{now}")

    def _resume_boots(self) -> None:
        """On resume: boot numbering and earlier boots' anchors from the store and the old summary."""
        recs = self.store.all()
        if not recs:
            return
        b_last = max(int(r.boot or 0) for r in recs)
        tb_last = max(int(r.time_boot_ms) for r in recs if int(r.boot or 0) == b_last)
        clk = (self.rd.read_summary().get("clock") or {}) if self.rd.summary_file.exists() else {}
        anchors = [float(clk.get("t_boot0", self.clock.t_boot0))] + [float(x) for x in clk.get("later_boots") or []]
        anchors += [anchors[-1]] * (b_last + 1 - len(anchors))  # boots the old summary never recorded
        self._old_anchors = anchors[:b_last + 1]
        self._boot_base = b_last + 1
        up = self.link.vehicle_uptime_s()
        if up is not None and up * 1000.0 + 3000.0 < tb_last:
            self._rebooted_since = (tb_last, up)
            self.events.append(f"resume: the vehicle rebooted since the run stopped (uptime {up:.0f} s, last "
                               f"sample at {tb_last / 1000:.0f} s)")

    def _clock_with_boots(self) -> FieldClock:
        """:attr:`clock` with a ``t_boot0`` for every boot (earlier sessions', then the collector's; see
        module docstring)."""
        boots = list(self.collector.boots) if self.collector is not None else []
        if len(boots) <= 1 and not self._old_anchors:
            return self.clock
        session = self._session_anchors(boots)
        full = self._old_anchors + session
        return FieldClock(full[0], self.clock.time_scale, self.clock.source, tuple(full[1:]))

    def _session_anchors(self, boots: list[dict]) -> list[float]:
        """``t_boot0`` of each boot this session has seen (the first is :attr:`clock`'s)."""
        if len(boots) <= 1:
            return [self.clock.t_boot0]
        c, scale = self.clock, self.clock.time_scale
        anchors = [c.t_boot0]
        for k in range(1, len(boots)):
            b0, bk = boots[0].get("utc_boot"), boots[k].get("utc_boot")
            if c.source == "utc" and bk is not None and self.field.time_origin is not None:
                anchors.append((bk - utc_epoch(self.field.time_origin)) / scale)
            elif b0 is not None and bk is not None:
                anchors.append(c.t_boot0 + (bk - b0) / scale)
            else:
                # no clock on the vehicle: continue from the last time seen (the down time is not counted)
                prev = boots[k - 1]
                anchors.append(anchors[-1] + (prev["last_tb"] - boots[k].get("first_tb", 0)) / 1000.0 / scale)
        return anchors

    def _on_reboot(self, boot: int, last_tb: int, first_tb: int) -> None:
        """From the reader thread (SampleCollector): the vehicle's time since boot went back."""
        if self.collector is not None and self.collector.boots:
            self.collector.boots[-1].setdefault("first_tb", first_tb)
        self._reboot_info = (boot, last_tb, first_tb)
        # the old boot's EKF report would make wait_ready() pass at once, before the new EKF has a position
        self.link.forget("EKF_STATUS_REPORT")
        self._rebooted.set()

    # -- the mission -----------------------------------------------------------------------------
    def run(self) -> dict:
        """Fly every leg; returns the summary (also in ``summary.json``)."""
        from passt_mav.runs.store import SampleStore

        rd = self.rd.create()
        if self.mission_text is not None and not (self.resume and rd.mission_file.exists()):
            rd.mission_file.write_text(self.mission_text)
        self.store = SampleStore(rd.samples_db)
        if self.resume:
            self._resume_boots()
        self.record.meta(live_meta(self))
        self._attach(_StoreWriter(self.store, self.grid))
        try:
            state, t_state, first = self._initial_state()
            self._say(f"mission {self.config.name}: {self.n_legs} legs of {self.config.planner.path_length} moves, "
                      f"model {self.predictor_info.get('used')}, planner {self.config.planner.name}; waiting for the vehicle")
            self._prepare_vehicle()
            for i in range(first, self.n_legs):
                state, t_state = self._leg(i, state, t_state)
            self.status = "complete"
        except _Paused as exc:
            self.status = "paused"
            self._note("stopped", str(exc))
            self._say(f"stopped: {exc}")
            try:  # the pilot's RC still overrides HOLD; a vehicle left in an unknown mode would not stop
                self.vehicle.hold()
            except MavlinkError as e2:
                log.warning("could not switch to HOLD: %s", e2)
        except BaseException as exc:
            self.status = "aborted"
            if isinstance(exc, LinkTimeout) and "signing" not in str(exc) and "signing" in self.link.signing_hint():
                # a vehicle that requires signing ignores a keyless controller: say so, not just "timed out"
                exc = LinkTimeout(f"{exc}{self.link.signing_hint()}")
            self._note("stopped", f"aborted: {type(exc).__name__}: {exc}")
            self._safe_hold()
            raise exc
        finally:
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
        self.collector = SampleCollector(writer, u_name=sens.u, v_name=sens.v,
                                         source=f"mav:{self.link.target_system}/{self.link.target_component}",
                                         on_reboot=self._on_reboot, boot_base=self._boot_base)
        self.collector.attach(self.link)
        self.record.start_status(lambda: live_status(self))

    def _prepare_vehicle(self) -> None:
        """Wait for the EKF, choose the clock, set WP_RADIUS (put back by :meth:`_detach`)."""
        self.vehicle.wait_ready(timeout=self.ready_timeout_s)
        self._choose_clock()
        if self.config.vehicle.wp_radius_m > 0:
            # a Rover's acceptance radius is WP_RADIUS (it drops a waypoint's param2); put back at the end
            self.vehicle.set_wp_radius(self.config.vehicle.wp_radius_m)

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
        self.record.stop_status(lambda: live_status(self))

    def _safe_hold(self) -> None:
        try:
            if self.vehicle.mode == 10:  # AUTO
                self.vehicle.hold()
        except MavlinkError as exc:
            log.warning("could not switch to HOLD: %s", exc)

    # -- one leg: plan -> check -> upload (transactional) -> fly -> absorb ---------------------------
    def _leg(self, i: int, state: np.ndarray, t_state: float) -> tuple[np.ndarray, float]:
        planned = self._plan(i, state, t_state)
        wm = self._checked_mission(i, planned)
        rec = self._write_plan(i, planned, wm)
        link0, store0 = self._link_snapshot(), self.store.count(i)
        items = wm.items()
        upload_tries, upload_s, t_fly, tb_fly = self._swap(i, items, time.perf_counter())
        self._write_prediction(i, planned)  # (the boat is underway meanwhile)
        duration_s, tb_end = self._fly_leg(i, wm, items, t_fly)
        absorbed = self._absorb(i, planned)
        rec.update(absorbed.record())
        rec.update({
            "status": "complete", "t_end": absorbed.t_state, "upload_s": upload_s, "upload_tries": upload_tries,
            "duration_s": duration_s, "duration_vehicle_s": (tb_end - tb_fly) if (
                tb_end is not None and tb_fly is not None and tb_end >= tb_fly) else None,
            "n_samples_new": self.store.count(i) - store0, "link": self._link_record(link0),
            "readings": self._readings_record(i),
        })
        self._finish_leg(i, rec, planned)
        return absorbed.state, absorbed.t_state

    def _plan(self, i: int, state: np.ndarray, t_state: float):
        """Position -> start cell; the vehicle's clock -> forecast the state to now; plan the leg.

        The clock reading is sent to the vehicle as a STATUSTEXT first (:func:`clock_statustext`):
        the telemetry log and ArduPilot's DataFlash log keep it for a replay.
        """
        lat, lon, start, tb, boot, t_now = self._where_and_when()
        k = self.step.forecast_steps(t_now, t_state)
        self._send_clock(i, tb, boot, k)
        return self.step.plan(i, state, t_state, start, t_now=t_now, k=k, start_latlon=(lat, lon),
                              clock_reading=(tb, boot))

    def _where_and_when(self) -> tuple[float, float, tuple[int, int], int, int, float]:
        """(lat, lon, start cell, time_boot_ms, boot, field time now) of the vehicle; position checked."""
        lat, lon = self._position()
        start = self.step.start_cell(lat, lon)
        tb, boot = self._clock_reading()
        return lat, lon, start, tb, boot, float(self._clock_with_boots().field_time(tb, boot))

    def _send_clock(self, i: int, tb: int, boot: int, k: int) -> None:
        """The clock reading leg ``i`` is planned from, as a STATUSTEXT (:func:`clock_statustext`)."""
        self._last_clock = (i, tb, boot, k)
        text = clock_statustext(i, tb, boot, k)
        try:
            self.link.send(self.link.conn.mav.statustext_encode(6, text.encode()))  # MAV_SEVERITY_INFO
        except MavlinkError as exc:  # a log record, not a command: a dead link shows up at the upload
            log.warning("clock STATUSTEXT not sent: %s", exc)

    def _clock_reading(self) -> tuple[int, int]:
        """The vehicle's newest ``time_boot_ms`` and the run's boot number it belongs to."""
        up = self.link.vehicle_uptime_s()
        if up is None:
            raise MavlinkError("no vehicle time (time_boot_ms) received yet")
        return int(round(up * 1000.0)), self._boot_base + (self.collector.boot if self.collector is not None else 0)

    def _checked_mission(self, i: int, planned):
        """The leg's :class:`WaypointMission`; raises before anything is uploaded when the path or a
        waypoint leaves the grid or the geofence (region + ``geofence_margin_m``)."""
        import geo
        from passt_mav.mission.waypoints import WaypointMission

        grid, margin = self.grid, float(self.config.geofence_margin_m)
        geo.validate_path(grid, planned.plan.path)
        wm = WaypointMission.from_path(grid, planned.plan.path, speed=self.speed,
                                       wp_radius_m=self.config.vehicle.wp_radius_m, fence_margin_m=margin)
        inside = np.asarray(grid.contains(wm.waypoints[:, 0], wm.waypoints[:, 1], margin), bool)
        if not inside.all():
            bad = int(np.flatnonzero(~inside)[0])
            self.record.event("fence_refused", f"leg {i + 1}: waypoint {bad} outside the geofence; not uploaded")
            raise PlannerError(f"leg {i}: waypoint {bad} at {wm.waypoints[bad, 0]:.6f},{wm.waypoints[bad, 1]:.6f} "
                               f"lies outside the geofence (region + {margin:g} m); nothing uploaded")
        return wm

    def _write_plan(self, i: int, planned, wm) -> dict:
        """Waypoints (.waypoints, .plan) and leg.json (status flying)."""
        rd = self.rd
        rd.leg_dir(i)
        wm.to_wpl(rd.waypoints_file(i))
        wm.to_plan(rd.plan_file(i))
        rec = {**planned.record(self.dt), "status": "flying", "waypoints": wm.waypoints.tolist(),
               "waypoint_seqs": wm.waypoint_seqs(), "t_now": planned.t_now}
        rd.write_leg(i, rec)
        return rec

    def _write_prediction(self, i: int, planned) -> None:
        """The model's forecast over the leg (:meth:`LegStep.forecast_leg`) to prediction.nc."""
        from passt_mav.fields.field import FlowField

        fc = self.step.forecast_leg(planned)
        times = planned.t_start + self.dt * np.arange(fc.shape[0])
        FlowField(fc, self.grid, times, self.field.time_origin, self.field.units).to_netcdf(self.rd.prediction_file(i))

    def _fly_leg(self, i: int, wm, items, t_fly: float) -> tuple[float, float | None]:
        """Fly until the mission completes, then HOLD; returns (wall s, vehicle uptime s at the end)."""
        self._live_leg = (i, (self.link.vehicle_uptime_s() or 0.0) + self._expected_vehicle_s(wm))
        self.record.event("leg_start", f"{self._leg_label(i)} started ({len(wm.waypoints)} waypoints)")
        try:
            self._fly(i, wm, items, len(items) - 1)  # MISSION_CURRENT.total excludes home
        finally:
            self.collector.leg = None
        self.vehicle.hold()
        duration_s = time.perf_counter() - t_fly
        tb_end = self.link.vehicle_uptime_s()
        # the leg's last readings wait for the fix after them (<= the gap bound of vehicle time)
        self.collector.wait_placed(i, self.collector.track.max_gap_ms / 1000.0 / max(self.speedup, 1.0) + 0.5)
        self.writer.flush()
        return duration_s, tb_end

    def _absorb(self, i: int, planned):
        """The leg's stored samples through :meth:`LegStep.absorb`; the estimate to estimate.nc."""
        from passt_mav.fields.field import FlowField

        try:
            absorbed = self._update(planned, self.store.for_leg(i), self._clock_with_boots())
        except ReconstructionError as exc:
            raise MavlinkError(f"leg {i}: no current samples arrived (is the sensor sending "
                               f"{self.config.sensors.u}/{self.config.sensors.v}?): {exc}") from None
        std = None if absorbed.std is None else absorbed.std[None]
        FlowField(absorbed.state[None], self.grid, np.array([absorbed.t_state]), self.field.time_origin,
                  self.field.units).to_netcdf(self.rd.estimate_file(i), std=std)
        return absorbed

    def _update(self, planned, recs, clock):
        """The state update of a leg (:meth:`LegStep.absorb`; a fleet's boat shares one state)."""
        return self.step.absorb(planned, recs, clock)

    def _finish_leg(self, i: int, rec: dict, planned) -> None:
        """leg.json (complete), timings.json, summary.json, and one line of progress."""
        self.rd.write_leg(i, rec)
        self.rd.write_timings(i, {"planning_s": rec["planning_s"],
                                  **{f"{k}_s": x for k, x in planned.plan.timings.items()},
                                  "upload_s": rec["upload_s"], "leg_s": rec["duration_s"]})
        self.leg_records = [x for x in self.leg_records if int(x["index"]) != i] + [rec]
        self._write_summary()
        self.record.event("leg_end", f"{self._leg_label(i)} done: {rec['n_samples']} samples")
        r_p, r_m, link = rec["rmse_passt"], rec["rmse_model"], rec["link"]
        rm = "" if r_p is None else f", RMSE passt {r_p:.4f} model {r_m if r_m is None else round(r_m, 4)}"
        rtt = "-" if link["rtt_ms"] is None else f"{link['rtt_ms']:.1f} ms"
        rd = rec.get("readings") or {}
        used = "" if not rd.get("received") else f" of {rd['received']} readings ({100 * rd['fraction_used']:.0f} % used)"
        self._say(f"{self._leg_label(i)}: {rec['n_samples']} samples{used} ({rec['n_gp_points']} to the GP), "
                  f"{rec['duration_s']:.1f} s wall ({rec['duration_vehicle_s'] or 0:.0f} s vehicle), planning "
                  f"{rec['planning_s'] * 1000:.0f} ms, upload {rec['upload_s']:.2f} s{rm}, link RTT {rtt} "
                  f"loss {100 * link['loss']:.1f} %" + ("" if link.get("vehicle_bytes_per_s") is None else
                                                      f", vehicle sends {link['vehicle_bytes_per_s']:.0f} B/s"))

    def _leg_label(self, i: int) -> str:
        """How leg ``i`` (0-based) is named in progress lines."""
        return f"leg {i + 1}/{self.n_legs}"

    def _swap(self, i: int, items, t0w: float, attempts: int = 3) -> tuple[int, float, float, float | None]:
        """HOLD, verified upload, set-current 1, arm, AUTO: the transactional leg swap.

        A link lost on the way (LinkTimeout while the link is lost or closed) is reconnected and
        the swap starts again from HOLD, up to ``attempts`` times: the upload is verified by
        reading back, the other steps are idempotent, so a swap half done is never flown.
        Returns ``(upload_tries, upload_s, t_fly (perf_counter), vehicle uptime at AUTO)``.
        """
        v = self.vehicle
        for attempt in range(1, attempts + 1):
            try:
                if self._rebooted.is_set() or attempt > 1:
                    # after a reconnect the vehicle may have rebooted (its first time stamps may not be here
                    # yet): an upload right after boot is refused and AUTO needs the EKF, so wait for it first
                    self._rebooted.clear()
                    v.wait_ready(timeout=self.ready_timeout_s)
                if v.mode == 10:
                    v.hold()
                tries = self._upload(i, items)
                # seq 1 is the first mission item (DO_CHANGE_SPEED, then the waypoints): start there
                v.mission.set_current(1)
                upload_s = time.perf_counter() - t0w
                if not v.armed:
                    v.arm(timeout=max(30.0, 120.0 / self.speedup))
                    if getattr(self, "_last_clock", (None,))[0] == i:
                        # again: ArduPilot starts its DataFlash log at arming (LOG_DISARMED 0), after the
                        # first one; a replay of the .bin then finds this leg's clock reading too
                        self._send_clock(*self._last_clock)
                self.collector.leg = i
                self._resume_seq = 1
                t_fly = time.perf_counter()
                tb_fly = self.link.vehicle_uptime_s()
                v.start_mission()
                self._verify_pending = True  # _fly reads the mission back: another GCS may have uploaded meanwhile
                return tries, upload_s, t_fly, tb_fly
            except MavlinkError as exc:
                if not (isinstance(exc, LinkTimeout) or self.link.closed_reason is not None) or not self.link.lost \
                        or attempt == attempts:
                    raise
                self._say(f"leg {i + 1}: link lost during the leg swap ({exc}); reconnecting and starting the swap "
                          f"again from HOLD (attempt {attempt + 1}/{attempts})")
                self._note("link_lost", f"leg {i}: link lost during the swap at {_utc_now()}: {exc}")
                self.link.reconnect()
        raise AssertionError("unreachable")

    def _upload(self, i: int, items, tries: int = 4) -> int:
        """Upload, then read back and compare (as ``MissionClient.upload_verified``), with retries.

        Retried (the vehicle is in HOLD meanwhile): a transfer the vehicle cancelled (its 8 s
        timeout) or answered ERROR, a timeout, and a read-back that differs. A read-back that
        fails is re-read first: at a high simulator speed-up the vehicle re-requests items after
        1 s of *its* time, our duplicate answers then draw a late MISSION_ACK ERROR that lands in
        the download. DENIED (another ground station's upload is in progress: ArduPilot serves one
        at a time) is waited out, saying so once, for up to :attr:`FOREIGN_WAIT_S` (vehicle seconds)
        without counting as a try. Capacity (NO_SPACE) and other refusals raise at once.
        """
        from passt_mav.errors import MissionRejected, MissionVerifyError
        from passt_mav.mavlink.mission_client import _differences  # upload_verified's own comparison

        mc = self.vehicle.mission
        retry = (15, 1)  # MAV_MISSION_OPERATION_CANCELLED, MAV_MISSION_ERROR
        last: Exception | None = None
        denied_since: float | None = None
        k = 0
        while k < tries:
            k += 1
            try:
                up = mc.upload(items)
            except (MissionRejected, LinkTimeout) as exc:
                if isinstance(exc, MissionRejected) and exc.result == 14:  # MAV_MISSION_DENIED
                    denied_since = denied_since or self._denied(i)
                    if (time.monotonic() - denied_since) * self.speedup < self.FOREIGN_WAIT_S:
                        time.sleep(max(0.05, 1.0 / self.speedup))
                        k -= 1  # waiting for the other station is not a failed try
                        continue
                elif isinstance(exc, MissionRejected) and exc.result not in retry:
                    raise
                if self.link.lost:
                    raise  # the swap reconnects and starts again; retrying on a dead link only waits
                last = exc
            else:
                got = None
                for _ in range(3):
                    try:
                        got = mc.download()
                        break
                    except (MissionRejected, LinkTimeout) as exc:
                        last = exc
                        time.sleep(0.05)
                if got is not None:
                    diff = _differences(list(items), got, 0)
                    if not diff:
                        self._mission_mark = self._watch.expect(len(items), up.opaque_id)
                        return k
                    last = MissionVerifyError(f"mission read back differs from the upload: {diff}")
            self._say(f"leg {i + 1}: upload try {k} failed ({last}); retrying" if k < tries else
                      f"leg {i + 1}: upload failed {tries} times ({last})")
            self.events.append(f"leg {i}: upload try {k} failed: {last}")
            time.sleep(0.05)
        assert last is not None
        raise last

    #: replacements of our mission by another ground station in one leg before the controller stops in HOLD
    FOREIGN_REPLACEMENTS = 2
    #: vehicle seconds to wait for another ground station's mission transfer (our upload DENIED meanwhile)
    FOREIGN_WAIT_S = 60.0

    @property
    def _watch(self):
        """:class:`~passt_mav.mavlink.mission_client.MissionWatch` on this link (made on first use)."""
        w = self.__dict__.get("_mission_watch")
        if w is None:
            from passt_mav.mavlink.mission_client import MissionWatch

            w = self.__dict__["_mission_watch"] = MissionWatch(self.link)
            self._mission_mark = w.mark()
        return w

    def _verify_flying(self, i: int, items, resume_seq: int = 1) -> None:
        """Read the mission back while in AUTO: the vehicle must be flying ours.

        Called by :meth:`_fly` once AUTO is entered (after every swap) and when the
        :class:`~passt_mav.mavlink.mission_client.MissionWatch` sees signs of another upload. A
        ground station beside us (QGroundControl re-downloading, or an operator uploading) may
        have replaced the mission between our read-back and AUTO, or during the leg. If the read-back
        differs: say so, HOLD, upload ours again, resume at ``resume_seq``, AUTO, read back again;
        after :attr:`FOREIGN_REPLACEMENTS` replacements in this leg stop in HOLD (status ``paused``)
        rather than fight the other station for the vehicle.
        """
        from passt_mav.mavlink.mission_client import _differences  # upload_verified's own comparison

        v = self.vehicle
        while True:
            got = v.mission.download()
            diff = _differences(list(items), got, 0)
            if not diff:
                self._mission_mark = self._watch.expect(len(items), self._watch.expected_id)
                return
            who = self._watch.changed(self._mission_mark) or "seen by the read-back"
            what = _replaced_what(items, got)
            replaced = self.__dict__.setdefault("_replaced", {})  # leg -> replacements seen
            n = replaced[i] = replaced.get(i, 0) + 1
            log.info("leg %d: mission on the vehicle differs: %s", i, diff)
            self._note("mission_replaced", f"leg {i}: mission replaced on the vehicle at {_utc_now()} ({who}): {what}")
            if n > self.FOREIGN_REPLACEMENTS:
                v.hold()
                raise _Paused(f"leg {i}: another ground station replaced our mission {n} times ({who}); stopped in "
                              f"HOLD; stop its uploads, then continue with --resume")
            self._say(f"leg {i + 1}: another ground station replaced our mission on the vehicle ({who}; {what}); "
                      f"HOLD, uploading ours again, resuming at item {resume_seq}")
            v.hold()
            self._upload(i, items)
            v.mission.set_current(resume_seq)
            v.start_mission()
            if resume_seq > 1:
                self._set_speed_again(i, "the mission was uploaded again")

    def _set_speed_again(self, i: int, why: str) -> None:
        """DO_CHANGE_SPEED to the mission's speed: resuming past seq 1 skips the mission's own (the vehicle would
        go on at its WP_SPEED parameter)."""
        from passt_mav.errors import CommandRejected
        from passt_mav.mavlink.link import mavlink2

        try:
            self.link.command_long(mavlink2.MAV_CMD_DO_CHANGE_SPEED, 1, self.speed, -1)
        except (CommandRejected, LinkTimeout) as exc:
            self._say(f"leg {i + 1}: WARNING: the leg's speed {self.speed:g} m/s was not set again after {why} "
                      f"({exc}); the vehicle goes on at its WP_SPEED")
            self.events.append(f"leg {i}: speed not set again after {why}: {exc}")

    def _denied(self, i: int) -> float:
        """Our upload was DENIED: ArduPilot serves one upload at a time and another ground station's is in
        progress. Says so once; returns when (monotonic s) the wait began."""
        who = self._watch.changed((0, 0)) or "not visible on this link"
        self._say(f"leg {i + 1}: the vehicle denied our upload: another ground station is transferring a mission "
                  f"({who}); waiting up to {self.FOREIGN_WAIT_S:g} s (vehicle time) for it to finish")
        self.events.append(f"leg {i}: upload denied at {_utc_now()}: another station's transfer ({who})")
        return time.monotonic()

    # -- flying one leg, with its faults ------------------------------------------------------------
    def _expected_vehicle_s(self, wm) -> float:
        """Vehicle seconds the leg should take at the mission's speed (no current)."""
        import geo

        wp = wm.waypoints
        dist = float(np.sum(geo.geodesic_distance_m(wp[:-1, 0], wp[:-1, 1], wp[1:, 0], wp[1:, 1]))) if len(wp) > 1 else 0.0
        dist += self.grid.mean_cell_size_m  # reaching the first waypoint from anywhere in the start cell
        return dist / self.speed

    def _leg_deadline(self, budget_s: float) -> "_Deadline":
        return _Deadline(self.link, budget_s, self.speedup)

    def _fly(self, i: int, wm, items, n_items: int) -> None:
        """Wait for the leg to complete: reconnect on link loss, resume after a reboot, pause when a
        pilot takes the vehicle out of AUTO."""
        v = self.vehicle
        p = v.progress
        deadline = self._leg_deadline(4.0 * self._expected_vehicle_s(wm) + 30.0)
        while True:
            if getattr(self, "_verify_pending", False) and v.mode == 10 and not self.link.lost:
                try:
                    self._verify_flying(i, items, resume_seq=self._resume_seq)
                    self._verify_pending = False
                except MavlinkError as exc:
                    # DENIED: another station's upload is in progress (the vehicle serves no download
                    # meanwhile): read back once it is over. A lost link: recovered below, then read back.
                    if getattr(exc, "result", None) != 14 and not self.link.lost and self.link.error is None:
                        raise
            with p.changed:
                done = (p.state == 5 and p.total == n_items) or n_items in p.reached
                if not done:
                    p.changed.wait(0.1)
                    done = (p.state == 5 and p.total == n_items) or n_items in p.reached
            if done:
                return
            if deadline.passed():
                raise LinkTimeout(f"leg {i} not complete in time (item {p.current}/{p.total})")
            if self._rebooted.is_set():
                deadline.extend(self._after_reboot(i, items, n_items), rebooted=True)
                continue
            if self.link.lost or self.link.error is not None:
                self._recover_link(i, items)
                deadline.extend(30.0)
                continue
            mode = v.mode
            if mode == 10 and v.armed:
                # the item to come back to if the autopilot reboots (it forgets its progress)
                nxt = max([p.current] + [r + 1 for r in p.reached[-1:]])
                self._resume_seq = int(min(max(nxt, 1), n_items))
                if self._watch.changed(self._mission_mark):  # another ground station's upload: read back
                    self._verify_pending = True
            elif mode is not None and mode != 10:
                if self._reboot_suspected(mode):
                    continue
                try:
                    waited = self._pause(i, mode)
                except _Rebooted:
                    continue
                deadline.extend(waited)

    def _reboot_grace_s(self) -> float:
        """Wall seconds to wait for a reboot's signature (time going back): ~3 s of vehicle time."""
        return max(0.3, 3.0 / self.speedup)

    def _reboot_suspected(self, mode: int) -> bool:
        """Out of AUTO and disarmed (or INITIALISING): a rebooted autopilot looks like this before its
        first time stamp arrives. Wait a moment for the signature; True if it came."""
        if self.vehicle.armed and mode != 16:
            return False  # a pilot's mode change: the vehicle stays armed
        return self._rebooted.wait(self._reboot_grace_s())

    def _after_reboot(self, i: int, items, n_items: int) -> float:
        """The autopilot rebooted mid-leg: wait, verify, re-arm, resume at the interrupted item (or HOLD
        and stop with ``vehicle.on_reboot: hold``). Returns the wall seconds it took."""
        t0 = time.monotonic()
        v = self.vehicle
        self._rebooted.clear()
        boot, last_tb, first_tb = self._reboot_info or (0, 0, 0)
        seq = int(self._resume_seq)
        self._say(f"leg {i + 1}: the autopilot rebooted (its time since boot went from {last_tb / 1000:.1f} s back to "
                  f"{first_tb / 1000:.1f} s): not a pilot; waiting for it to be ready (EKF)")
        self._note("reboot", f"leg {i}: vehicle rebooted at {_utc_now()} (boot {boot}, was at item {seq})")
        if self.link.lost:
            self.link.reconnect()
        self.link.request_streams()  # a reboot forgets the rates set by SET_MESSAGE_INTERVAL
        v.wait_ready(timeout=self.ready_timeout_s)
        if self.config.vehicle.on_reboot == "hold":
            v.hold()
            raise _Paused(f"leg {i}: the autopilot rebooted mid-leg; vehicle.on_reboot is 'hold': stopped in HOLD "
                          f"(the leg was at item {seq}/{n_items}; continue with --resume)")
        from passt_mav.mavlink.mission_client import _differences  # the same comparison as upload_verified

        got = v.mission.download()
        diff = _differences(list(items), got, 0)
        if diff:
            self._say(f"leg {i + 1}: the mission on the vehicle differs after the reboot ({diff}); re-uploading")
            self._upload(i, items)
        v.mission.set_current(seq)
        v.arm(timeout=max(30.0, 120.0 / self.speedup))
        v.start_mission()
        if seq > 1:
            # the mission's DO_CHANGE_SPEED (seq 1) lies behind the resumed item and the reboot forgot it
            self._set_speed_again(i, "the reboot")
        self._say(f"leg {i + 1}: mission verified after the reboot; re-armed, AUTO again at item {seq}/{n_items}")
        self._note("reboot_recovered", f"leg {i}: resumed after the reboot at item {seq}/{n_items}"
                           + (" (mission re-uploaded)" if diff else " (stored mission verified)"))
        return time.monotonic() - t0

    def _recover_link(self, i: int, items) -> None:
        v = self.vehicle
        why = self.link.closed_reason or f"{self.link.seconds_since_heartbeat:.1f} s without heartbeat"
        self._say(f"leg {i + 1}: link lost ({why}); reconnecting")
        self._note("link_lost", f"leg {i}: link lost at {_utc_now()} ({why})")
        self.link.error = None
        self.link.reconnect()
        # a rebooted autopilot also drops its links: look at its time before treating this as a link fault
        try:
            self.link.wait("GLOBAL_POSITION_INT", timeout=max(1.0, 3.0 / self.speedup) + self.link.reply_timeout)
        except LinkTimeout:
            pass
        self.record.event("link_back", f"leg {i}: link back at {_utc_now()}")
        if self._rebooted.wait(0.1):
            return  # _fly handles the reboot (it verifies the mission itself)
        got = v.mission.download()
        from passt_mav.mavlink.mission_client import _differences  # the same comparison as upload_verified

        diff = _differences(list(items), got, 0)
        cur = self.link.wait("MISSION_CURRENT", timeout=max(2.0, self.link.reply_timeout))
        if diff:
            self._say(f"leg {i + 1}: the vehicle's mission differs after the reconnect ({diff}); re-uploading")
            was_auto = v.mode == 10
            if was_auto:
                v.hold()
            v.mission.upload_verified(items)
            v.mission.set_current(max(1, min(int(cur.seq), len(items) - 1)))
            if was_auto:
                v.set_mode("AUTO")
        self.events.append(f"leg {i}: reconnected, mission verified, item {cur.seq}/{cur.total}")
        self._say(f"leg {i + 1}: reconnected; mission on the vehicle verified, at item {cur.seq}/{getattr(cur, 'total', '?')}")

    def _pause(self, i: int, mode: int) -> float:
        from passt_mav.mavlink import ROVER_MODE_NAMES

        name = ROVER_MODE_NAMES.get(mode, str(mode))
        self._say(f"leg {i + 1}: the vehicle left AUTO (mode {name}): a pilot has control; pausing "
                  f"(waiting up to {self.pause_timeout_s:.0f} s for AUTO)")
        self._note("pilot_takeover", f"leg {i}: vehicle left AUTO (mode {name}) at {_utc_now()}")
        t0 = time.monotonic()
        while time.monotonic() - t0 < self.pause_timeout_s:
            if self.vehicle.mode == 10:
                self._say(f"leg {i + 1}: back in AUTO; continuing")
                self._note("pilot_released", f"leg {i}: back in AUTO")
                return time.monotonic() - t0
            if self._rebooted.is_set():
                raise _Rebooted()  # not the pilot after all (or the pilot rebooted it): _fly resumes
            if self.link.lost:
                self.link.reconnect()
            time.sleep(0.05)
        raise _Paused(f"leg {i}: the vehicle stayed in {name} for {self.pause_timeout_s:.0f} s; stopping in HOLD")


def _replaced_what(sent, got) -> str:
    """A short description of a mission on the vehicle that is not ours (the full one goes to the log)."""
    from passt_mav.mavlink.mission_client import rover_stored

    if len(sent) != len(got):
        return f"it holds {len(got)} items, ours has {len(sent)}"
    bad = [a.seq for a, b in zip(sent[1:], got[1:]) if not rover_stored(a).same_as(rover_stored(b))]
    return f"{len(bad)} of our {len(sent) - 1} items differ, the first at seq {bad[0]}" if bad else "home differs"


def mission_overrides(data: dict, overrides: dict) -> dict:
    """A copy of a mission mapping with dotted-key overrides (``{"planner.path_length": 6}``)."""
    import copy

    out = copy.deepcopy(data)
    for key, val in overrides.items():
        cur = out
        parts = key.split(".")
        for p in parts[:-1]:
            cur = cur.setdefault(p, {})
        cur[parts[-1]] = val
    return out


def load_mission_text(path: str | Path) -> tuple[str, dict]:
    import yaml

    text = Path(path).read_text()
    return text, yaml.safe_load(text)
