"""Legs rebuilt from a mission's logs: what the vehicle was told and what it measured, leg by leg.

Storage layer (below the controller): reads logs, imports neither the controller nor
the analysis on top. :func:`rebuild_from_tlog` reads a MAVLink telemetry log
(``.tlog``); a leg is the stretch between the GCS's switch to AUTO (after a mission
upload) and the controller's mark of its end (:func:`leg_statustext`), else its next
mode command that is not AUTO and not inside the operator's pause (the marks of a
Pause and its Resume). :class:`LoggedLeg` is what
:func:`passt_mav.analysis.replay.replay` feeds through the between-leg step
(:class:`passt_mav.loop.legstep.LegStep`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from passt_mav.runs.tlog import LogReadError

__all__ = [
    "LoggedLeg",
    "LogRebuild",
    "rebuild_from_tlog",
    "clock_statustext",
    "parse_clock_statustext",
    "LEG_MARKS",
    "leg_statustext",
    "parse_leg_statustext",
]

_AUTO, _DO_SET_MODE, _MISSION_START = 10, 176, 300
_NAV_WAYPOINT = 16
_CLOCK_TEXT = "PASST leg {i} tb {tb} b {boot} k {k}"
_MARK_TEXT = "PASST leg {i} {mark}"

#: what the controller marks in the log while a leg flies (:func:`leg_statustext`): ``end`` (the controller's
#: collector stopped giving readings to the leg), ``pause`` (the operator's Pause: the boat waits, the leg goes
#: on), ``resume`` (the operator's Resume: AUTO again, confirmed)
LEG_MARKS = ("end", "pause", "resume")


def clock_statustext(i: int, tb_ms: int, boot: int, k: int) -> str:
    """The STATUSTEXT the controller sends (GCS -> vehicle) right before it plans leg ``i``.

    ``tb_ms``: the vehicle's ``time_boot_ms`` it read as "now"; ``boot``: which boot of the
    vehicle that time belongs to (0 = the first of the run); ``k``: snapshots forecast
    before planning. It lands in the telemetry log (and ArduPilot writes a GCS's
    STATUSTEXT into its DataFlash log as a MSG), so a replay of a bare log reads the
    clock reading instead of searching for it. At most 50 characters (STATUSTEXT.text).
    """
    s = _CLOCK_TEXT.format(i=int(i), tb=int(tb_ms), boot=int(boot), k=int(k))
    assert len(s) <= 50, s
    return s


def parse_clock_statustext(text: str) -> tuple[int, int, int, int] | None:
    """``(leg, time_boot_ms, boot, k)`` from :func:`clock_statustext`'s text (any prefix, e.g.
    DataFlash's ``SRC=255/190:``), None for any other text."""
    import re

    m = re.search(r"PASST leg (\d+) tb (\d+) b (\d+) k (\d+)", text or "")
    return None if m is None else tuple(int(x) for x in m.groups())  # type: ignore[return-value]


def leg_statustext(i: int, mark: str) -> str:
    """The STATUSTEXT the controller sends (GCS -> vehicle) when leg ``i`` ends, pauses or resumes (``mark``, one of
    :data:`LEG_MARKS`), so that the log tells a pause's wait from a leg's end.

    ``end`` is sent at the moment the controller's collector stops giving readings to the leg, before the mode
    command that makes the boat wait (both under the link's dispatch lock: no reading is logged between them);
    ``pause`` before the Pause's mode command (the readings of the wait belong to the leg); ``resume`` once the
    Resume's AUTO is confirmed. Logs of older controllers lack them: a leg then ends at the GCS's first mode
    command other than AUTO. At most 50 characters (STATUSTEXT.text).
    """
    if mark not in LEG_MARKS:
        raise ValueError(f"unknown leg mark {mark!r}; one of {', '.join(LEG_MARKS)}")
    return _MARK_TEXT.format(i=int(i), mark=mark)


def parse_leg_statustext(text: str) -> tuple[int, str] | None:
    """``(leg, mark)`` from :func:`leg_statustext`'s text (any prefix, e.g. DataFlash's ``SRC=255/190:``), None
    for any other text (the clock reading's included)."""
    import re

    m = re.search(r"PASST leg (\d+) (" + "|".join(LEG_MARKS) + r")\s*$", (text or "").rstrip("\x00"))
    return None if m is None else (int(m.group(1)), m.group(2))


@dataclass
class LoggedLeg:
    """One leg as the log shows it.

    ``start_latlon``: the newest position before the leg's first upload (what the controller
    planned from); ``t_now_ms``: the newest vehicle ``time_boot_ms`` then. The controller
    read its clock somewhere between ``t_lo_ms`` (the newest ``time_boot_ms`` when the
    previous leg ended, or the first of the log) and ``t_now_ms``: the log does not say
    where (it reads it after the GP update, before planning, and sends nothing then);
    ``waypoints``: (lat, lon) deg of the NAV_WAYPOINTs of the last upload before AUTO;
    ``samples``: collector records (``time_boot_ms``, ``lat``, ``lon``, ``u``, ``v`` m/s east/north,
    ``gap_ms``: the interpolation gap of the position, :class:`geo.track.Track`);
    ``n_readings``: the u/v readings of the leg, ``len(samples)`` of which the track placed;
    ``clock``: ``(time_boot_ms, boot, k)`` the controller planned from, read from its
    :func:`clock_statustext` (None in logs of controllers that did not send it: then only the
    bracket ``t_lo_ms``..``t_now_ms`` is known);
    ``marks``: the controller's :func:`leg_statustext` marks while the leg flew, in order, as ``(mark, time_boot_ms)``
    (the vehicle's newest ``time_boot_ms`` then, ms; None before any): a ``pause`` ... ``resume`` is a wait inside
    the leg, the ``end`` its end (empty in logs of controllers that did not send them).
    """

    index: int
    start_latlon: tuple[float, float] | None = None
    t_now_ms: int | None = None
    t_lo_ms: int | None = None
    waypoints: list[tuple[float, float]] = field(default_factory=list)
    samples: list[dict] = field(default_factory=list)
    closed: bool = False
    clock: tuple[int, int, int] | None = None
    planned_index: int | None = None  # the controller's leg number (a fleet numbers legs across boats)
    n_readings: int | None = None  # u/v readings in the leg, placed or not (len(samples) were placed); None: unknown
    marks: list[tuple[str, int | None]] = field(default_factory=list)


@dataclass
class LogRebuild:
    """Legs plus what the reader had to skip (``bad_frames`` stretches, ``skipped_bytes``)."""

    path: Path
    legs: list[LoggedLeg]
    n_messages: int = 0
    bad_frames: int = 0
    skipped_bytes: int = 0
    n_bytes: int = 0
    n_samples_outside_legs: int = 0


def rebuild_from_tlog(path: str | Path, *, u_name: str = "CUR_U", v_name: str = "CUR_V") -> LogRebuild:
    """Legs, positions, clock and samples from a ``.tlog`` (ours, MAVProxy's, pymavlink's).

    Damaged logs are read as far as they are readable (the scanner of
    :mod:`passt_mav.runs.tlog`: CRC-checked records, resynchronisation after junk).
    """
    from passt_mav.runs.tlog import TlogScanner, read_log_file, read_tlog

    path = Path(path)
    data = read_log_file(path, "telemetry log")
    veh = read_tlog(path, u_name=u_name, v_name=v_name).vehicle_sysid  # the vehicle's system id
    if veh is None:
        raise LogReadError(f"{path}: no vehicle messages (HEARTBEAT or GLOBAL_POSITION_INT) in the log")
    legs = _TlogLegs(veh, u_name, v_name)
    scan = TlogScanner(data)
    n = 0
    for ts, m in scan:
        n += 1
        legs.handle(ts, m)
    return LogRebuild(path, legs.finish(), n, scan.bad, scan.skipped, len(data), legs.outside)


class _TlogLegs:
    """Legs from a tlog's messages in order: the vehicle's (``veh``) feed the sample collector and the clock
    and position the controller had; the GCS's (clock STATUSTEXT, uploads, mode commands) open and close legs."""

    def __init__(self, veh: int, u_name: str, v_name: str):
        from passt_mav.mavlink.samples import SampleCollector

        self.veh = veh
        self.legs: list[LoggedLeg] = []
        self.cur: LoggedLeg | None = None  # the leg flying (between AUTO and the next mode command)
        self.pending: LoggedLeg | None = None  # the leg being uploaded
        self.upload: dict[str, Any] | None = None  # the upload being sent: {"count": n, "items": {seq: ..}}
        self.pos: tuple[float, float] | None = None  # newest vehicle position (deg)
        self.tb: int | None = None  # newest vehicle time_boot_ms
        self.tb_lo: int | None = None  # time_boot_ms when the previous leg ended (the log's first)
        self.clock: tuple[int, int, int] | None = None  # the clock STATUSTEXT not yet given to a leg
        self.clock_leg: int | None = None  # the controller's leg number in it
        self.readings_seen: set[tuple[int, int, int, int]] = set()  # clock STATUSTEXTs read so far
        self.paused = False  # the flying leg is paused by the operator (its "pause" mark, no "resume" yet)
        self.outside = 0  # samples outside any leg
        self.collector = SampleCollector(self._on_sample, u_name=u_name, v_name=v_name)

    def _on_sample(self, rec: dict) -> None:
        """The leg open when the reading arrived (a reading waits for the fix after it: the leg may have ended)."""
        if rec.get("leg") is None:
            self.outside += 1
        else:
            self.legs[rec["leg"]].samples.append(rec)

    def handle(self, ts: int, m) -> None:
        """One message (``ts``: the tlog's reception time, µs UTC)."""
        typ = m.get_type()
        if m.get_srcSystem() == self.veh:
            self._vehicle(ts, m, typ)
        elif typ == "STATUSTEXT":
            self._statustext(m)
        elif typ == "MISSION_COUNT" and getattr(m, "mission_type", 0) == 0 and m.target_system in (0, self.veh):
            self._mission_count(m)
        elif (
            typ in ("MISSION_ITEM_INT", "MISSION_ITEM")
            and self.upload is not None
            and getattr(m, "mission_type", 0) == 0
            and 0 <= m.seq < self.upload["count"]
        ):
            scale = 1e-7 if typ == "MISSION_ITEM_INT" else 1.0
            self.upload["items"][int(m.seq)] = (int(m.command), m.x * scale, m.y * scale)
        else:
            mode = self._commanded_mode(m, typ)
            if mode is not None:
                self._mode(mode)

    def _vehicle(self, ts: int, m, typ: str) -> None:
        """A vehicle message: readings to the collector, the vehicle clock and position the controller read."""
        if typ in self.collector.TYPES:
            m._timestamp = ts * 1e-6  # reception time, as pymavlink stamps a live message
            self.collector.handle(m)
        if typ in ("SYSTEM_TIME", "GLOBAL_POSITION_INT", "ATTITUDE", "NAMED_VALUE_FLOAT"):
            self.tb = max(self.tb or 0, int(m.time_boot_ms))  # Link.vehicle_uptime_s
            if self.tb_lo is None:
                self.tb_lo = self.tb
        if typ == "GLOBAL_POSITION_INT" and not (m.lat == 0 and m.lon == 0):
            self.pos = (m.lat * 1e-7, m.lon * 1e-7)

    def _statustext(self, m) -> None:
        """The controller's clock reading (:func:`clock_statustext`), sent before it plans a leg, or its mark of
        the flying leg's end, pause or resume (:func:`leg_statustext`)."""
        text = m.text if isinstance(m.text, str) else m.text.decode(errors="replace")
        mark = parse_leg_statustext(text)
        if mark is not None:
            self._mark(mark[1])
            return
        parsed = parse_clock_statustext(text)
        if parsed is not None and parsed not in self.readings_seen:  # (sent again at arming: the same one)
            self.readings_seen.add(parsed)
            # the boot as the controller numbered it when it read its clock, just now: a resumed controller
            # numbers its first boot after the stored ones (RunClock.resume_boots), where this reader counts
            # only the vehicle's reboots; the samples from here on carry the controller's number, so the run's
            # clock maps them to their boot
            self.collector.boot_base = int(parsed[2]) - self.collector.boot
            if self.cur is not None:
                # a new clock reading while a leg flies: the controller that flew it died without a mode
                # command (kill -9, a power cut) and a resumed one plans now; its leg ends here
                self._end_leg()
        if parsed is not None and self.cur is None:
            self.clock, self.clock_leg = parsed[1:], parsed[0]
            if self.pending is not None:
                self.pending.clock, self.pending.planned_index = parsed[1:], parsed[0]

    def _mark(self, mark: str) -> None:
        """The controller's mark of the flying leg: ``end`` ends it here (where the controller's collector stopped
        giving it readings); ``pause`` makes the mode commands that follow no end of it, until ``resume``."""
        if self.cur is None:
            return  # (a leg the log did not open, or one already ended)
        self.cur.marks.append((mark, self.tb))
        if mark == "end":
            self._end_leg()
        else:
            self.paused = mark == "pause"

    def _mission_count(self, m) -> None:
        """An upload begins; the first of a new leg opens it with the position and time it was planned from."""
        if self.pending is None and self.cur is None:  # first upload of a new leg: planned just before
            self.pending = LoggedLeg(
                len(self.legs), self.pos, self.tb, self.tb_lo, clock=self.clock, planned_index=self.clock_leg
            )
            self.clock = self.clock_leg = None
        self.upload = {"count": int(m.count), "items": {}}

    def _commanded_mode(self, m, typ: str) -> int | None:
        """The mode a GCS command to the vehicle sets (MISSION_START: AUTO), None for any other message."""
        if typ == "COMMAND_LONG" and m.target_system in (0, self.veh):
            if m.command == _DO_SET_MODE:
                return int(m.param2)
            if m.command == _MISSION_START:
                return _AUTO
        elif typ == "SET_MODE" and m.target_system in (0, self.veh):
            return int(m.custom_mode)
        return None

    def _mode(self, mode: int) -> None:
        """AUTO after an upload starts the pending leg (its waypoints: the last upload's); another mode ends it."""
        if mode == _AUTO and self.cur is None and self.pending is not None:
            leg = self.pending
            up = self.upload or {"items": {}}
            leg.waypoints = [
                (la, lo) for s, (cmd, la, lo) in sorted(up["items"].items()) if s >= 1 and cmd == _NAV_WAYPOINT
            ]
            self.legs.append(leg)
            self.cur, self.pending = leg, None
            self.collector.leg = leg.index
        elif mode != _AUTO and self.cur is not None and not self.paused:
            self._end_leg()

    def _end_leg(self) -> None:
        """The flying leg ends (a mode command other than AUTO, or the next controller's clock reading)."""
        assert self.cur is not None  # (called only while a leg flies)
        self.cur.closed = True
        self.cur, self.paused = None, False
        self.tb_lo = self.tb
        self.collector.leg = None

    def finish(self) -> list[LoggedLeg]:
        """The legs, once the log ends (readings still waiting for a fix after them: the log has none)."""
        self.collector.flush()
        for leg in self.legs:
            leg.n_readings = self.collector.leg_counts(leg.index)["readings"]
        return self.legs
