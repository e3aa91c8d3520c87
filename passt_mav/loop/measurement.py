"""The measurement rules: how a current reading becomes a sample, and how an estimate is scored.

One module, so that the live controller, the replay of its logs and the report cannot
disagree on the same log. Its users:

* the live collector :class:`passt_mav.mavlink.SampleCollector` (rules 1-3), which the tlog replay
  (:func:`passt_mav.runs.legs.rebuild_from_tlog`) feeds the log through;
* the log readers :func:`passt_mav.runs.tlog.read_tlog` and :func:`~passt_mav.runs.tlog.read_dataflash`
  (rules 1-3; the DataFlash replay :func:`passt_mav.runs.dataflash_legs.rebuild_from_dataflash`
  reads through the latter);
* the between-leg step :mod:`passt_mav.loop.legstep` (rules 4-6) and the report
  :mod:`passt_mav.analysis.report` (rules 4-6; its boots are the tlog reader's, rule 3).

The rules, in the order a reading meets them:

1. **Halves** (:class:`HalfPairer`): a reading is two values, the east (``CUR_U``) and north
   (``CUR_V``) current in m/s, each stamped with the autopilot's clock (NAMED_VALUE_FLOAT
   ``time_boot_ms``; DataFlash ``NVF`` ``TimeUS``). A half is paired with the nearest waiting half of
   the other component at most :attr:`Rules.pair_tolerance_s` away; the reading's time is its u half's.
2. **Position** (:class:`geo.track.Track`): the reading is placed on the vehicle's track by linear
   interpolation between the fixes around it, when they are at most :attr:`Rules.max_gap_s` apart.
3. **Boots** (:class:`BootCounter`): the clock going back by more than :attr:`Rules.reboot_back_s`
   is a reboot; what follows belongs to the next boot (samples are keyed ``(boot, time_boot_ms)``).
4. **Truth** (:func:`truth_at`): the truth field at a field time, linear in time between snapshots.
5. **Error** (:func:`rmse`): RMS difference over u and v pooled, of the cells known in both arrays.
6. **Columns** (:func:`sample_columns`): sample records (store rows or dicts) as arrays.

No MAVLink, no model, no files: it imports ``geo`` and (inside the functions that need it) numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

from geo.track import DEFAULT_MAX_GAP_MS
from passt_mav.errors import UserError

__all__ = [
    "Rules",
    "RULES",
    "HalfPairer",
    "Reading",
    "BootCounter",
    "truth_at",
    "rmse",
    "sample_columns",
    "leg_number",
    "OUTSIDE_LEG",
]


@dataclass(frozen=True)
class Rules:
    """The measurement constants (seconds), and why each has its value. :data:`RULES` holds them.

    ``pair_tolerance_s`` = 0.05 s, the largest time between the u and v halves of one reading. The
    sensor script sends them back to back (two ``gcs:send_named_float`` calls) and ArduPilot stamps
    each with its own clock reading: in the Rover 4.7 SITL run of ``tests/data/dataflash``, 26 of 440
    readings had halves 1-2 ms apart in the tlog (``time_boot_ms``), and ``NVF`` ``TimeUS`` up to
    0.8 ms apart in the ``.bin``. Asking for equal stamps lost those 6 %. The bound must stay below
    half the shortest time between two readings, or a reading that lost a half would take its
    neighbour's: 50 ms serves sensors up to 10 Hz (the shipped Lua sensor sends 4 Hz) and leaves
    50 ms for the script to be held up between its two calls.

    ``max_gap_s`` = 3.0 s (:data:`geo.track.DEFAULT_MAX_GAP_MS`), the largest time between the two
    fixes a reading's position is interpolated from: three 1 Hz GLOBAL_POSITION_INT intervals, so
    one or two lost fixes (a lossy radio) still leave the readings between them placed. A boat at
    5 m/s turning inside the gap is placed at most about 3.75 m (speed x gap / 4) from its track.

    ``reboot_back_s`` = 3.0 s: the vehicle's clock going back by more than this is a reboot. One link
    delivers a vehicle's messages in order and a log keeps the order they came in, so time going
    back by more than a few fix intervals is a restarted clock, not reordering; a reboot takes it
    from a mission's minutes back to a fresh boot's seconds. The controller numbers boots this way
    live (the sample store keys samples by boot), so the log readers and the report do too.
    """

    pair_tolerance_s: float = 0.05
    max_gap_s: float = DEFAULT_MAX_GAP_MS / 1000.0
    reboot_back_s: float = 3.0

    @property
    def pair_tolerance_ms(self) -> int:
        """:attr:`pair_tolerance_s` in ms (the autopilot's clock counts ms)."""
        return int(round(self.pair_tolerance_s * 1000.0))

    @property
    def max_gap_ms(self) -> int:
        """:attr:`max_gap_s` in ms."""
        return int(round(self.max_gap_s * 1000.0))

    @property
    def reboot_back_ms(self) -> int:
        """:attr:`reboot_back_s` in ms."""
        return int(round(self.reboot_back_s * 1000.0))

    def describe(self) -> dict[str, float]:
        """The constants as a record (s)."""
        return {
            "pair_tolerance_s": self.pair_tolerance_s,
            "max_gap_s": self.max_gap_s,
            "reboot_back_s": self.reboot_back_s,
        }


#: the rules every reader of a measurement follows (:class:`Rules`)
RULES = Rules()


# -- 1. the halves of a reading ---------------------------------------------------------------------
class Reading(NamedTuple):
    """A paired reading: ``t_ms`` (its u half's stamp, ms), ``u``/``v`` (m/s east/north) and what the
    caller attached to each half (``meta_u``, ``meta_v``: e.g. reception time, leg, source)."""

    t_ms: int
    u: float
    v: float
    meta_u: Any = None
    meta_v: Any = None


class HalfPairer:
    """Pairs the u and v halves of readings as they come (rule 1 of the module docstring).

    :meth:`add` a half: when a waiting half of the other component lies within ``tolerance_ms``
    (the nearest; the first come on a tie) the two make a :class:`Reading`; otherwise the half waits.
    Feed the halves of one boot in the order they were sent or logged (:meth:`clear` at a reboot).
    Halves that never find their partner are dropped by :meth:`expire`, or by :meth:`add` once they
    are ``keep_ms`` older than the newest half; :attr:`expired` counts them.

    Args:
        tolerance_ms: largest time between the halves of one reading (ms, >= 0).
        keep_ms: a half this much older than the newest one added is dropped (ms, vehicle time).
    """

    def __init__(self, tolerance_ms: int = RULES.pair_tolerance_ms, *, keep_ms: int = 10_000):
        if int(tolerance_ms) < 0:
            raise ValueError(f"tolerance_ms must be >= 0, got {tolerance_ms!r}")
        self.tolerance_ms = int(tolerance_ms)
        self.keep_ms = int(keep_ms)
        self.expired = 0
        self._waiting: dict[str, list[tuple[int, float, Any]]] = {"u": [], "v": []}  # (t_ms, value, meta)

    def add(self, which: str, t_ms: int, value: float, meta: Any = None) -> Reading | None:
        """Add the ``which`` ("u" or "v") half stamped ``t_ms`` (ms); the reading it completes, or None."""
        if which not in ("u", "v"):
            raise ValueError(f"which must be 'u' or 'v', got {which!r}")
        t = int(t_ms)
        self.expire(t - self.keep_ms)
        other = self._waiting["v" if which == "u" else "u"]
        best, bd = None, None
        for j, (t2, _, _) in enumerate(other):
            d = abs(t2 - t)
            if d <= self.tolerance_ms and (bd is None or d < bd):
                best, bd = j, d
        if best is None:
            self._waiting[which].append((t, float(value), meta))
            return None
        t2, value2, meta2 = other.pop(best)
        if which == "u":
            return Reading(t, float(value), value2, meta, meta2)
        return Reading(t2, value2, float(value), meta2, meta)

    def expire(self, before_ms: int) -> int:
        """Drop the waiting halves stamped before ``before_ms`` (ms); returns how many."""
        n = 0
        for k, halves in self._waiting.items():
            keep = [h for h in halves if h[0] >= before_ms]
            n += len(halves) - len(keep)
            self._waiting[k] = keep
        self.expired += n
        return n

    def clear(self) -> None:
        """Forget every waiting half (a reboot: the new boot reuses the old times); not counted as expired."""
        self._waiting = {"u": [], "v": []}

    def __contains__(self, t_ms: int) -> bool:
        """Whether a half stamped ``t_ms`` waits for its partner."""
        return any(h[0] == int(t_ms) for halves in self._waiting.values() for h in halves)

    def __len__(self) -> int:
        """Halves waiting for their partner."""
        return sum(len(h) for h in self._waiting.values())


# -- 3. boots ---------------------------------------------------------------------------------------
class BootCounter:
    """Numbers the autopilot's boots from its clock (rule 3 of the module docstring).

    :meth:`see` every ``time_boot_ms`` of the vehicle in the order it came; ``boot`` is the
    current boot (0 = the first seen), ``newest`` the newest time of it (ms, None before any).

    Args:
        back_ms: the clock going back by more than this is a reboot (ms).
    """

    def __init__(self, back_ms: int = RULES.reboot_back_ms):
        self.back_ms = int(back_ms)
        self.boot = 0
        self.newest: int | None = None

    def see(self, t_ms: int) -> int | None:
        """Take one time stamp (ms); when it starts a new boot, the previous boot's newest time, else None."""
        t = int(t_ms)
        if self.newest is not None and self.newest - t > self.back_ms:
            last, self.newest = self.newest, t
            self.boot += 1
            return last
        self.newest = t if self.newest is None else max(self.newest, t)
        return None


# -- 4. truth, 5. error -----------------------------------------------------------------------------
def truth_at(field, t: float):
    """The truth ``(2, rows, cols)`` float64 at field time ``t`` (the field's time units), or None outside it.

    A time within 1e-9 (relative, at least 1e-9 absolute) of a snapshot's is that snapshot, exactly;
    between snapshots, linear in time. ``field``: anything with ``times`` (increasing), ``data``
    ``(time, 2, rows, cols)`` and ``n_times`` (a :class:`~passt_mav.fields.FlowField`).
    """
    import numpy as np

    times = np.asarray(field.times, np.float64)
    t = float(t)
    tol = 1e-9 * max(1.0, abs(t))
    if not times[0] - tol <= t <= times[-1] + tol:
        return None
    k = np.flatnonzero(np.abs(times - t) <= tol)
    if k.size:
        return np.array(field.data[int(k[0])], np.float64)
    j = int(np.clip(np.searchsorted(times, t) - 1, 0, field.n_times - 2))
    w = (t - times[j]) / (times[j + 1] - times[j])
    return (1 - w) * np.asarray(field.data[j], np.float64) + w * np.asarray(field.data[j + 1], np.float64)


def rmse(estimate, truth) -> float | None:
    """Root mean square error over u and v pooled, of the cells known in both (field units, e.g. m/s).

    ``estimate``, ``truth``: arrays ``(..., 2, rows, cols)`` (channel axis -3). The one NaN rule: a
    cell where any component is missing (NaN) in either array is left out, not counted as zero error,
    and a cell is scored whole or not at all. None when no cell is left (or ``truth`` is None).

    Raises:
        UserError: the shapes differ, or the arrays have no ``(2, rows, cols)`` tail.
    """
    import numpy as np

    if estimate is None or truth is None:
        return None
    e, t = np.asarray(estimate, np.float64), np.asarray(truth, np.float64)
    if e.shape != t.shape:
        raise UserError(f"estimate shape {e.shape} does not match truth shape {t.shape}")
    if e.ndim < 3 or e.shape[-3] != 2:
        raise UserError(f"expected arrays (..., 2, rows, cols), got {e.shape}")
    ok = np.isfinite(e).all(axis=-3) & np.isfinite(t).all(axis=-3)  # (..., rows, cols)
    if not ok.any():
        return None
    # all u, then all v, summed as one run: the loop's recorded RMSEs replay bit for bit
    sq = np.moveaxis((e - t) ** 2, -3, 0)[:, ok].ravel()
    return float(np.sqrt(sq.mean()))


# -- 6. columns -------------------------------------------------------------------------------------
def sample_columns(recs) -> dict:
    """Sample records (:class:`~passt_mav.runs.store.Sample` rows, or dicts as the collector writes them)
    as arrays, one entry per record.

    Keys: ``time_boot_ms`` (float64 ms; exact below 2**53, and :func:`passt_mav.loop.legstep.in_field_time`
    records carry field time there), ``utc`` (epoch s), ``lat``/``lon`` (deg), ``u``/``v`` (m/s
    east/north), all float64 with NaN where a record has none; ``leg`` (int64, -1 where none) and
    ``boot`` (int64, 0 where none).
    """
    import numpy as np

    recs = list(recs)

    def get(r, k):
        return r.get(k) if isinstance(r, dict) else getattr(r, k, None)

    out = {
        k: np.array([get(r, k) for r in recs], np.float64).reshape(-1)
        for k in ("time_boot_ms", "utc", "lat", "lon", "u", "v")
    }
    for k, none in (("leg", -1), ("boot", 0)):
        out[k] = np.array([none if get(r, k) is None else int(get(r, k)) for r in recs], np.int64)
    return out


#: what a person reads for a reading taken outside any leg (on the way to the first leg's start, holding
#: between legs, after the last): the run's records store leg index -1 there
OUTSIDE_LEG = "outside"


def leg_number(index) -> str:
    """A leg as a person reads it: numbered from 1 (the console's "leg 1/5"), from the run's 0-based leg
    ``index`` (``leg.json`` ``index``, the sample store's ``leg``, the ``legs/NNN`` folders); a negative
    index (a reading outside any leg) is :data:`OUTSIDE_LEG`; "?" where the index is not an integer."""
    import numbers

    if isinstance(index, bool) or not isinstance(index, numbers.Integral):
        return "?"
    return OUTSIDE_LEG if index < 0 else str(int(index) + 1)
