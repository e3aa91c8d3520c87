"""The one clock of the vehicle side: every wait, timeout, deadline and backstop asks a :class:`Clock`.

Two kinds of seconds meet on a link (docs/architecture.md, "Who owns the clock"):

* **wall seconds**: the ground station's own time. Timeouts, deadlines, back-offs and backstops count
  them (:meth:`Clock.now`, monotonic); records stamp UTC with :meth:`Clock.wall`.
* **vehicle seconds**: the vehicle's time since boot (``time_boot_ms``). A real boat or a simulator at a
  speed-up runs them at ``speedup`` x wall time (:func:`wall_seconds`, :func:`vehicle_seconds`); a
  simulator in lockstep (:class:`~passt_mav.mavlink.link.Lockstep`) runs them only while we wait for it,
  one step at a time, and a wait of ``t`` wall seconds may step ``t x pace`` of them (:class:`StepBudget`).

A :class:`~passt_mav.mavlink.Link` owns one clock (``Link(clock=...)``, :data:`SYSTEM_CLOCK` by default);
the client and the controller's vehicle side ask ``link.clock`` (or a clock handed to them), never the
``time`` module (``tests/test_layers.py`` checks it). A test may hand the link a clock of its own.
"""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "WallClock", "SYSTEM_CLOCK", "clock_of", "Timeout", "StepBudget", "wall_seconds", "vehicle_seconds"]


@runtime_checkable
class Clock(Protocol):
    """What the vehicle side asks of a clock."""

    def now(self) -> float:
        """Wall seconds on a monotonic clock (timeouts, deadlines, durations)."""

    def wall(self) -> float:
        """UTC now, seconds since the epoch (records)."""

    def wall_ns(self) -> int:
        """UTC now, integer nanoseconds since the epoch (TIMESYNC's ``ts1``)."""

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` wall seconds."""


class WallClock:
    """The machine's clocks: ``time.monotonic``, ``time.time``, ``time.time_ns``, ``time.sleep``."""

    def now(self) -> float:
        return time.monotonic()

    def wall(self) -> float:
        return time.time()

    def wall_ns(self) -> int:
        return time.time_ns()

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def __repr__(self) -> str:
        return "WallClock()"


#: the machine's clock: a link's unless it is handed another
SYSTEM_CLOCK = WallClock()


def clock_of(obj, default: Clock = SYSTEM_CLOCK) -> Clock:
    """``obj.clock`` when ``obj`` (a link) has a :class:`Clock`, else ``default``."""
    c = getattr(obj, "clock", None)
    return c if isinstance(c, Clock) else default


class Timeout:
    """A wall-clock deadline ``seconds`` from now on ``clock``.

    Attributes:
        t0: when it was set (``clock.now()``, wall s).
        end: when it runs out (wall s).
    """

    __slots__ = ("clock", "end", "t0")

    def __init__(self, clock: Clock, seconds: float):
        self.clock = clock
        self.t0 = clock.now()
        self.end = self.t0 + seconds

    def left(self) -> float:
        """Wall seconds left (negative once past)."""
        return self.end - self.clock.now()

    def expired(self) -> bool:
        """The deadline is reached."""
        return self.clock.now() >= self.end

    def elapsed(self) -> float:
        """Wall seconds since it was set."""
        return self.clock.now() - self.t0


class StepBudget:
    """What a wait of ``wall_timeout`` wall seconds may step of a lockstep vehicle's clock: ``wall_timeout x pace``
    vehicle seconds (None: no bound). The vehicle's clock runs only while we step it, so the wait counts the
    vehicle seconds stepped, not the wall seconds passed."""

    __slots__ = ("budget", "ran")

    def __init__(self, wall_timeout: float | None, pace: float):
        #: vehicle seconds the wait may step
        self.budget = float("inf") if wall_timeout is None else max(float(wall_timeout), 0.0) * pace
        #: vehicle seconds stepped so far
        self.ran = 0.0

    def stepped(self, seconds: float) -> None:
        """``seconds`` of the vehicle's clock ran."""
        self.ran += seconds

    def spent(self) -> bool:
        """The wait has stepped its budget."""
        return self.ran >= self.budget


def wall_seconds(vehicle_s: float, speedup: float, *, at_least: float = 0.0) -> float:
    """Wall seconds ``vehicle_s`` vehicle seconds take at ``speedup`` (vehicle s per wall s), at least ``at_least``.

    A hint for a vehicle that keeps its own clock: a simulator starved of CPU runs slower than its speed-up,
    so a limit that matters is kept in vehicle seconds and this only sizes a wall-clock wait."""
    return max(float(at_least), float(vehicle_s) / max(float(speedup), 1e-6))


def vehicle_seconds(wall_s: float, speedup: float) -> float:
    """Vehicle seconds that run in ``wall_s`` wall seconds at ``speedup`` (vehicle s per wall s)."""
    return float(wall_s) * float(speedup)
