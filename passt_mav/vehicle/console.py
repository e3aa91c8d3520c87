"""The operator's commands from the live page, carried out while a leg flies (docs/console.md).

A mixin of :class:`~passt_mav.vehicle.session.VehicleSession` (as :mod:`~passt_mav.vehicle.outages` is): it uses
the session's ``vehicle``, ``link`` (and its clock), ``journal``, ``pause_timeout_s``, ``resume_seq``, ``rebooted``,
``set_speed_again``, ``lost_since`` and ``reconnect_within_window``. The view server appends each command to the
run's channel (:mod:`passt_mav.runs.commands`); :meth:`OperatorCommands.operator_step`, called once per turn of
:meth:`VehicleSession.fly`, reads this boat's new ones and acts through the paths a pilot takeover and a
link loss already use:

* ``pause``: HOLD; then wait as for a pilot who took over (:meth:`VehicleSession.pause`): for ``resume``
  (AUTO again: the vehicle goes on at the item it was flying, the leg's speed set again past its first item),
  ``skip``, ``replan`` or ``end``, for AUTO set by someone else, or until ``pause_timeout_s`` (wall s) has
  passed: then :class:`~passt_mav.vehicle.flow.Paused` (the run stops in HOLD, status ``paused``,
  ``--resume`` continues). The loop's state is untouched meanwhile.
* ``skip``: the leg ends here (:meth:`fly` returns ``"skip"``): HOLD, its samples absorbed, the next leg planned.
* ``replan``: the leg is planned again from here (:meth:`fly` returns ``"replan"``): its attempt is kept as
  an interrupted one (as after ``--resume``), its samples stay in the store for the re-flown leg.
* ``end``: HOLD or RTL (the operator's choice), then :class:`Ended`: the run ends cleanly, status
  ``ended``, state saved for ``--resume``.
* ``approve`` / ``reject`` (approve mode, :meth:`OperatorCommands.await_approval`): before a leg's upload the
  controller waits for one of them (or ``end``); a rejected leg is planned again.

Each command is answered by an event of kind ``command`` carrying its id (level ``ok`` when carried out,
``warn`` when not, with the reason), also in summary.json's events and on the console.
A pause and its resume are also marked in the telemetry log (:mod:`~passt_mav.vehicle.leg_marks`): the pause's
wait then reads as a wait inside the leg, not as its end, and ``passt-mav replay`` keeps its readings in the leg.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from passt_mav.errors import MavlinkError
from passt_mav.mavlink.vehicle import ROVER_MODE_NAMES, ROVER_MODES
from passt_mav.vehicle.flow import Ended, Paused, Rebooted, utc_now
from passt_mav.vehicle.leg_marks import mark_leg
from passt_mav.vehicle.machine_faults import check_store

if TYPE_CHECKING:
    import threading

    from passt_mav.mavlink.link import Link
    from passt_mav.mavlink.vehicle import Vehicle
    from passt_mav.runs.commands import CommandReader
    from passt_mav.runs.store_guard import StoreGuard
    from passt_mav.vehicle.budget import SafetyBudget
    from passt_mav.vehicle.session import Journal
    from passt_mav.vehicle.waits import WaitLog

__all__ = ["OperatorCommands", "Ended", "refuse_if_flying"]

AUTO = ROVER_MODES["AUTO"]


def refuse_if_flying(vehicle) -> None:
    """A new run's first look at the vehicle: armed in AUTO, it flies a mission this run did not upload (another
    controller or ground station is in charge of it, or a run of ours that is to be continued with ``--resume``).
    Taking it over would cut that mission short, so the run refuses to start: :class:`~passt_mav.errors.UserError`,
    one line, nothing sent to the vehicle."""
    from passt_mav.errors import UserError

    if vehicle.armed and vehicle.mode == AUTO:
        vehicle.hands_off = True  # (the run's clean-up must not stop that mission either)
        p = vehicle.progress
        at = f" at item {p.current}" + (f"/{p.total}" if p.total else "") if p.current else ""
        raise UserError(
            f"the vehicle is armed in AUTO, flying a mission{at} that this run did not upload: another controller "
            "or ground station is in charge of it. Put it in HOLD or LOITER from there first (or continue your "
            "own run with --resume --out RUN)"
        )


class OperatorCommands:
    """The operator's commands for one boat (module docstring). ``commands``: the boat's
    :class:`~passt_mav.runs.commands.CommandReader`, None = no channel (nothing is read)."""

    commands: CommandReader | None = None

    if TYPE_CHECKING:  # the session's, which this mixin uses (module docstring)
        #: the boat's :class:`~passt_mav.vehicle.waits.WaitLog` (:class:`VehicleSession` makes it): a pause's drift
        #: is recorded
        waits: WaitLog
        vehicle: Vehicle
        link: Link
        journal: Journal
        pause_timeout_s: float
        rebooted: threading.Event
        budget: SafetyBudget | None
        store_guard: StoreGuard | None  # the store writer's (machine_faults.check_store)

        def set_speed_again(self, i: int, why: str) -> None: ...
        def lost_since(self) -> float: ...
        def reconnect_within_window(self, i: int, t_lost: float, during: str = "leg") -> dict: ...
    else:
        waits = None

    def _answer(self, cmd: dict, text: str, *, ok: bool = True) -> None:
        """The command's answer: an event of kind ``command`` with its id, summary.json's events, a line."""
        who = cmd.get("source") or "the page"
        line = f"operator ({who}): {cmd['action']}" + (f" {cmd['end_mode']}" if cmd.get("end_mode") else "")
        line += f": {text}"
        self.journal.note("command", line, level="ok" if ok else "warn", command_id=cmd.get("id"))
        self.journal.say(line)

    def console_turn(self, i: int, n_items: int) -> str | float | None:
        """One turn of :meth:`VehicleSession.fly`: the sample store (the session's ``store_guard``: a store the
        machine failed raises :class:`~passt_mav.vehicle.flow.MachineFault`), the operator's commands
        (:meth:`operator_step`), then the safety budget (the session's ``budget``): ``"budget"`` once it is spent
        (the leg is cut there)."""
        check_store(getattr(self, "store_guard", None))
        how = self.operator_step(i, n_items)
        if isinstance(how, str):
            return how
        budget = getattr(self, "budget", None)
        if budget is not None and budget.spent():
            cur = self.vehicle.progress.current
            self.journal.note("budget", f"leg {i}: safety budget spent at item {cur}/{n_items}: {budget.reason}; cut")
            return "budget"
        return how

    def operator_step(self, i: int, n_items: int) -> str | float | None:
        """The boat's new commands, carried out in order. Returns ``"skip"`` or ``"replan"`` (the leg ends
        here), the wall seconds spent paused (the leg's deadline waits that much longer), or None."""
        if self.commands is None:
            return None
        waited = 0.0
        for cmd in self.commands.take():
            how = self._carry_out(cmd, i, n_items)
            if isinstance(how, str):
                return how
            waited += how or 0.0
        return waited or None

    def _carry_out(self, cmd: dict, i: int, n_items: int, *, paused: bool = False) -> str | float | None:
        act = cmd["action"]
        if act == "pause" and not paused:
            return self._operator_pause(cmd, i, n_items)
        if act in ("pause", "resume"):
            self._answer(cmd, "already paused" if paused else "not paused: nothing to resume", ok=False)
            return None
        if act in ("approve", "reject"):
            self._answer(cmd, f"no leg awaits approval (leg {i + 1} is flying)", ok=False)
            return None
        if act in ("skip", "replan"):
            what = (
                "the leg ends here: HOLD, its samples absorbed, the next leg planned"
                if act == "skip"
                else "the leg is planned again from here (this attempt kept, its samples too)"
            )
            self._answer(cmd, f"leg {i + 1} at item {self.vehicle.progress.current}/{n_items}: {what}")
            return act
        if act == "end":
            self._operator_end(cmd, i)
        return None

    def _operator_end(self, cmd: dict, i: int) -> None:
        mode = cmd.get("end_mode") or "HOLD"
        try:
            self.vehicle.set_mode(mode)
        except MavlinkError as exc:
            self._answer(cmd, f"the vehicle refused {mode} ({exc}); {self.vehicle.wait_mode} instead", ok=False)
            mode = self.vehicle.keep_station()
        text = f"mission ended in leg {i + 1}: {mode}; state saved (continue with --resume)"
        self._answer(cmd, text)
        raise Ended(text, mode)

    def _operator_pause(self, cmd: dict, i: int, n_items: int) -> str | float | None:
        """The boat waits (:meth:`~passt_mav.mavlink.Vehicle.keep_station`: LOITER or HOLD), then the next command
        (module docstring). Returns the wall seconds paused, or ``"skip"``/``"replan"``."""
        v = self.vehicle
        # the pause's wait is no end of the leg: the telemetry log says so before the mode command
        mark_leg(self.link, i, "pause")
        try:
            mode = v.keep_station()
        except MavlinkError as exc:
            self._answer(cmd, f"{v.wait_mode} refused or not confirmed: {exc}", ok=False)
            return None
        seq = int(v.progress.current)
        self._answer(
            cmd,
            f"leg {i + 1} paused: {mode} at item {seq}/{n_items} (resume within {self.pause_timeout_s:.0f} s, "
            "--pause-timeout)",
        )
        if self.waits is not None:
            self.waits.begin("pause", i)
        try:
            return self._paused(i, n_items)
        finally:
            if self.waits is not None:
                self.waits.end()

    def _paused(self, i: int, n_items: int) -> str | float:
        """The wait of a pause (:meth:`_operator_pause`) until a command or AUTO ends it."""
        v = self.vehicle
        t0 = self.link.clock.now()
        while True:
            for c in self.commands.take() if self.commands is not None else ():
                if c["action"] == "resume":
                    return self._operator_resume(c, i, n_items, t0)
                how = self._carry_out(c, i, n_items, paused=True)
                if isinstance(how, str):
                    return how
            if v.mode == AUTO:
                mark_leg(self.link, i, "resume")
                self.journal.note("command", f"leg {i}: back in AUTO (not by the page) while paused by the operator")
                return self.link.clock.now() - t0
            if self.rebooted.is_set():
                return self.link.clock.now() - t0  # fly() handles the reboot (it resumes the leg)
            if self.link.lost:
                self.reconnect_within_window(i, self.lost_since(), "pause")
            if self.link.clock.now() - t0 > self.pause_timeout_s:
                raise Paused(
                    f"leg {i}: paused by the operator for {self.pause_timeout_s:.0f} s (--pause-timeout) without "
                    f"a resume; stopping in {self.vehicle.wait_mode} (continue with --resume)"
                )
            self.link.idle(0.05)

    def _operator_resume(self, cmd: dict, i: int, n_items: int, t0: float) -> float:
        """AUTO again at the item the vehicle was flying (Rover resumes its mission where HOLD stopped it)."""
        v = self.vehicle
        try:
            v.set_mode("AUTO")
        except MavlinkError as exc:
            self._answer(cmd, f"AUTO refused or not confirmed ({exc}); still in {v.wait_mode}", ok=False)
            return self.link.clock.now() - t0
        mark_leg(self.link, i, "resume")
        self.set_speed_again(i, "the operator's pause")
        mode = v.mode_name or str(v.mode)
        self._answer(cmd, f"leg {i + 1} resumed: {mode} at item {v.progress.current}/{n_items}")
        return self.link.clock.now() - t0

    def pause(self, i: int, mode: int, n_items: int) -> float | str:
        """A pilot took the vehicle out of AUTO (into ``mode``): wait up to ``pause_timeout_s`` (wall s) for AUTO to
        come back, the page's commands taken meanwhile in the order given (:meth:`_piloted`). Returns the wall
        seconds waited, or ``"skip"``/``"replan"``; :class:`~passt_mav.vehicle.flow.Paused` when AUTO did not
        come back, :class:`~passt_mav.vehicle.flow.Rebooted` if the vehicle rebooted."""
        name = ROVER_MODE_NAMES.get(mode, str(mode))
        self.journal.say(
            f"leg {i + 1}: the vehicle left AUTO (mode {name}): a pilot has control; pausing "
            f"(waiting up to {self.pause_timeout_s:.0f} s for AUTO, or Resume on the page)"
        )
        self.journal.note("pilot_takeover", f"leg {i + 1}: vehicle left AUTO (mode {name}) at {utc_now()}")
        t0 = self.link.clock.now()
        while self.link.clock.now() - t0 < self.pause_timeout_s:
            how = self._piloted(i, n_items, name)
            if isinstance(how, str):
                return how
            if self.vehicle.mode == AUTO:
                if not how:  # (a Resume from the page set the speed again already)
                    self.set_speed_again(i, "the pilot's AUTO")
                self.journal.say(f"leg {i + 1}: back in AUTO; continuing")
                self.journal.note("pilot_released", f"leg {i + 1}: back in AUTO")
                return self.link.clock.now() - t0
            if self.rebooted.is_set():
                raise Rebooted()  # not the pilot after all (or the pilot rebooted it): fly() resumes
            if self.link.lost:
                self.reconnect_within_window(i, self.lost_since(), "pause")
            self.link.idle(0.05)
        raise Paused(
            f"leg {i + 1}: the vehicle stayed in {name} for {self.pause_timeout_s:.0f} s; stopping in "
            f"{self.vehicle.wait_mode}"
        )

    def _piloted(self, i: int, n_items: int, name: str) -> str | bool:
        """The page's commands while a pilot holds the boat in mode ``name``, in order: ``resume`` sets AUTO again
        (True once it did), ``skip``/``replan`` end the leg there (returned), ``end`` ends the mission; a pause
        is answered as already holding. False when nothing set AUTO."""
        for c in self.commands.take() if self.commands is not None else ():
            act = c["action"]
            if act == "resume":
                self._operator_resume(c, i, n_items, self.link.clock.now())  # (answered either way)
                if self.vehicle.mode == AUTO:
                    return True
            elif act == "pause":
                self._answer(c, f"already holding: a pilot has control (mode {name})", ok=False)
            else:
                how = self._carry_out(c, i, n_items, paused=True)
                if isinstance(how, str):
                    return how
        return False

    def await_approval(self, i: int, what: str, timeout_s: float, on_timeout: str) -> str:
        """Approve mode: leg ``i`` (``what``: its figures, one line) waits for the operator before its upload.
        Returns ``"approve"`` or ``"reject"`` (an ``approve``/``reject`` command for this leg, or for no leg in
        particular); ``end`` ends the mission (:class:`Ended`). Past ``timeout_s`` wall seconds ``on_timeout``
        decides: ``approve`` (returns ``"timeout"``), or ``hold``: :class:`~passt_mav.vehicle.flow.Paused` (the
        vehicle is held)."""
        self.journal.note("approval", f"leg {i}: awaits approval ({what}); timeout {timeout_s:.0f} s: {on_timeout}")
        self.journal.say(
            f"leg {i + 1} awaits approval ({what}): approve or reject on the live page, or type a (approve) or "
            f"r (reject) + Enter here; in {timeout_s:.0f} s: {on_timeout}"
        )
        t0 = self.link.clock.now()
        while True:
            for c in self.commands.take() if self.commands is not None else ():
                act = c["action"]
                if act in ("approve", "reject") and c.get("leg") in (None, i):
                    self._answer(c, f"leg {i + 1} " + ("approved" if act == "approve" else "rejected: planned again"))
                    return act
                if act == "end":
                    self._operator_end(c, i)
                why = f"leg {c.get('leg', 0) + 1} does not await approval" if act in ("approve", "reject") else ""
                self._answer(c, why or f"no leg is flying: leg {i + 1} awaits approval", ok=False)
            if self.link.clock.now() - t0 > timeout_s:
                if on_timeout == "approve":
                    self.journal.note(
                        "approval", f"leg {i}: no answer within {timeout_s:.0f} s: approved by the timeout"
                    )
                    return "timeout"
                raise Paused(
                    f"leg {i}: no approval within {timeout_s:.0f} s (approve.on_timeout: hold): stopped in "
                    f"{self.vehicle.wait_mode}; "
                    "continue with --resume"
                )
            if self.link.lost:
                self.reconnect_within_window(i, self.lost_since(), "approval")
            self.link.idle(0.05)
