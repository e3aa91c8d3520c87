"""Progress of long work, one helper for every command, so every long job shows its progress the same way.

``progress(iterable_or_total, desc, unit)`` shows a tqdm bar with rate and ETA when stderr is a
terminal, and otherwise (a log file, CI, a pipe) writes plain lines to stderr: one when the work
starts, one each time another ``every_pct`` % is done or ``every_s`` seconds have passed since the
last line (whichever comes first, never more than one line per ``min_s`` seconds), and one at the
end, e.g. ::

    evaluate: 12/40 trials (30 %), 41 s elapsed, ETA 96 s

so a log holds at most about ``100 / every_pct`` lines plus one per ``every_s`` seconds of work,
never a line per item (tqdm's own non-terminal output is a carriage-return stream, unreadable in a
log). ``quiet=True`` shows nothing. Work of unknown length (``total=None``: waiting for a vehicle)
reports elapsed time every ``every_s`` seconds.

Use it as an iterator wrapper (``for x in progress(items, "replay", "leg")``) or by hand
(``with progress(40, "evaluate", "trial") as p: ... p.update(k)``); ``p.note(text)`` sets the
bar's postfix / the plain line's trailing note (e.g. a loss). Only the standard library and tqdm
are imported (tqdm only for a terminal), so any layer may use it.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any, Self, TextIO

__all__ = ["Progress", "progress"]


def _fmt_s(s: float) -> str:
    s = max(0.0, float(s))
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


class Progress:
    """One unit of long work's progress (module docstring); build it with :func:`progress`."""

    def __init__(
        self,
        iterable: Iterable | None = None,
        *,
        total: int | None = None,
        desc: str = "",
        unit: str = "it",
        quiet: bool = False,
        stream: TextIO | None = None,
        every_pct: float = 10.0,
        every_s: float = 30.0,
        min_s: float = 1.0,
        tty: bool | None = None,
    ):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total = None if total is None else int(total)
        self.desc, self.unit, self.quiet = desc, unit, bool(quiet)
        self.stream = stream if stream is not None else sys.stderr
        self.every_pct, self.every_s, self.min_s = float(every_pct), float(every_s), float(min_s)
        self.n = 0
        self._note = ""
        self._t0 = self._last = time.monotonic()
        self._next_pct = self.every_pct
        self._closed = False
        self._bar = None
        if tty is None:
            isatty = getattr(self.stream, "isatty", None)
            tty = bool(isatty and isatty())
        self.tty = tty
        if self.quiet:
            return
        if self.tty:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, file=self.stream, dynamic_ncols=True, leave=False)
        else:
            self._line("started" if self.total is None else f"0/{self.total} {self._units(self.total)}")

    # -- plain lines ---------------------------------------------------------------------------
    def _units(self, n: int) -> str:
        u = self.unit
        return u if n == 1 or len(u) <= 2 or u.endswith("s") or not u.isalpha() else u + "s"

    def _line(self, text: str) -> None:
        note = f" ({self._note})" if self._note else ""
        print(f"{self.desc}: {text}{note}" if self.desc else text + note, file=self.stream, flush=True)
        self._last = time.monotonic()

    def _status(self) -> str:
        el = time.monotonic() - self._t0
        if self.total is None:
            done = f"{self.n} {self._units(self.n)}, " if self.n else ""
            return f"{done}{_fmt_s(el)} elapsed"
        pct = 100.0 * self.n / self.total if self.total else 100.0
        eta = f", ETA {_fmt_s(el / self.n * (self.total - self.n))}" if 0 < self.n < self.total else ""
        return f"{self.n}/{self.total} {self._units(self.total)} ({pct:.0f} %), {_fmt_s(el)} elapsed{eta}"

    def _maybe_line(self) -> None:
        now = time.monotonic()
        if now - self._last < self.min_s and not (self.total is not None and self.n >= self.total):
            return
        due = now - self._last >= self.every_s
        if self.total:
            pct = 100.0 * self.n / self.total
            if pct >= self._next_pct:
                due = True
                while self._next_pct <= pct:
                    self._next_pct += self.every_pct
        if due and not (self.total is not None and self.n >= self.total):  # the end line comes from close()
            self._line(self._status())

    # -- the interface ----------------------------------------------------------------------------
    def update(self, n: int = 1) -> None:
        """``n`` more units done."""
        self.n += int(n)
        if self.quiet:
            return
        if self._bar is not None:
            self._bar.update(int(n))
        else:
            self._maybe_line()

    def tick(self) -> None:
        """Nothing done, time passed (work of unknown length): a plain line if ``every_s`` is up."""
        if self.quiet:
            return
        if self._bar is not None:
            self._bar.refresh()
        elif time.monotonic() - self._last >= self.every_s:
            self._line(self._status())

    def note(self, text: str) -> None:
        """A short note shown after the count (bar postfix / end of the plain line), e.g. ``loss 0.012``."""
        self._note = str(text)
        if self._bar is not None:
            self._bar.set_postfix_str(self._note, refresh=False)

    def close(self, status: str | None = None) -> None:
        """End the work: the bar goes, the plain output gets its last line (``status`` or the count)."""
        if self._closed:
            return
        self._closed = True
        if self.quiet:
            return
        if self._bar is not None:
            self._bar.close()
        else:
            el = _fmt_s(time.monotonic() - self._t0)
            if status is None:
                count = f"{self.n}/{self.total}" if self.total is not None else str(self.n)
                status = f"{count} {self._units(self.total or self.n)} done in {el}"
            self._line(status)

    def __iter__(self) -> Iterator[Any]:
        if self.iterable is None:
            raise TypeError("this Progress was built from a total: call update() instead of iterating")
        try:
            for x in self.iterable:
                yield x
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def progress(
    it: Iterable | int | None = None,
    desc: str = "",
    unit: str = "it",
    *,
    total: int | None = None,
    quiet: bool = False,
    stream: TextIO | None = None,
    every_pct: float = 10.0,
    every_s: float = 30.0,
    min_s: float = 1.0,
    tty: bool | None = None,
) -> Progress:
    """A :class:`Progress` over an iterable, or for ``it`` (an int) units done by :meth:`Progress.update`,
    or of unknown length (``None``). Bar on a terminal stderr, plain lines otherwise (module docstring)."""
    if isinstance(it, int) and not isinstance(it, bool):
        it, total = None, it
    return Progress(
        it,
        total=total,
        desc=desc,
        unit=unit,
        quiet=quiet,
        stream=stream,
        every_pct=every_pct,
        every_s=every_s,
        min_s=min_s,
        tty=tty,
    )
