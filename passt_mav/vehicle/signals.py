"""Stop signals: SIGTERM, SIGINT and SIGHUP end a mission cleanly.

``passt-mav run`` flies its mission inside :class:`StopSignals` (a context manager, main thread only).
The first of these signals raises :class:`Stopped` in the main thread, where the controller catches
it: the vehicle to HOLD (or left flying in AUTO with ``vehicle.on_signal: auto``), the sample store
flushed, summary.json with status ``stopped``, the live view's ``stopped`` event; the command then
exits with ``128 + the signal's number`` (130 SIGINT, 143 SIGTERM, 129 SIGHUP), the code a shell
gives a process killed by that signal, so supervisors read it the same way.

A signal that arrives while the controller writes a run file (:meth:`StopSignals.critical`) is held
until the write is over: a file is never left half-written by a stop. One that arrives while the main
thread waits inside :mod:`threading` or :mod:`queue` (a ``Condition.wait`` behind a queue's ``get``)
is raised as soon as the thread is back in other code (a profile hook, :func:`sys.setprofile`), at the
latest when that wait times out: raised inside the wait, it left the queue's lock released while the
link's reader thread held it, and the reader died (``RuntimeError: release unlocked lock``), so the stop
found no link for its HOLD. Later signals, once stopping,
are only acknowledged (one line); the clean-up is short (HOLD, a flush, one JSON file).
"""

from __future__ import annotations

import contextlib
import queue
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any, Self

from passt_mav.vehicle.flow import Stopped

__all__ = ["Stopped", "StopSignals", "NO_SIGNALS", "exit_code"]

#: the signals that stop a mission cleanly
SIGNALS = tuple(s for s in (getattr(signal, n, None) for n in ("SIGTERM", "SIGINT", "SIGHUP")) if s is not None)


def _in_lock_wait(frame) -> bool:
    """The main thread, interrupted in ``frame``, is inside :mod:`threading` or :mod:`queue`: an exception must
    not be raised there (``Condition.wait`` re-acquires its lock in a ``finally``; interrupted there, the ``with``
    around it releases a lock another thread holds)."""
    return frame is not None and frame.f_code.co_filename in (threading.__file__, queue.__file__)


def exit_code(signum: int) -> int:
    """The command's exit code after a clean stop by ``signum``: 128 + its number (SIGTERM 143)."""
    return 128 + int(signum)


class StopSignals:
    """Handlers for :data:`SIGNALS` for the life of a ``with`` block (see the module docstring).

    ``echo``: where the one line per signal goes. Outside the main thread nothing is installed
    (Python delivers signals to the main thread only) and the object does nothing.
    """

    def __init__(self, echo: Callable[[str], None] = print):
        self.echo = echo
        self.received: int | None = None
        self._critical = 0
        self._pending = False
        self._disarmed = False
        self._old: dict[int, Any] = {}  # signal -> its handler before (a function, SIG_DFL, SIG_IGN or None)

    def __enter__(self) -> Self:
        if threading.current_thread() is threading.main_thread():
            for s in SIGNALS:
                self._old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc) -> None:
        if sys.getprofile() == self._raise_when_out:
            sys.setprofile(None)
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old.clear()

    def _handler(self, signum: int, frame) -> None:
        name = signal.Signals(signum).name
        if self.received is not None or self._disarmed:
            self.echo(f"{name} received: stopping already (HOLD, store flush, summary)")
            return
        self.received = signum
        self.echo(f"{name} received: stopping cleanly (HOLD, store flush, summary.json)")
        if self._critical:
            self._pending = True  # raised when the file being written is complete
            return
        if _in_lock_wait(frame):
            sys.setprofile(self._raise_when_out)  # (the handler runs in the main thread: its profile only)
            return
        raise Stopped(signum)

    def _raise_when_out(self, frame, _event, _arg) -> None:
        """Profile hook of the main thread while a stop waits for it to leave :mod:`threading`/:mod:`queue`
        (this module's frames, the handler's return first, are not that code either)."""
        if _in_lock_wait(frame) or frame.f_code.co_filename == __file__:
            return
        sys.setprofile(None)
        if self._disarmed:
            return
        if self._critical:
            self._pending = True
            return
        raise Stopped(self.received or signal.SIGTERM)

    @contextlib.contextmanager
    def critical(self) -> Iterator[None]:
        """A block a stop must not cut short (writing a run file): a signal meanwhile is raised after it."""
        self._critical += 1
        try:
            yield
        finally:
            self._critical -= 1
            if not self._critical and self._pending and not self._disarmed:
                self._pending = False
                raise Stopped(self.received or signal.SIGTERM)

    def disarm(self) -> None:
        """From now on signals are only acknowledged (the run is ending: its clean-up must finish)."""
        self._disarmed = True


class _NoSignals:
    """:class:`StopSignals`' interface doing nothing (a controller run from a test or a thread)."""

    received = None

    @contextlib.contextmanager
    def critical(self) -> Iterator[None]:
        yield

    def disarm(self) -> None:
        pass


#: the default of a controller that was given no :class:`StopSignals`
NO_SIGNALS = _NoSignals()
