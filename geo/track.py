"""A vehicle's track in time: its position at any moment between two fixes.

A current reading (NAMED_VALUE_FLOAT ``CUR_U``/``CUR_V``, or a DataFlash ``NVF``) is
stamped with the autopilot's ``time_boot_ms`` (ms since boot) but carries no
position; the position fixes (GLOBAL_POSITION_INT, DataFlash ``POS``) come at
their own times, usually slower (1 Hz telemetry against a 4 Hz sensor). A boat's
track is smooth at that scale, so the reading is placed by linear interpolation
between the fix at or before it and the fix at or after it, **only when the two
are at most ``max_gap_ms`` apart** (the *gap*; 0 when a fix has the reading's own
time). Beyond that the reading is dropped: a turn at a waypoint inside a long gap
would be cut short. Error bound: for a boat at speed ``s`` turning inside the
gap, the interpolated point is at most about ``s * gap / 4`` from the true track
(3.75 m at 5 m/s and the default 3 s gap; a straight run at constant speed is exact).

This is the one rule every sample takes: the live collector
(:class:`passt_mav.mavlink.SampleCollector`), the tlog reader and the DataFlash
reader (:mod:`passt_mav.runs.tlog`) all ask a :class:`Track`.

Units and frames: times in ms of the autopilot's clock (``time_boot_ms``; one
:class:`Track` holds one boot: a reboot restarts the clock, start a new track);
lat/lon WGS84 degrees. Longitudes are interpolated along the short way round
(a track across the antimeridian stays in [-180, 180)).
"""

from __future__ import annotations

import bisect
from typing import NamedTuple

__all__ = ["Track", "TrackPosition", "DEFAULT_MAX_GAP_MS"]

#: Default bound on the interpolation gap (ms): three 1 Hz fix intervals, so that one or two lost
#: GLOBAL_POSITION_INT in a row (a lossy radio) still leave the readings between them usable.
DEFAULT_MAX_GAP_MS = 3000


class TrackPosition(NamedTuple):
    """Where the vehicle was: ``lat``/``lon`` (deg) and the ``gap_ms`` between the fixes used (0: a fix at that time)."""

    lat: float
    lon: float
    gap_ms: int


class Track:
    """Position fixes of one boot, kept in time order, interpolated at any time (module docstring).

    Args:
        max_gap_ms: largest time between the two fixes a position is interpolated from (ms, > 0).
    """

    def __init__(self, max_gap_ms: int = DEFAULT_MAX_GAP_MS):
        if not int(max_gap_ms) > 0:
            raise ValueError(f"max_gap_ms must be > 0, got {max_gap_ms!r}")
        self.max_gap_ms = int(max_gap_ms)
        self._t: list[int] = []
        self._ll: list[tuple[float, float]] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def last_ms(self) -> int | None:
        """Time of the newest fix (ms), or None."""
        return self._t[-1] if self._t else None

    def add(self, t_ms: int, lat: float, lon: float) -> None:
        """Add a fix (any order; a second fix at the same time replaces the first)."""
        t = int(t_ms)
        i = bisect.bisect_left(self._t, t)
        if i < len(self._t) and self._t[i] == t:
            self._ll[i] = (float(lat), float(lon))
        else:
            self._t.insert(i, t)
            self._ll.insert(i, (float(lat), float(lon)))

    def forget_before(self, t_ms: int) -> None:
        """Drop fixes older than ``t_ms`` but the newest of them (still needed to bracket ``t_ms``)."""
        i = bisect.bisect_left(self._t, int(t_ms)) - 1
        if i > 0:
            del self._t[:i], self._ll[:i]

    def clear(self) -> None:
        self._t.clear(), self._ll.clear()

    def at(self, t_ms: int) -> TrackPosition | None:
        """The position at ``t_ms`` (ms), or None when no two fixes within ``max_gap_ms`` bracket it."""
        t = int(t_ms)
        i = bisect.bisect_left(self._t, t)
        if i < len(self._t) and self._t[i] == t:
            la, lo = self._ll[i]
            return TrackPosition(la, lo, 0)
        if i == 0 or i == len(self._t):
            return None
        t0, t1 = self._t[i - 1], self._t[i]
        if t1 - t0 > self.max_gap_ms:
            return None
        (la0, lo0), (la1, lo1) = self._ll[i - 1], self._ll[i]
        w = (t - t0) / (t1 - t0)
        dlo = (lo1 - lo0 + 180.0) % 360.0 - 180.0
        lon = (lo0 + w * dlo + 180.0) % 360.0 - 180.0
        return TrackPosition(la0 + w * (la1 - la0), lon, t1 - t0)

    def may_bracket(self, t_ms: int, now_ms: int) -> bool:
        """Whether a fix still to come could place a reading at ``t_ms``, vehicle time now being ``now_ms``.

        True while no fix at or after ``t_ms`` has arrived and one arriving now could still be within
        ``max_gap_ms`` of the last fix before ``t_ms`` (or, with no fix before it, have its exact time).
        A live collector holds such a reading; otherwise :meth:`at` is final.
        """
        t = int(t_ms)
        i = bisect.bisect_left(self._t, t)
        if i < len(self._t):
            return False  # the fix after it is here: at() has decided
        if i == 0:
            return int(now_ms) <= t
        return int(now_ms) - self._t[i - 1] <= self.max_gap_ms
