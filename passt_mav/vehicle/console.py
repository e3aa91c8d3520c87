"""The operator's commands from the live page, carried out while a leg flies (docs/console.md).

A mixin of :class:`~passt_mav.vehicle.session.VehicleSession` (as :mod:`~passt_mav.vehicle.outages` is): it uses
the session's ``vehicle``, ``link``, ``journal``, ``pause_timeout_s``, ``resume_seq``, ``rebooted``,
``set_speed_again`` and ``reconnect_within_window``. The view server appends each command to the run's
channel (:mod:`passt_mav.runs.commands`); :meth:`OperatorCommands.operator_step`, called once per turn of
:meth:`VehicleSession.fly`, reads this boat's new ones and acts through the paths a pilot takeover and a
link loss already use:

* ``pause``: HOLD; then wait as for a pilot who took over (:meth:`VehicleSession.pause`): for ``resume``
  (AUTO again: the vehicle goes on at the item it was flying, the leg's speed set again past its first item),
  ``skip``, ``replan`` or ``end``, for AUTO set by someone else, or until ``pause_timeout_s`` (wall s) has
  passed: then :class:`~passt_mav.vehicle.session.Paused` (the run stops in HOLD, status ``paused``,
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
"""

from __future__ import annotations

import time

from passt_mav.errors import MavlinkError
from passt_mav.mavlink.vehicle import ROVER_MODE_NAMES, ROVER_MODES

__all__ = ["OperatorCommands", "Ended"]

AUTO = ROVER_MODES["AUTO"]


class Ended(Exception):  # noqa: N818 - an outcome, like Paused
    """The operator ended the mission; the vehicle is in ``mode`` (``HOLD`` or ``RTL``) already."""

    def __init__(self, text: str, mode: str):
        super().__init__(text)
        self.mode = mode


class OperatorCommands:
    """The operator's commands for one boat (module docstring). ``commands``: the boat's
    :class:`~passt_mav.runs.commands.CommandReader`, None = no channel (nothing is read)."""

    commands = None
    #: the boat's :class:`~passt_mav.vehicle.waits.WaitLog` (:class:`VehicleSession` makes it): a pause's drift is recorded
    waits = None

    def _answer(self, cmd: dict, text: str, *, ok: bool = True) -> None:
        """The command's answer: an event of kind ``command`` with its id, summary.json's events, a line."""
        who = cmd.get("source") or "the page"
        line = f"operator ({who}): {cmd['action']}" + (f" {cmd['end_mode']}" if cmd.get("end_mode") else "")
        line += f": {text}"
        self.journal.note("command", line, level="ok" if ok else "warn", command_id=cmd.get("id"))
        self.journal.say(line)

    def console_turn(self, i: int, n_items: int) -> str | float | None:
        """One turn of :meth:`VehicleSession.fly`: the operator's commands (:meth:`operator_step`), then the safety
        budget (the session's ``budget``): ``"budget"`` once it is spent (the leg is cut there)."""
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
        for cmd in self.commands.poll():
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
        from passt_mav.vehicle.session import Paused

        v = self.vehicle
        t0 = time.monotonic()
        while True:
            for c in self.commands.poll():
                if c["action"] == "resume":
                    return self._operator_resume(c, i, n_items, t0)
                how = self._carry_out(c, i, n_items, paused=True)
                if isinstance(how, str):
                    return how
            if v.mode == AUTO:
                self.journal.note("command", f"leg {i}: back in AUTO (not by the page) while paused by the operator")
                return time.monotonic() - t0
            if self.rebooted.is_set():
                return time.monotonic() - t0  # fly() handles the reboot (it resumes the leg)
            if self.link.lost:
                self.reconnect_within_window(i, time.monotonic() - self._silent_s(), "pause")
            if time.monotonic() - t0 > self.pause_timeout_s:
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
            return time.monotonic() - t0
        self.set_speed_again(i, "the operator's pause")
        mode = ROVER_MODE_NAMES.get(v.mode, str(v.mode))
        self._answer(cmd, f"leg {i + 1} resumed: {mode} at item {v.progress.current}/{n_items}")
        return time.monotonic() - t0

    def await_approval(self, i: int, what: str, timeout_s: float, on_timeout: str) -> str:
        """Approve mode: leg ``i`` (``what``: its figures, one line) waits for the operator before its upload.
        Returns ``"approve"`` or ``"reject"`` (an ``approve``/``reject`` command for this leg, or for no leg in
        particular); ``end`` ends the mission (:class:`Ended`). Past ``timeout_s`` wall seconds ``on_timeout``
        decides: ``approve`` (returns ``"timeout"``), or ``hold``: :class:`~passt_mav.vehicle.session.Paused` (the
        vehicle is held)."""
        from passt_mav.vehicle.session import Paused

        self.journal.note("approval", f"leg {i}: awaits approval ({what}); timeout {timeout_s:.0f} s: {on_timeout}")
        self.journal.say(
            f"leg {i + 1} awaits approval ({what}): approve or reject on the live page, or type a (approve) or "
            f"r (reject) + Enter here; in {timeout_s:.0f} s: {on_timeout}"
        )
        t0 = time.monotonic()
        while True:
            for c in self.commands.poll() if self.commands is not None else ():
                act = c["action"]
                if act in ("approve", "reject") and c.get("leg") in (None, i):
                    self._answer(c, f"leg {i + 1} " + ("approved" if act == "approve" else "rejected: planned again"))
                    return act
                if act == "end":
                    self._operator_end(c, i)
                why = f"leg {c.get('leg', 0) + 1} does not await approval" if act in ("approve", "reject") else ""
                self._answer(c, why or f"no leg is flying: leg {i + 1} awaits approval", ok=False)
            if time.monotonic() - t0 > timeout_s:
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
                self.reconnect_within_window(i, time.monotonic() - self._silent_s(), "approval")
            self.link.idle(0.05)
