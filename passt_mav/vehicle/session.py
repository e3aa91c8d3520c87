"""The vehicle side of a mission: one boat's link, its leg swaps and its faults.

A :class:`VehicleSession` owns what the controller does *to the vehicle*; the controller
(:mod:`passt_mav.vehicle.controller`) keeps the PASST loop, the clock and the run's records. Per leg:

* :meth:`VehicleSession.swap` - HOLD, verified upload, set-current 1, arm, AUTO (transactional:
  a link lost on the way is reconnected and the swap starts again from HOLD);
* :meth:`VehicleSession.fly` - wait for the mission to complete, handling a lost link
  (:meth:`~VehicleSession.recover_link`), an autopilot reboot (:meth:`~VehicleSession.after_reboot`),
  a pilot taking over (:meth:`~VehicleSession.pause`) and another ground station replacing the
  mission (:meth:`~VehicleSession.verify_flying`).

What it says goes through a :class:`Journal` (progress lines, the run's event list, the live
view's ``events.jsonl``). Everything it sends goes through the public methods of
:class:`~passt_mav.mavlink.Link`, :class:`~passt_mav.mavlink.Vehicle` and
:class:`~passt_mav.mavlink.mission_client.MissionClient`; modes by name (:data:`ROVER_MODES`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from passt_mav.errors import CommandRejected, LinkTimeout, MavlinkError, MissionRejected, MissionVerifyError
from passt_mav.mavlink.clock import clock_of, vehicle_seconds, wall_seconds
from passt_mav.mavlink.link import mavlink2 as M
from passt_mav.mavlink.mission_client import MissionWatch, differences, rover_stored
from passt_mav.mavlink.vehicle import ROVER_MODES
from passt_mav.vehicle.console import OperatorCommands, refuse_if_flying
from passt_mav.vehicle.flow import LinkWindowOver, Paused, Rebooted, utc_now  # (re-exported: __all__)
from passt_mav.vehicle.link_figures import LinkFigures
from passt_mav.vehicle.outages import LinkOutages
from passt_mav.vehicle.waits import WaitLog

__all__ = ["VehicleSession", "Journal", "Deadline", "Paused", "LinkWindowOver", "Rebooted", "utc_now"]

log = logging.getLogger(__name__)

AUTO = ROVER_MODES["AUTO"]
INITIALISING = ROVER_MODES["INITIALISING"]
#: upload results retried as a failed try (the vehicle cancelled the transfer, or answered ERROR)
_RETRIED = (M.MAV_MISSION_OPERATION_CANCELLED, M.MAV_MISSION_ERROR)


class Journal:
    """Where a boat's controller reports: progress lines (``echo``), the run's event list
    (summary.json) and the live view's events (a :class:`~passt_mav.runs.live.RecordWriter`)."""

    def __init__(self, echo: Callable[[str], None], record, events: list[str] | None = None):
        self.echo = echo
        self.record = record
        self.events: list[str] = [] if events is None else events

    def say(self, text: str) -> None:
        """A progress line (and the log)."""
        self.echo(text)
        log.info(text)

    def note(self, kind: str, text: str, *, level: str | None = None, command_id: str | None = None) -> None:
        """An event: the run's list and the live view's (``kind``: runs.live.KINDS; ``level`` and
        ``command_id``: :meth:`~passt_mav.runs.live.RecordWriter.event`'s)."""
        self.events.append(text)
        self.record.event(kind, text, level=level, command_id=command_id)


class Deadline:
    """A leg's time limit, kept in the vehicle's time: ``budget_s`` vehicle seconds from now.

    A sped-up simulator starved of CPU runs slower than its nominal speed-up (a lockstep simulator
    runs as fast as the machine lets it, whatever ``--speedup-hint`` says); a wall-clock limit would
    then fail legs that are fine. So the wall clock only backs up a vehicle whose clock has **stopped**
    (a frozen simulator, a dead link): :meth:`wall_passed` is true once the vehicle's time since boot
    has not advanced for :attr:`STALL_WALL_S` wall seconds (plus any waiting added by :meth:`extend`).
    Before the vehicle has reported any time, the old backstop stands: ten times the budget at the
    nominal speed-up, + 60 s."""

    #: wall seconds without any advance of the vehicle's clock before the backstop fires
    STALL_WALL_S = 120.0

    def __init__(self, link, budget_s: float, speedup: float):
        self.link, self.speedup = link, max(float(speedup), 1e-6)
        #: the wall clock of the backstop: the link's (:attr:`passt_mav.mavlink.Link.clock`)
        self.clock = clock_of(link)
        self.last_up = link.vehicle_uptime_s()
        self.vehicle = None if self.last_up is None else self.last_up + budget_s
        self.wall = self.clock.now() + wall_seconds(10.0 * budget_s, self.speedup) + 60.0
        #: (wall s on the clock, vehicle uptime s) when the vehicle's clock was last seen advancing
        self._progress = (self.clock.now(), self.last_up)
        self.stalled_s = 0.0  # wall seconds the vehicle's clock had stood still when the backstop fired

    def extend(self, wall_s: float, *, rebooted: bool = False) -> None:
        """Add ``wall_s`` of waiting (reconnect, reboot, pilot). After a reboot the vehicle's clock
        started again: what was left of the budget counts from its new time."""
        self.waited(wall_s)
        if self.vehicle is None:
            return
        if rebooted:
            left = self.vehicle - (self.last_up or 0.0)
            up = self.last_up = self.link.vehicle_uptime_s()
            self.vehicle = None if up is None else up + left
        else:
            self.vehicle += vehicle_seconds(wall_s, self.speedup)

    def waited(self, wall_s: float) -> None:
        """``wall_s`` wall seconds went to a wait of our own (a reconnect): the backstop starts again from now."""
        self.wall += wall_s
        self._progress = (self.clock.now(), self._progress[1])

    def passed(self) -> bool:
        """The budget is spent: in vehicle time (:meth:`vehicle_passed`) or on the wall backstop."""
        return self.vehicle_passed() or self.wall_passed()

    def vehicle_passed(self) -> bool:
        """The vehicle's clock has run past the budget."""
        up = self.link.vehicle_uptime_s()
        if up is not None and (self.last_up is None or up >= self.last_up):  # (a reboot's restart: see extend)
            self.last_up = up
        return self.vehicle is not None and up is not None and up > self.vehicle

    def wall_passed(self) -> bool:
        """The vehicle's clock has stood still for :attr:`STALL_WALL_S` wall seconds (class docstring); before
        it reported any time: ten times the budget at the nominal speed-up, + 60 s."""
        now = self.clock.now()
        up = self.link.vehicle_uptime_s()
        t_ref, up_ref = self._progress
        if up is not None and (up_ref is None or up != up_ref):  # any change (a reboot's restart too) is progress
            self._progress = (now, up)
            return False
        if up_ref is None and up is None:
            return now > self.wall
        self.stalled_s = now - t_ref
        return self.stalled_s > self.STALL_WALL_S


def replaced_what(sent, got) -> str:
    """A short description of a mission on the vehicle that is not ours (the full one goes to the log)."""
    if len(sent) != len(got):
        return f"it holds {len(got)} items, ours has {len(sent)}"
    bad = [a.seq for a, b in zip(sent[1:], got[1:]) if not rover_stored(a).same_as(rover_stored(b))]
    return f"{len(bad)} of our {len(sent) - 1} items differ, the first at seq {bad[0]}" if bad else "home differs"


class VehicleSession(LinkOutages, OperatorCommands, LinkFigures):
    """One boat's vehicle side (module docstring): swap, fly, and the faults on the way.

    Args:
        link / vehicle: the connected :class:`~passt_mav.mavlink.Link` and its :class:`~passt_mav.mavlink.Vehicle`.
        journal: where it reports (:class:`Journal`).
        speed_mps: the mission's speed (m/s), set again after a resume past the mission's DO_CHANGE_SPEED.
        on_reboot: ``"resume"`` or ``"hold"`` (mission key ``vehicle.on_reboot``).
        speedup: simulated / wall seconds of the vehicle (1 for a real boat); scales wall timeouts.
        ready_timeout_s: wall seconds to wait for EKF/GPS readiness.
        pause_timeout_s: wall seconds to wait for AUTO to come back after a pilot took over.
        link_loss_window_s: vehicle seconds a lost link is tried again before the run stops
            (:class:`LinkWindowOver`); nothing is heard from the vehicle meanwhile, so the wait is kept
            on the wall clock as ``link_loss_window_s / speedup``.
        overrun_factor / on_overrun: a leg still flying after ``overrun_factor`` x its expected vehicle
            time + 30 s is reported; ``"cut"`` ends it there (:meth:`fly` returns ``"cut"``), ``"warn"``
            only reports it.
        wp_radius_m: the mission's waypoint radius (m): a wait's drift beyond twice it is said (:attr:`waits`).
    """

    #: replacements of our mission by another ground station in one leg before the controller stops in HOLD
    FOREIGN_REPLACEMENTS = 2
    #: the vehicle was ready once in this session (:meth:`wait_ready`)
    was_ready = False
    #: vehicle seconds to wait for another ground station's mission transfer (our upload DENIED meanwhile)
    FOREIGN_WAIT_S = 60.0
    #: read-backs in AUTO that may fail in a row (a radio drop within one, a broken-off transfer) before the leg fails
    VERIFY_TIMEOUTS = 5

    def __init__(
        self,
        link,
        vehicle,
        journal: Journal,
        *,
        speed_mps: float,
        on_reboot: str = "resume",
        speedup: float = 1.0,
        ready_timeout_s: float = 120.0,
        pause_timeout_s: float = 300.0,
        link_loss_window_s: float = 600.0,
        overrun_factor: float = 2.0,
        on_overrun: str = "cut",
        wp_radius_m: float = 2.0,
    ):
        self.link, self.vehicle, self.journal = link, vehicle, journal
        #: the boat's waits and their drift (:class:`~passt_mav.vehicle.waits.WaitLog`): leg.json ``waits``,
        #: how the run left the boat (summary.json ``end``)
        self.waits = WaitLog(vehicle, link, journal.say, wp_radius_m)
        self.speed = float(speed_mps)
        self.on_reboot = on_reboot
        self.speedup = max(float(speedup), 1e-6)
        self.ready_timeout_s = float(ready_timeout_s)
        self.pause_timeout_s = float(pause_timeout_s)
        self.link_loss_window_s = float(link_loss_window_s)
        self.overrun_factor, self.on_overrun = float(overrun_factor), on_overrun
        #: one record per outage ridden out (or not), oldest first (see :meth:`recover_link`)
        self.outages: list[dict] = []
        #: set by :meth:`rebooted_signal` (the collector's reader thread), cleared by whoever handles it
        self.rebooted = threading.Event()
        self.reboot_info: tuple[int, int, int] | None = None
        #: the item to come back to if the autopilot reboots (it forgets its progress)
        self.resume_seq = 1
        #: the mission is to be read back in AUTO (after a swap; signs of another station's upload)
        self.verify_pending = False
        self._mission_watch: MissionWatch | None = None
        self._mission_mark: tuple[int, int] = (0, 0)
        #: the mission's safety budget (:class:`~passt_mav.vehicle.budget.SafetyBudget`), None = not watched
        self.budget = None
        self._replaced: dict[int, int] = {}  # leg -> replacements by another station seen
        self._verify_timeouts = 0  # read-backs in AUTO timed out in a row

    # -- small things ---------------------------------------------------------------------------
    def _say(self, text: str) -> None:
        self.journal.say(text)

    @property
    def arm_timeout_s(self) -> float:
        return wall_seconds(120.0, self.speedup, at_least=30.0)

    def wait_ready(self, *, new_run: bool = False) -> None:
        """Wait for the EKF (``ready_timeout_s``); the first time in a ``new_run`` a vehicle that flies a mission
        already is refused (:func:`~passt_mav.vehicle.console.refuse_if_flying`), never later (a fleet's boat that
        rejoins after a link drop flies its own leg in AUTO)."""
        self.vehicle.wait_ready(timeout=self.ready_timeout_s)
        if new_run and not self.was_ready:
            refuse_if_flying(self.vehicle)
        self.was_ready = True

    def position(self, timeout: float = 10.0) -> tuple[float, float]:
        """The vehicle's (lat, lon) degrees; MavlinkError without a GPS position within ``timeout`` wall s."""
        end = self.link.clock.now() + timeout
        while (p := self.vehicle.position()) is None:
            if self.link.clock.now() > end:
                raise MavlinkError("no GPS position from the vehicle")
            self.link.idle(0.02)
        return p

    def rebooted_signal(self, info: tuple[int, int, int]) -> None:
        """From the reader thread: the vehicle's time since boot went back ((boot, last_tb, first_tb))."""
        self.reboot_info = info
        # the old boot's EKF report would make wait_ready() pass at once, before the new EKF has a position
        self.link.forget("EKF_STATUS_REPORT")
        self.rebooted.set()

    @property
    def watch(self) -> MissionWatch:
        """:class:`~passt_mav.mavlink.mission_client.MissionWatch` on this link (made on first use)."""
        if self._mission_watch is None:
            self._mission_watch = MissionWatch(self.link)
            self._mission_mark = self._mission_watch.mark()
        return self._mission_watch

    # -- the leg swap ----------------------------------------------------------------------------
    def swap(
        self,
        i: int,
        items,
        t0w: float,
        *,
        on_armed: Callable[[], None],
        on_start: Callable[[], None],
        attempts: int = 3,
    ) -> tuple[int, float, float, float | None]:
        """HOLD, verified upload, set-current 1, arm, AUTO: the transactional leg swap.

        A link lost on the way (LinkTimeout while the link is lost or closed) is reconnected and
        the swap starts again from HOLD, up to ``attempts`` times: the upload is verified by
        reading back, the other steps are idempotent, so a swap half done is never flown.
        ``on_armed()`` after arming a disarmed vehicle, ``on_start()`` just before AUTO.
        Returns ``(upload_tries, upload_s, t_fly (the link's clock, wall s), vehicle uptime at AUTO)``.
        """
        for attempt in range(1, attempts + 1):
            try:
                return self._swap_once(i, items, t0w, attempt, on_armed, on_start)
            except MavlinkError as exc:
                if (
                    not (isinstance(exc, LinkTimeout) or self.link.closed_reason is not None)
                    or not self.link.lost
                    or attempt == attempts
                ):
                    raise
                self._say(
                    f"leg {i + 1}: link lost during the leg swap ({exc}); reconnecting and starting the swap "
                    f"again from HOLD (attempt {attempt + 1}/{attempts})"
                )
                self.journal.note("link_lost", f"leg {i + 1}: link lost during the swap at {utc_now()}: {exc}")
                self.reconnect_within_window(i, self.lost_since(), "swap")
        raise AssertionError("unreachable")

    def _swap_once(self, i: int, items, t0w: float, attempt: int, on_armed, on_start):
        v = self.vehicle
        if self.rebooted.is_set() or attempt > 1:
            # after a reconnect the vehicle may have rebooted (its first time stamps may not be here
            # yet): an upload right after boot is refused and AUTO needs the EKF, so wait for it first
            self.rebooted.clear()
            self.wait_ready()
        if v.mode == AUTO:
            v.keep_station()
        tries = self.upload(i, items)
        # seq 1 is the first mission item (DO_CHANGE_SPEED, then the waypoints): start there
        v.mission.set_current(1)
        upload_s = self.link.clock.now() - t0w
        if not v.armed:
            v.arm(timeout=self.arm_timeout_s)
            on_armed()
        on_start()
        self.resume_seq = 1
        t_fly = self.link.clock.now()
        tb_fly = self.link.vehicle_uptime_s()
        v.start_mission()
        self.verify_pending = True  # fly() reads the mission back: another GCS may have uploaded meanwhile
        self.set_speed_again(i, "AUTO was entered")  # a boat's Rover drops seq 1's (tests/test_sitl_current.py)
        return tries, upload_s, t_fly, tb_fly

    def upload(self, i: int, items, tries: int = 4) -> int:
        """Upload, then read back and compare (as ``MissionClient.upload_verified``), with retries.

        Retried (the vehicle is in HOLD meanwhile): a transfer the vehicle cancelled (its 8 s
        timeout) or answered ERROR, a timeout, and a read-back that differs. A read-back that
        fails is re-read first: at a high simulator speed-up the vehicle re-requests items after
        1 s of *its* time, our duplicate answers then draw a late MISSION_ACK ERROR that lands in
        the download. DENIED (another ground station's upload is in progress: ArduPilot serves one
        at a time) is waited out, saying so once, for up to :attr:`FOREIGN_WAIT_S` (vehicle seconds)
        without counting as a try. Capacity (NO_SPACE) and other refusals raise at once.
        Returns the number of tries.
        """
        last: Exception | None = None
        denied_since: float | None = None
        k = 0
        while k < tries:
            k += 1
            try:
                up = self.vehicle.mission.upload(items)
            except (MissionRejected, LinkTimeout) as exc:
                if isinstance(exc, MissionRejected) and exc.result == M.MAV_MISSION_DENIED:
                    denied_since = self._denied(i) if denied_since is None else denied_since
                    if self._vehicle_now() - denied_since < self.FOREIGN_WAIT_S:
                        self.link.idle(wall_seconds(1.0, self.speedup, at_least=0.05))  # lockstep: one step
                        k -= 1  # waiting for the other station is not a failed try
                        continue
                elif isinstance(exc, MissionRejected) and exc.result not in _RETRIED:
                    raise
                if self.link.lost:
                    raise  # the swap reconnects and starts again; retrying on a dead link only waits
                last = exc
            else:
                last = self._read_back(items, up.opaque_id)
                if last is None:
                    return k
            self._say(
                f"leg {i + 1}: upload try {k} failed ({last}); retrying"
                if k < tries
                else f"leg {i + 1}: upload failed {tries} times ({last})"
            )
            self.journal.events.append(f"leg {i + 1}: upload try {k} failed: {last}")
            self.link.clock.sleep(0.05)
        assert last is not None
        raise last

    def _read_back(self, items, opaque_id: int) -> Exception | None:
        """After an upload: read the mission back (up to 3 reads); None if it is ours, else why not."""
        last: Exception | None = None
        for _ in range(3):
            try:
                got = self.vehicle.mission.download()
            except (MissionRejected, LinkTimeout) as exc:
                last = exc
                self.link.clock.sleep(0.05)
                continue
            diff = differences(list(items), got, 0)
            if not diff:
                self._mission_mark = self.watch.expect(len(items), opaque_id)
                return None
            return MissionVerifyError(f"mission read back differs from the upload: {diff}")
        return last

    def _vehicle_now(self) -> float:
        """Vehicle seconds: a lockstep vehicle's stepped clock, else the link's wall clock x the speed-up."""
        step = self.link.lockstep
        return step.t if step is not None else vehicle_seconds(self.link.clock.now(), self.speedup)

    def _denied(self, i: int) -> float:
        """Our upload was DENIED: ArduPilot serves one upload at a time and another ground station's is in
        progress. Says so once; returns when (:meth:`_vehicle_now`, vehicle s) the wait began."""
        who = self.watch.changed((0, 0)) or "not visible on this link"
        self._say(
            f"leg {i + 1}: the vehicle denied our upload: another ground station is transferring a mission "
            f"({who}); waiting up to {self.FOREIGN_WAIT_S:g} s (vehicle time) for it to finish"
        )
        self.journal.events.append(f"leg {i + 1}: upload denied at {utc_now()}: another station's transfer ({who})")
        return self._vehicle_now()

    def verify_flying(self, i: int, items, resume_seq: int = 1) -> None:
        """Read the mission back while in AUTO: the vehicle must be flying ours.

        Called by :meth:`fly` once AUTO is entered (after every swap) and when the
        :class:`~passt_mav.mavlink.mission_client.MissionWatch` sees signs of another upload. A
        ground station beside us (QGroundControl re-downloading, or an operator uploading) may
        have replaced the mission between our read-back and AUTO, or during the leg. If the read-back
        differs: say so, HOLD, upload ours again, resume at ``resume_seq``, AUTO, read back again;
        after :attr:`FOREIGN_REPLACEMENTS` replacements in this leg stop in HOLD (:class:`Paused`)
        rather than fight the other station for the vehicle.
        """
        v = self.vehicle
        while True:
            got = v.mission.download()
            diff = differences(list(items), got, 0)
            if not diff:
                self._mission_mark = self.watch.expect(len(items), self.watch.expected_id)
                return
            who = self.watch.changed(self._mission_mark) or "seen by the read-back"
            what = replaced_what(items, got)
            n = self._replaced[i] = self._replaced.get(i, 0) + 1
            log.info("leg %d: mission on the vehicle differs: %s", i + 1, diff)
            self.journal.note(
                "mission_replaced", f"leg {i + 1}: mission replaced on the vehicle at {utc_now()} ({who}): {what}"
            )
            if n > self.FOREIGN_REPLACEMENTS:
                v.keep_station()
                raise Paused(
                    f"leg {i + 1}: another ground station replaced our mission {n} times ({who}); stopped in "
                    f"HOLD; stop its uploads, then continue with --resume"
                )
            self._say(
                f"leg {i + 1}: another ground station replaced our mission on the vehicle ({who}; {what}); "
                f"HOLD, uploading ours again, resuming at item {resume_seq}"
            )
            v.keep_station()
            self.upload(i, items)
            v.mission.set_current(resume_seq)
            v.start_mission()
            self.set_speed_again(i, "the mission was uploaded again")

    def set_speed_again(self, i: int, why: str) -> None:
        """The mission's speed after every entry into AUTO (:meth:`~passt_mav.mavlink.Vehicle.set_speed`: Rover
        resets it to WP_SPEED there, and a boat loses the mission's own seq-1 DO_CHANGE_SPEED); a refusal is said."""
        try:
            self.vehicle.set_speed(self.speed, speedup=self.speedup)
        except (CommandRejected, LinkTimeout) as exc:
            self._say(
                f"leg {i + 1}: WARNING: the leg's speed {self.speed:g} m/s was not set again after {why} "
                f"({exc}); the vehicle goes on at its WP_SPEED"
            )
            self.journal.events.append(f"leg {i + 1}: speed not set again after {why}: {exc}")

    # -- flying one leg, with its faults ------------------------------------------------------------
    def fly(self, i: int, items, n_items: int, expected_s: float) -> str | None:
        """Wait for the leg to complete (``n_items`` excludes home; ``expected_s``: vehicle seconds it should
        take): ride out a lost link (:meth:`recover_link`), resume after a reboot, pause when a pilot takes
        the vehicle out of AUTO. Past ``overrun_factor`` x ``expected_s`` + 30 s of vehicle time the overrun
        is reported (:meth:`overrun`); returns ``"cut"`` when ``on_overrun`` is ``cut`` (the caller holds the
        vehicle and ends the leg), else None when the mission completed. A vehicle whose clock stops (a
        frozen simulator) still ends on the wall backstop (:class:`Deadline`): LinkTimeout. The operator's
        commands are carried out between turns (:meth:`console_turn`): ``"skip"`` or ``"replan"`` end the leg; so
        does the safety budget once spent (:attr:`budget`): ``"budget"``."""
        if self.budget is not None:
            self.budget.start_leg()
        try:
            return self._fly_turns(i, items, n_items, expected_s)
        finally:
            if self.budget is not None:
                self.budget.end_leg()

    def _fly_turns(self, i: int, items, n_items: int, expected_s: float) -> str | None:
        planned_s = self.overrun_factor * expected_s + 30.0
        deadline = Deadline(self.link, planned_s, self.speedup)
        p = self.vehicle.progress
        reported = False
        while True:
            self._verify_if_pending(i, items)
            how = self.console_turn(i, n_items)  # the operator's commands, the budget (passt_mav.vehicle.console)
            if isinstance(how, str):
                return how
            if how:
                deadline.extend(how)
            if self._wait_complete(n_items):
                return None
            if deadline.wall_passed():
                raise LinkTimeout(
                    f"leg {i + 1}: the vehicle's clock has not advanced for {deadline.stalled_s:.0f} wall s "
                    f"(a frozen simulator or a dead link?) at item {p.current}/{p.total}"
                )
            if not reported and deadline.vehicle_passed():
                reported = True
                if self.overrun(i, expected_s, planned_s, n_items):
                    return "cut"
            if self.rebooted.is_set():
                deadline.extend(self.after_reboot(i, items, n_items), rebooted=True)
                continue
            if self.link.lost or self.link.error is not None:
                t0 = self.link.clock.now()
                self.recover_link(i, items)
                # the vehicle flew on meanwhile (its clock counts that); only the wall backstop waits longer
                deadline.waited(self.link.clock.now() - t0)
                continue
            waited = self._watch_mode(i, n_items)
            if isinstance(waited, str):  # the page's skip or replan while a pilot held the boat
                return waited
            if waited:
                deadline.extend(waited)

    def overrun(self, i: int, expected_s: float, planned_s: float, n_items: int) -> bool:
        """Leg ``i`` has flown past ``planned_s`` vehicle seconds (``overrun_factor`` x ``expected_s`` + 30 s):
        one line and an event; True when the mission's rule (``on_overrun: cut``) ends the leg here."""
        p = self.vehicle.progress
        cut = self.on_overrun == "cut"
        what = (
            "cutting the leg: HOLD, its samples absorbed, the next leg planned from here"
            if cut
            else "flying on (vehicle.on_overrun: warn)"
        )
        self._say(
            f"leg {i + 1}: WARNING: overrun: still flying after {planned_s:.0f} s of vehicle time "
            f"({self.overrun_factor:g} x the expected {expected_s:.0f} s + 30 s), at item {p.current}/{n_items}; {what}"
        )
        self.journal.note(
            "warning",
            f"leg {i + 1}: overrun at {utc_now()}: past {planned_s:.0f} vehicle s at item {p.current}/{n_items}",
        )
        return cut

    def _verify_if_pending(self, i: int, items) -> None:
        if not (self.verify_pending and self.vehicle.mode == AUTO and not self.link.lost):
            return
        try:
            self.verify_flying(i, items, resume_seq=self.resume_seq)
            self.verify_pending = False
            self._verify_timeouts = 0
        except MavlinkError as exc:
            # DENIED: another station's upload is in progress (the vehicle serves no download
            # meanwhile): read back once it is over. A lost link: recovered by fly(), then read back.
            # A timeout (a radio drop that began and ended within the read-back) or a transfer the vehicle
            # broke off (a late duplicate answer at a high speed-up): read back again (a few times in a row).
            retry = isinstance(exc, MissionRejected) and exc.result in (*_RETRIED, M.MAV_MISSION_INVALID_SEQUENCE)
            if isinstance(exc, LinkTimeout) or retry:
                self._verify_timeouts += 1
                if self._verify_timeouts <= self.VERIFY_TIMEOUTS:
                    return
            if getattr(exc, "result", None) != M.MAV_MISSION_DENIED and not self.link.lost and self.link.error is None:
                raise

    def _wait_complete(self, n_items: int) -> bool:
        """True once the mission is complete (MISSION_CURRENT complete with our total, or the last item
        reached); waits up to 0.1 s for news."""
        p = self.vehicle.progress

        def done() -> bool:
            return (p.state == M.MISSION_STATE_COMPLETE and p.total == n_items) or n_items in p.reached

        with p.changed:
            if done():
                return True
            if self.link.lockstep is None:
                p.changed.wait(0.1)
                return done()
        self.link.idle(0.1)  # in lockstep the vehicle's clock runs only here: one step, then look again
        with p.changed:
            return done()

    def _watch_mode(self, i: int, n_items: int) -> float | str:
        """In AUTO: note the item to resume at and signs of another station. Out of AUTO: a reboot or a pilot.
        Returns wall seconds spent waiting for a pilot (0 otherwise), or the page's ``"skip"``/``"replan"``."""
        v, p = self.vehicle, self.vehicle.progress
        mode = v.mode
        if mode == AUTO and v.armed:
            nxt = max([p.current] + [r + 1 for r in p.reached[-1:]])
            self.resume_seq = int(min(max(nxt, 1), n_items))
            if self.watch.changed(self._mission_mark):  # another ground station's upload: read back
                self.verify_pending = True
        elif mode is not None and mode != AUTO:
            if self._reboot_suspected(mode):
                return 0.0
            try:
                return self.pause(i, mode, n_items)
            except Rebooted:
                return 0.0
        return 0.0

    def _reboot_suspected(self, mode: int) -> bool:
        """Out of AUTO and disarmed (or INITIALISING): a rebooted autopilot looks like this before its
        first time stamp arrives. Wait ~3 s of vehicle time for the signature; True if it came."""
        if self.vehicle.armed and mode != INITIALISING:
            return False  # a pilot's mode change: the vehicle stays armed
        return self.rebooted.wait(wall_seconds(3.0, self.speedup, at_least=0.3))

    def after_reboot(self, i: int, items, n_items: int) -> float:
        """The autopilot rebooted mid-leg: wait, verify, re-arm, resume at the interrupted item (or HOLD
        and stop with ``vehicle.on_reboot: hold``). Returns the wall seconds it took."""
        t0 = self.link.clock.now()
        v = self.vehicle
        self.rebooted.clear()
        boot, last_tb, first_tb = self.reboot_info or (0, 0, 0)
        # the item after the last one reached before the reboot (the reader thread records MISSION_ITEM_REACHED
        # at once; resume_seq is noted by the flying loop, which the reboot may have overtaken)
        reached = v.progress.reached[-1:]
        seq = int(min(max([int(self.resume_seq)] + [r + 1 for r in reached]), max(n_items, 1)))
        self._say(
            f"leg {i + 1}: the autopilot rebooted (its time since boot went from {last_tb / 1000:.1f} s back to "
            f"{first_tb / 1000:.1f} s): not a pilot; waiting for it to be ready (EKF)"
        )
        self.journal.note("reboot", f"leg {i + 1}: vehicle rebooted at {utc_now()} (boot {boot}, was at item {seq})")
        if self.link.lost:
            self.reconnect_within_window(i, self.lost_since(), "reboot")
        self.link.request_streams()  # a reboot forgets the rates set by SET_MESSAGE_INTERVAL
        self.wait_ready()
        if self.on_reboot == "hold":
            v.keep_station()
            raise Paused(
                f"leg {i + 1}: the autopilot rebooted mid-leg; vehicle.on_reboot is 'hold': stopped in {v.wait_mode} "
                f"(the leg was at item {seq}/{n_items}; continue with --resume)"
            )
        diff = differences(list(items), v.mission.download(), 0)
        if diff:
            self._say(f"leg {i + 1}: the mission on the vehicle differs after the reboot ({diff}); re-uploading")
            self.upload(i, items)
        v.mission.set_current(seq)
        v.arm(timeout=self.arm_timeout_s)
        v.start_mission()
        self.set_speed_again(i, "the reboot")
        self._say(f"leg {i + 1}: mission verified after the reboot; re-armed, AUTO again at item {seq}/{n_items}")
        self.journal.note(
            "reboot_recovered",
            f"leg {i + 1}: resumed after the reboot at item {seq}/{n_items}"
            + (" (mission re-uploaded)" if diff else " (stored mission verified)"),
        )
        return self.link.clock.now() - t0


def expected_vehicle_s(grid, wm, speed_mps: float) -> float:
    """Vehicle seconds a leg's waypoints ``wm`` should take at ``speed_mps`` (no current)."""
    import geo

    wp = wm.waypoints
    dist = float(np.sum(geo.geodesic_distance_m(wp[:-1, 0], wp[:-1, 1], wp[1:, 0], wp[1:, 1]))) if len(wp) > 1 else 0.0
    dist += grid.mean_cell_size_m  # reaching the first waypoint from anywhere in the start cell
    return dist / speed_mps
