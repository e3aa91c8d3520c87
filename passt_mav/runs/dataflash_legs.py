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
the GCS's next mode command and a pilot's RC takeover does not end it. Samples
(:func:`~passt_mav.runs.tlog.read_dataflash`: an NVF CUR_U paired with the CUR_V and
placed on the track by interpolating between the positions around it, at most
``max_gap_ms`` apart: :mod:`passt_mav.measurement`, the live collector's rules) belong to the leg
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
from typing import Any

from passt_mav.measurement import RULES
from passt_mav.runs.legs import LoggedLeg, LogRebuild, parse_clock_statustext
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
    track = [(p.time_boot_ms, p.lat, p.lon) for p in tl.track]
    track_t = [t for t, _, _ in track]

    def pos_at(t_ms: int) -> tuple[float, float] | None:
        """The newest position at or before ``t_ms`` (what the controller had then), else the first after."""
        i = bisect.bisect_right(track_t, t_ms)
        if i:
            return track[i - 1][1], track[i - 1][2]
        return (track[0][1], track[0][2]) if track else None

    legs: list[DataflashLeg] = []
    cur: DataflashLeg | None = None
    pending: DataflashLeg | None = None
    upload: dict[str, Any] | None = None  # the mission block being read: {"total": CTot, "items": {CNum: ..}}
    last_upload: dict[int, tuple[int, float, float]] | None = None
    clock: tuple[tuple[int, int, int], str] | None = None
    mode: int | None = None
    t_lo = track_t[0] if track_t else 0
    boots: list[int] = []
    fresh = False  # a mission block since the last leg opened
    text = ""
    for tus, typ, m in events:
        t_ms = tus // 1000
        if typ == "MSG":
            prev_text, text = text, str(getattr(m, "Message", "") or "")
            parsed = parse_clock_statustext(text)
            if parsed is not None:
                boots.append(parsed[2])
                if cur is None:
                    clock = (parsed[1:], text)
                    if pending is not None:
                        pending.clock, pending.clock_text = clock
                continue
            if text == "New mission":
                upload = {"total": None, "items": {}}
                # an upload ("Flight plan received" just before) anchors the leg: planned just before its
                # first upload; the block a log opens with (the stored mission) anchors nothing
                if prev_text == "Flight plan received" and cur is None and pending is None:
                    pending = DataflashLeg(len(legs), pos_at(t_ms), t_ms, t_lo)
                    if clock is not None:
                        pending.clock, pending.clock_text = clock
                        clock = None
            elif cur is not None and text.startswith("Reached waypoint #"):
                try:
                    cur.reached.append((t_ms, int(text.rsplit("#", 1)[1])))
                except ValueError:
                    pass
            elif cur is not None and text == "Mission Complete" and cur.complete_ms is None:
                cur.complete_ms = t_ms
        elif typ == "CMD":
            if upload is None:
                continue  # an item logged outside a mission block
            try:
                n, total = int(m.CNum), int(m.CTot)
                item = (int(m.CId), float(m.Lat), float(m.Lng))
            except (AttributeError, TypeError, ValueError):
                continue
            if n in upload["items"] or not 0 <= n < total:
                continue
            upload["total"] = total
            upload["items"][n] = item
            last_upload, fresh = upload["items"], True
            if len(upload["items"]) == total:
                upload = None  # complete: later CMDs are no part of it
        elif typ == "MODE":
            try:
                new, rsn = int(m.ModeNum), int(getattr(m, "Rsn", -1))
            except (AttributeError, TypeError, ValueError):
                continue
            changed, mode = new != mode, new
            if not changed:
                continue  # the current mode written again (after a mission block, at log start)
            if new == _AUTO and cur is None and pending is None and fresh:
                # the log began after the upload (LOG_DISARMED 0: logging starts at arming): its opening
                # block is the mission flown, and the leg is anchored at AUTO
                pending = DataflashLeg(len(legs), pos_at(t_ms), t_ms, t_lo)
                if clock is not None:
                    pending.clock, pending.clock_text = clock
                    clock = None
            if new == _AUTO and cur is None and pending is not None:
                cur, pending, fresh = pending, None, False
                cur.t_auto_ms = t_ms
                if cur.start_latlon is None:
                    cur.start_latlon = pos_at(t_ms)
                cur.waypoints = [
                    (la, lo)
                    for s, (cmd, la, lo) in sorted((last_upload or {}).items())
                    if s >= 1 and cmd == _NAV_WAYPOINT
                ]
                legs.append(cur)
            elif new != _AUTO and cur is not None and rsn == _GCS_COMMAND:
                cur.closed, cur.t_end_ms = True, t_ms
                cur = None
                t_lo = t_ms
    boot = boots[0] if boots else 0
    starts = [lg.t_auto_ms for lg in legs]

    def leg_at(tb: int) -> DataflashLeg | None:
        i = bisect.bisect_right(starts, tb) - 1
        lg = legs[i] if i >= 0 else None
        return None if lg is None or (lg.t_end_ms is not None and tb >= lg.t_end_ms) else lg

    for lg in legs:
        lg.n_readings = 0
    for tb in tl.reading_times:
        if (lg := leg_at(tb)) is not None:
            lg.n_readings += 1
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
    return LogRebuild(path, list(legs), tl.n_messages, tl.bad_frames, tl.skipped_bytes, tl.n_bytes, outside)
