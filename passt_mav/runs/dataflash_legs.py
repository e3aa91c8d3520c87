"""Legs rebuilt from the autopilot's own log: an ArduPilot DataFlash ``.bin``.

Storage layer (below the controller), the DataFlash twin of
:func:`passt_mav.runs.legs.rebuild_from_tlog`: the same :class:`~passt_mav.runs.legs.LoggedLeg`
structure, so :func:`passt_mav.analysis.replay.replay` can feed it through the
between-leg step. On a real boat the onboard log is the complete record: the tlog
has the radio's gaps, the ``.bin`` does not.

What ArduRover 4.7 (SITL, upstream 56005f8c) writes and this reader relies on; every
record's ``TimeUS`` is the autopilot's µs since boot, the clock of MAVLink's
``time_boot_ms`` (``time_boot_ms`` = ``TimeUS // 1000``, within 0-3 ms of the
MAVLink stamp of the same event):

* a mission upload: ``MSG "Flight plan received"``, ``MSG "New mission"``, then one
  ``CMD`` per stored item (``CTot`` items, ``CNum`` 0 = home, ``CId`` 16 =
  NAV_WAYPOINT, ``Lat``/``Lng`` degrees, the int32 the GCS sent). A log started after
  the upload (``LOG_DISARMED 0``: logging starts at arming) opens with the same
  block for the stored mission. Needs ``LOG_BITMASK`` bit 8 (CMD).
* mode changes: ``MODE`` (``ModeNum``: 10 = AUTO, 4 = HOLD, 0 = MANUAL; ``Rsn``:
  ``ModeReason``, 2 = GCS_COMMAND, 26 = initialised). The current mode is written
  again without a change (e.g. right after a mission block): only a change counts.
* the controller's clock reading, a STATUSTEXT the vehicle received:
  ``MSG "SRC=245/195:PASST leg 0 tb 43411 b 0 k 0"`` (``SRC=sysid/compid:`` + the text;
  ``GCS:`` + the text when the sender's system id is the vehicle's MAV_GCS_SYSID, 255 by
  default, which the controller's own ids 245/195 are not), parsed by
  :func:`~passt_mav.runs.legs.parse_clock_statustext`. Sent before leg 0's upload, it
  is in the log only when logging ran before arming (``LOG_DISARMED 1``).
* ``MSG "Reached waypoint #N"`` (N = mission seq) and ``MSG "Mission Complete"``;
  Rover stays in AUTO after the mission's end until the GCS sends HOLD.
* the Lua sensor's ``gcs:send_named_float``: ``NVF`` records (``Name`` CUR_U /
  CUR_V, ``Value`` m/s east / north), logged whatever ``LOG_BITMASK`` says;
* positions: ``POS`` (the AHRS position, as GLOBAL_POSITION_INT; ``LOG_BITMASK``
  bit 1, ATTITUDE_MED, 10 Hz) or, without POS, ``GPS`` (bit 2, 5 Hz). Both are
  thinned by ``LOG_FILE_RATEMAX``, as is NVF (more than ~4 Hz keeps every reading).

A leg opens at a change to AUTO that follows a mission upload (anchored at its ``New
mission``; in a log begun after the upload, at AUTO) and closes at the next
GCS-commanded change away from AUTO (``Rsn`` 2): as in the tlog, where a leg ends at
the GCS's next mode command and a pilot's RC takeover does not end it. The operator's
Pause is no end: between the controller's marks ``PASST leg I pause`` and ``PASST leg I
resume`` (MSG, :func:`~passt_mav.runs.legs.leg_statustext`) the GCS's mode changes do not
close the leg; a pause that ends the leg closes it at the mark ``PASST leg I end``. Samples
(:func:`~passt_mav.runs.tlog.read_dataflash`: an NVF CUR_U paired with the CUR_V and
placed on the track by interpolating between the positions around it, at most
``max_gap_ms`` apart: :mod:`passt_mav.loop.measurement`, the live collector's rules) belong to the leg
whose [AUTO, close) span holds their time.

Differences from the tlog rebuild (measured on SITL, see tests/test_dataflash_legs.py):

* samples: the log holds every reading (4 Hz) and positions at 10 Hz, so the
  interpolation gap is ~100 ms; the tlog interpolates between 1 Hz GLOBAL_POSITION_INT
  (gap ~1000 ms). Both place nearly every reading; where both have a sample of the same
  reading (same time within 3 ms) u and v are equal and the positions agree to a few
  metres; the tlog's leg also keeps the few readings between the GCS's AUTO command and
  the vehicle's MODE record;
* ``t_now_ms`` / ``start_latlon``: taken at the ``New mission`` record, which is
  written when the upload is complete (the tlog takes them at the upload's
  MISSION_COUNT: a few hundred ms of vehicle time earlier); ``t_lo_ms`` of leg 0 is
  the log's first position (the tlog's is its first message), of later legs the
  GCS's mode change that closed the previous one;
* the sample records carry ``utc`` NaN (DataFlash has no reception time) and
  ``boot`` from the log's clock STATUSTEXT (0 without one): one ``.bin`` is one boot.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from passt_mav.loop.measurement import RULES
from passt_mav.runs.legs import LoggedLeg, LogRebuild, parse_clock_statustext, parse_leg_statustext
from passt_mav.runs.tlog import LogReadError, read_dataflash

__all__ = ["DataflashLeg", "rebuild_from_dataflash"]

_AUTO = 10
_NAV_WAYPOINT = 16
_GCS_COMMAND = 2  # ModeReason::GCS_COMMAND
_EVENT_TYPES = ["MSG", "MODE", "CMD"]


@dataclass
class DataflashLeg(LoggedLeg):
    """A :class:`LoggedLeg` with what only the onboard log has (times in ms since boot).

    ``t_auto_ms``: the change to AUTO; ``t_end_ms``: the GCS's change away from AUTO
    (None while the log ends in the leg); ``reached``: ``(time_ms, seq)`` of each
    "Reached waypoint #seq"; ``complete_ms``: "Mission Complete" (None if not reached);
    ``clock_text``: the MSG the clock reading came from (e.g. ``GCS:PASST leg 0 tb ...``).
    """

    t_auto_ms: int | None = None
    t_end_ms: int | None = None
    reached: list[tuple[int, int]] = field(default_factory=list)
    complete_ms: int | None = None
    clock_text: str | None = None


def _events(path: Path) -> list[tuple[int, str, Any]]:
    """``(TimeUS, type, record)`` of MSG, MODE and CMD in file order (pymavlink DFReader)."""
    import contextlib
    import io

    from pymavlink import DFReader

    class _Reader(DFReader.DFReader_binary):
        def init_arrays_fast(self, progress_callback=None):
            # the compiled indexer prints every bad byte of a damaged file straight to the terminal
            # (read_dataflash counts them already); the Python one writes to sys.stderr, caught below
            self.init_arrays(progress_callback)

    out: list[tuple[int, str, Any]] = []
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            r = _Reader(str(path), zero_time_base=True)
        except Exception as exc:  # noqa: BLE001 - pymavlink raises assorted errors on a file that is no log
            raise LogReadError(f"{path}: not a readable DataFlash log ({exc})") from None
        while True:
            try:
                m = r.recv_match(type=_EVENT_TYPES)
            except Exception:  # noqa: BLE001 - a record cut by the end of the file
                break
            if m is None:
                break
            try:
                out.append((int(m.TimeUS), m.get_type(), m))
            except (AttributeError, TypeError, ValueError):
                continue
    return out


def rebuild_from_dataflash(
    path: str | Path,
    *,
    u_name: str = "CUR_U",
    v_name: str = "CUR_V",
    pair_tolerance_ms: int = RULES.pair_tolerance_ms,
    max_gap_ms: int = RULES.max_gap_ms,
) -> LogRebuild:
    """Legs, positions, clock readings and samples from an ArduPilot DataFlash ``.bin`` (module docstring).

    ``u_name`` / ``v_name``: the NVF names of the east / north current (m/s);
    ``pair_tolerance_ms``: largest time difference between a reading's halves (ms);
    ``max_gap_ms``: largest time between the two positions a reading is interpolated
    between (ms, :class:`geo.track.Track`). Legs are :class:`DataflashLeg`;
    samples are dicts ``time_boot_ms``, ``utc`` (NaN), ``lat``, ``lon`` (deg), ``u``,
    ``v`` (m/s east/north), ``gap_ms``, ``source`` ("dataflash"), ``boot``, ``leg``;
    a leg's ``n_readings`` counts its readings, placed or not.

    Raises:
        LogReadError: the file is missing or no DataFlash log.
    """
    path = Path(path)
    tl = read_dataflash(
        path, u_name=u_name, v_name=v_name, pair_tolerance_ms=int(pair_tolerance_ms), max_gap_ms=int(max_gap_ms)
    )
    events = _events(path)
    if tl.n_messages == 0 and not events:
        raise LogReadError(f"{path}: no DataFlash records in the file")
    legs = _DataflashLegs([(p.time_boot_ms, p.lat, p.lon) for p in tl.track])
    for tus, typ, m in events:
        legs.handle(tus // 1000, typ, m)
    outside = _place_samples(legs.legs, tl, legs.boot)
    return LogRebuild(path, list(legs.legs), tl.n_messages, tl.bad_frames, tl.skipped_bytes, tl.n_bytes, outside)


class _DataflashLegs:
    """Legs from the log's MSG, CMD and MODE records in file order (module docstring); ``track``: the
    positions ``(time_boot_ms, lat, lon)`` (deg) in time order."""

    def __init__(self, track: list[tuple[int, float, float]]):
        self.track = track
        self.track_t = [t for t, _, _ in track]
        self.legs: list[DataflashLeg] = []
        self.cur: DataflashLeg | None = None  # the leg flying (AUTO until the GCS's next mode change)
        self.pending: DataflashLeg | None = None  # the leg uploaded, not yet started
        self.upload: dict[str, Any] | None = None  # the mission block being read: {"total": CTot, "items": {CNum: ..}}
        self.last_upload: dict[int, tuple[int, float, float]] | None = None
        self.clock: tuple[tuple[int, int, int], str] | None = None  # a clock reading not yet given to a leg
        self.mode: int | None = None
        self.t_lo = self.track_t[0] if self.track_t else 0
        self.boots: list[int] = []
        self.fresh = False  # a mission block since the last leg opened
        self.text = ""  # the last MSG
        self.paused = False  # the flying leg is paused by the operator (its "pause" mark, no "resume" yet)

    @property
    def boot(self) -> int:
        """The vehicle boot the log belongs to: its first clock STATUSTEXT's (0 without one)."""
        return self.boots[0] if self.boots else 0

    def pos_at(self, t_ms: int) -> tuple[float, float] | None:
        """The newest position at or before ``t_ms`` (what the controller had then), else the first after."""
        i = bisect.bisect_right(self.track_t, t_ms)
        if i:
            return self.track[i - 1][1], self.track[i - 1][2]
        return (self.track[0][1], self.track[0][2]) if self.track else None

    def handle(self, t_ms: int, typ: str, m) -> None:
        """One MSG, CMD or MODE record (``t_ms``: its ``TimeUS`` in ms)."""
        if typ == "MSG":
            self._msg(t_ms, m)
        elif typ == "CMD":
            self._cmd(m)
        elif typ == "MODE":
            self._mode(t_ms, m)

    def _open_pending(self, t_ms: int) -> None:
        """A leg planned just before ``t_ms``, holding the clock reading sent for it."""
        self.pending = DataflashLeg(len(self.legs), self.pos_at(t_ms), t_ms, self.t_lo)
        if self.clock is not None:
            self.pending.clock, self.pending.clock_text = self.clock
            self.clock = None

    def _msg(self, t_ms: int, m) -> None:
        """A text: the controller's clock reading, a mission upload, a waypoint reached, the mission's end."""
        prev_text, self.text = self.text, str(getattr(m, "Message", "") or "")
        text, cur = self.text, self.cur
        mark = parse_leg_statustext(text)
        if mark is not None:
            self._mark(t_ms, mark[1])
            return
        parsed = parse_clock_statustext(text)
        if parsed is not None:
            self.boots.append(parsed[2])
            if cur is None:
                self.clock = (parsed[1:], text)
                if self.pending is not None:
                    self.pending.clock, self.pending.clock_text = self.clock
            return
        if text == "New mission":
            self.upload = {"total": None, "items": {}}
            # an upload ("Flight plan received" just before) anchors the leg: planned just before its
            # first upload; the block a log opens with (the stored mission) anchors nothing
            if prev_text == "Flight plan received" and cur is None and self.pending is None:
                self._open_pending(t_ms)
        elif cur is not None and text.startswith("Reached waypoint #"):
            try:
                cur.reached.append((t_ms, int(text.rsplit("#", 1)[1])))
            except ValueError:
                pass
        elif cur is not None and text == "Mission Complete" and cur.complete_ms is None:
            cur.complete_ms = t_ms

    def _mark(self, t_ms: int, mark: str) -> None:
        """The controller's mark of the flying leg (:func:`~passt_mav.runs.legs.leg_statustext`): ``pause`` makes
        the GCS's mode changes that follow no end of it, until ``resume``; ``end`` inside a pause ends it here
        (outside one the GCS's mode change right after it does, as in logs without marks)."""
        cur = self.cur
        if cur is None:
            return
        cur.marks.append((mark, t_ms))
        if mark == "end" and self.paused:
            self._end(t_ms)
        elif mark != "end":
            self.paused = mark == "pause"

    def _end(self, t_ms: int) -> None:
        """The flying leg ends at ``t_ms`` (ms since boot)."""
        assert self.cur is not None  # (called only while a leg flies)
        self.cur.closed, self.cur.t_end_ms = True, t_ms
        self.cur, self.paused = None, False
        self.t_lo = t_ms

    def _cmd(self, m) -> None:
        """A mission item of the block being read (once per ``CNum``)."""
        upload = self.upload
        if upload is None:
            return  # an item logged outside a mission block
        try:
            n, total = int(m.CNum), int(m.CTot)
            item = (int(m.CId), float(m.Lat), float(m.Lng))
        except (AttributeError, TypeError, ValueError):
            return
        if n in upload["items"] or not 0 <= n < total:
            return
        upload["total"] = total
        upload["items"][n] = item
        self.last_upload, self.fresh = upload["items"], True
        if len(upload["items"]) == total:
            self.upload = None  # complete: later CMDs are no part of it

    def _mode(self, t_ms: int, m) -> None:
        """A mode change: AUTO after an upload starts a leg, the GCS's change away from AUTO ends it."""
        try:
            new, rsn = int(m.ModeNum), int(getattr(m, "Rsn", -1))
        except (AttributeError, TypeError, ValueError):
            return
        changed, self.mode = new != self.mode, new
        if not changed:
            return  # the current mode written again (after a mission block, at log start)
        if new == _AUTO and self.cur is None and self.pending is None and self.fresh:
            # the log began after the upload (LOG_DISARMED 0: logging starts at arming): its opening
            # block is the mission flown, and the leg is anchored at AUTO
            self._open_pending(t_ms)
        if new == _AUTO and self.cur is None and self.pending is not None:
            self._start(t_ms)
        elif new != _AUTO and self.cur is not None and rsn == _GCS_COMMAND and not self.paused:
            self._end(t_ms)

    def _start(self, t_ms: int) -> None:
        """The pending leg starts flying at ``t_ms``: its waypoints are the last mission block's."""
        cur, self.pending, self.fresh = self.pending, None, False
        assert cur is not None  # (called only with a leg pending)
        self.cur = cur
        cur.t_auto_ms = t_ms
        if cur.start_latlon is None:
            cur.start_latlon = self.pos_at(t_ms)
        cur.waypoints = [
            (la, lo) for s, (cmd, la, lo) in sorted((self.last_upload or {}).items()) if s >= 1 and cmd == _NAV_WAYPOINT
        ]
        self.legs.append(cur)


def _place_samples(legs: list[DataflashLeg], tl, boot: int) -> int:
    """Count each leg's readings and give it the samples in its [AUTO, end) span; the samples outside any leg."""
    starts = cast("list[int]", [lg.t_auto_ms for lg in legs])  # every leg here flew: _start set its AUTO time

    def leg_at(tb: int) -> DataflashLeg | None:
        i = bisect.bisect_right(starts, tb) - 1
        lg = legs[i] if i >= 0 else None
        return None if lg is None or (lg.t_end_ms is not None and tb >= lg.t_end_ms) else lg

    for leg in legs:
        leg.n_readings = 0
    for tb in tl.reading_times:
        if (lg := leg_at(tb)) is not None:
            lg.n_readings = (lg.n_readings or 0) + 1  # (0 from the loop above)
    outside = 0
    for s in tl.samples:
        tb = int(s.time_boot_ms)
        lg = leg_at(tb)
        if lg is None:
            outside += 1
            continue
        lg.samples.append(
            {
                "time_boot_ms": tb,
                "utc": float("nan"),
                "lat": float(s.lat),
                "lon": float(s.lon),
                "u": float(s.u),
                "v": float(s.v),
                "gap_ms": s.gap_ms,
                "source": "dataflash",
                "boot": boot,
                "leg": lg.index,
            }
        )
    return outside
