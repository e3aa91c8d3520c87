"""What a run keeps across controller sessions: ``--resume`` (docs/resilience.md, "Resume keeps the record").

A mixin of :class:`~passt_mav.vehicle.controller.MissionController`: the state to continue from (the last
complete leg's ``estimate.nc``), the interrupted attempt of the leg that was in flight (its files to
``legs/NNN/attempt_K/``, a summary of it in the re-planned leg's record) and the run's ``sessions`` (each
controller session's first leg and the legs it planned: where a replay restarts as the run did). It uses
the controller's ``rd``, ``store``, ``step``, ``loop``, ``run_clock``, ``resume``, ``events``, ``leg_records``
and ``_say``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from passt_mav.errors import UserError
from passt_mav.vehicle.flow import utc_now

if TYPE_CHECKING:
    from collections.abc import Callable

    from passt_mav.loop.legstep import LegStep
    from passt_mav.runs.rundir import RunDir
    from passt_mav.runs.store import SampleStore
    from passt_mav.vehicle.clock import RunClock

__all__ = ["ResumeRecord"]


class ResumeRecord:
    """The resume part of the mission controller (module docstring)."""

    if TYPE_CHECKING:  # the controller's, which this mixin uses (module docstring)
        rd: RunDir
        store: SampleStore  # (run() opens it)
        step: LegStep
        run_clock: RunClock
        resume: bool
        started_utc: str
        leg_records: list[dict]
        status: str
        _write_summary: Callable[[], None]  # (an attribute: a fleet's boat is handed the fleet's)

        @property
        def events(self) -> list[str]: ...
        def _say(self, s: str) -> None: ...

    def _init_resume_record(self) -> None:
        self._attempts: dict[int, list[dict]] = {}  # leg -> its interrupted attempts
        #: one record per controller session of this run (a resume adds one): UTC start, first leg, the legs
        #: it planned in order (their clock STATUSTEXTs in the log)
        self.sessions: list[dict] = []

    def _old_summary(self) -> dict | None:
        return self.rd.read_summary() if self.rd.summary_file.exists() else None

    def _initial_state(self) -> tuple[np.ndarray, float, int]:
        """(state, t_state, first leg index)."""
        state, t_state = self.step.initial_state()
        if not self.resume:
            self.sessions = [{"started_utc": self.started_utc, "first_leg": 0, "planned": []}]
            return state, t_state, 0
        from passt_mav.fields.field import load_field

        done = [r for r in self.rd.read_legs() if r.get("status") == "complete"]
        done.sort(key=lambda r: int(r["index"]))
        # legs must be contiguous from 0: a gap means the directory is not one run
        done = [r for k, r in enumerate(done) if int(r["index"]) == k]
        old = self._old_summary()
        if old is not None:
            self.run_clock.restore(old.get("clock") or {})
            self.started_utc = old.get("started_utc") or self.started_utc
            self.events[:0] = list(old.get("events") or [])  # (before what resume_boots found)
        self.leg_records = done
        self.sessions = [
            *((old or {}).get("sessions") or []),
            {"started_utc": utc_now(), "first_leg": len(done), "planned": []},
        ]
        if self._archive_attempt(len(done)) and len(self.sessions) > 1:
            # the attempt was planned by the session before: one killed (SIGKILL, a power cut) last wrote its
            # summary when a leg completed, before it planned this one; the replay restarts by these lists
            planned = self.sessions[-2].setdefault("planned", [])
            if not planned or planned[-1] != len(done):
                planned.append(len(done))
        # summary.json says "running" again (no finished_utc) from this session's start: the live view, which
        # reads a finished run as a record, takes this session's commands (an approval, a pause)
        self.status = "running"
        self._write_summary()
        if not done:
            # killed during leg 0: still say so (the store keeps that leg's samples; it is re-planned)
            self._say(f"resuming {self.rd.root}: no leg completed yet; leg 1 is re-planned from here")
            self.events.append(f"resumed before leg 1 completed at {utc_now()}")
            return state, t_state, 0
        last = done[-1]
        est = self.rd.estimate_file(int(last["index"]))
        if not est.exists():
            raise UserError(f"cannot resume: {est} is missing")
        fld = load_field(est)
        self.step.resume_after(len(done), float(last["t_state"]))
        self._say(f"resuming {self.rd.root}: {len(done)} leg(s) done, state at field time {last['t_state']:.1f}")
        self.events.append(f"resumed after leg {len(done)} at {utc_now()}")
        return np.array(fld.data[0], dtype=np.float32), float(last["t_state"]), len(done)

    def _archive_attempt(self, i: int, status: str = "interrupted") -> bool:
        """Leg ``i`` was in flight when the controller stopped (or the operator asked to re-plan it: ``status``):
        keep that attempt's record. Its files move to
        ``legs/NNN/attempt_K/`` (K = 1, 2, ...) and a summary of it (path, start cell, clock, samples stored)
        goes to :attr:`_attempts`, which the re-planned leg's record lists under ``attempts``. Its samples stay
        in the store under leg ``i``: measurements like any other, the re-flown leg absorbs them too. Returns
        whether there was such an attempt."""
        if not self.rd.leg_file(i).exists():
            return False
        old = self.rd.read_leg(i)
        if old.get("status") == "complete":
            return False
        d = self.rd.leg_dir(i)
        k = 1 + sum(1 for x in d.glob("attempt_*") if x.is_dir())
        dest = d / f"attempt_{k}"
        dest.mkdir()
        for f in d.iterdir():
            if f.is_file():
                f.rename(dest / f.name)
        keep = ("path", "start_cell", "t_now", "t_start", "forecast_steps_before", "clock_reading")
        self._attempts[i] = [
            *old.get("attempts", []),
            {
                "attempt": k,
                "status": status,
                "dir": f"attempt_{k}",
                "n_samples_stored": self.store.count(i),
                **{key: old[key] for key in keep if key in old},
            },
        ]
        self._say(f"leg {i + 1}: its attempt {k} ({status}) kept in {dest} ({self.store.count(i)} samples stored)")
        return True
