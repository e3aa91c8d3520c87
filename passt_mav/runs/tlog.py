"""Read a run back from its logs: MAVLink telemetry logs (.tlog) and ArduPilot DataFlash logs (.bin).

:func:`read_tlog` reads the ``.tlog`` format written by MAVProxy, pymavlink
(``mavfile.setup_logfile``) and the simulator: each record is an 8-byte
big-endian UTC timestamp in microseconds followed by one MAVLink 1 or 2 frame.
From it, it rebuilds

* ``track``: the vehicle's GLOBAL_POSITION_INT positions (0/0 before a GPS fix is
  ignored);
* ``samples``: current measurements, a NAMED_VALUE_FLOAT ``CUR_U`` paired with
  the ``CUR_V`` nearest in ``time_boot_ms`` within ``pair_tolerance_ms`` (names
  configurable), placed on the track at the reading's time: interpolated between the
  GLOBAL_POSITION_INT fixes around it when they are at most ``max_gap_ms`` apart
  (the gap is the sample's ``gap_ms``). ``n_readings`` counts the u/v pairs, placed or not.
  Pairing, placing and boots (``time_boot_ms`` going back: a reboot; every position and
  sample carries its ``boot``) follow :mod:`passt_mav.loop.measurement`, the live collector's rules;
* ``missions``: mission uploads from a GCS (MISSION_COUNT + MISSION_ITEM_INT or
  MISSION_ITEM, re-sent items kept once) and the vehicle's MISSION_ACK result;
* ``legs``: one per accepted upload (MISSION_ACK 0). A leg is complete at
  "Mission Complete" (STATUSTEXT) or MISSION_CURRENT ``mission_state`` 5 - the
  latter only once the leg was seen running (state 3 or an item reached), since
  right after an upload the vehicle still reports the old mission complete;
* ``events``: mode and arming changes, uploads, waypoints reached, completions,
  status texts.

Each sample and track point carries the leg open when it was received (-1 outside
any leg), so a reader sees exactly what the GCS saw.

Damaged logs: a file cut mid-record or with junk bytes in it is read as far as it
is readable. Every record is checked (MAVLink CRC with the message's CRC_EXTRA,
exact frame length); after a bad record the reader searches forward for the next
position where a plausible timestamp is followed by a valid frame, and counts
the bytes it passed over (``skipped_bytes``) and the damaged stretches
(``bad_frames``). pymavlink's ``mavlogfile`` decodes the frames but neither
resynchronises a timestamped stream nor reports what it skipped, hence this
small scanner around pymavlink's own frame decoder.

:func:`read_dataflash` reads ArduPilot DataFlash ``.bin`` logs the same way
(FMT records, then fixed-length records; decoding through ``DFReader``'s format
classes): positions from ``POS`` (or ``GPS``), samples from a ``CUR`` message
(columns ``U``, ``V``, written by an on-board Lua script) or from ``NVF`` named
values, paired by ``TimeUS`` and placed on the track by the same rules (one ``.bin`` is one boot: ArduPilot
starts a new log file when it boots). DataFlash records have no checksum, so a record is
accepted only when it is followed by another valid record header (or the end of
the file); a record with junk inside it is dropped rather than misread.
"""

from __future__ import annotations

import re
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geo.track import Track
from passt_mav.errors import UserError
from passt_mav.loop.measurement import RULES, BootCounter, HalfPairer
from passt_mav.runs.store import Sample

__all__ = [
    "LogReadError",
    "TrackPoint",
    "MissionItem",
    "MissionUpload",
    "LegRecord",
    "LogEvent",
    "TelemetryLog",
    "read_tlog",
    "read_dataflash",
]


class LogReadError(UserError):
    """A log file is missing or cannot be read at all."""


# -- records -------------------------------------------------------------------------
@dataclass(frozen=True)
class TrackPoint:
    """A vehicle position: ``time_boot_ms``, WGS84 ``lat``/``lon`` (deg), reception ``utc`` (epoch s), ``leg``,
    ``boot`` (the autopilot's boot, 0 = the first in the log: :class:`passt_mav.loop.measurement.BootCounter`)."""

    time_boot_ms: int
    lat: float
    lon: float
    utc: float
    leg: int = -1
    boot: int = 0


@dataclass(frozen=True)
class MissionItem:
    """One uploaded mission item; ``lat``/``lon`` in degrees (int32 degE7 or float32 on the wire)."""

    seq: int
    command: int
    frame: int
    lat: float
    lon: float
    alt: float
    is_int: bool


#: MAV_CMD_NAV_* commands that carry a position the vehicle drives to
_NAV_POSITION_CMDS = frozenset({16, 17, 18, 19, 21, 31, 82})


@dataclass
class MissionUpload:
    """A mission upload seen in the log (mission_type 0).

    ``result`` is the vehicle's MISSION_ACK type (None: no answer in the log);
    ``items`` hold each sequence number once (a re-sent item overwrites, as on the
    vehicle). ``waypoints`` are the positions of the navigation items after seq 0
    (seq 0 is the home placeholder).
    """

    index: int
    gcs: tuple[int, int]
    count: int
    utc_start: float
    items_by_seq: dict[int, MissionItem] = field(default_factory=dict)
    result: int | None = None
    utc_end: float | None = None

    @property
    def accepted(self) -> bool:
        return self.result == 0

    @property
    def items(self) -> list[MissionItem]:
        return [self.items_by_seq[k] for k in sorted(self.items_by_seq)]

    @property
    def complete(self) -> bool:
        """Every item 0..count-1 was sent."""
        return set(self.items_by_seq) == set(range(self.count))

    @property
    def int_items(self) -> bool:
        """All items were MISSION_ITEM_INT (exact degE7); False if any was a float MISSION_ITEM."""
        return bool(self.items_by_seq) and all(it.is_int for it in self.items_by_seq.values())

    @property
    def waypoints(self) -> list[tuple[float, float]]:
        return [(it.lat, it.lon) for it in self.items if it.seq >= 1 and it.command in _NAV_POSITION_CMDS]

    @property
    def n_waypoints(self) -> int:
        return len(self.waypoints)


@dataclass
class LegRecord:
    """One leg: from an accepted upload to its completion (or the next accepted upload / end of log).

    Times are reception UTC (epoch s); ``t_end`` is None while the leg was still open
    at the end of the log.
    """

    index: int
    mission: int
    t_start: float
    t_end: float | None = None
    complete: bool = False
    n_waypoints: int = 0
    n_samples: int = 0
    active: bool = False
    n_readings: int = 0  # u/v pairs received in the leg; n_samples of them were placed on the track


@dataclass(frozen=True)
class LogEvent:
    """Something that happened: ``kind`` in mode, armed, upload, item_reached, complete, text."""

    utc: float
    kind: str
    value: int | None = None
    detail: str = ""


@dataclass
class TelemetryLog:
    """What a log holds (see module docstring). ``utc`` values are UNIX epoch seconds."""

    path: Path
    kind: str
    samples: list[Sample] = field(default_factory=list)
    track: list[TrackPoint] = field(default_factory=list)
    missions: list[MissionUpload] = field(default_factory=list)
    legs: list[LegRecord] = field(default_factory=list)
    events: list[LogEvent] = field(default_factory=list)
    n_messages: int = 0
    bad_frames: int = 0
    skipped_bytes: int = 0
    truncated_bytes: int = 0  # an incomplete last record (a log copied while written, a power cut): not damage
    n_bytes: int = 0
    vehicle_sysid: int | None = None
    vehicle_compid: int | None = None
    message_counts: Counter = field(default_factory=Counter)
    #: vehicle frames missing by MAVLink sequence numbers (lost before logging; an
    #: over-estimate when the log interleaves several links of one vehicle)
    seq_lost: int = 0
    utc_first: float | None = None
    utc_last: float | None = None
    #: u/v reading pairs found; ``len(samples)`` of them were placed on the track (the rest: no two
    #: fixes within ``max_gap_ms`` around them)
    n_readings: int = 0
    #: ``time_boot_ms`` of every reading pair (DataFlash only: the tlog counts readings per leg)
    reading_times: list[int] = field(default_factory=list)

    def track_array(self):
        """``(n, 3)`` float64: time_boot_ms, lat, lon (deg)."""
        import numpy as np

        return np.array([(p.time_boot_ms, p.lat, p.lon) for p in self.track], dtype=np.float64).reshape(-1, 3)

    def leg_track(self, leg: int):
        """``(n, 2)`` lat/lon of the positions received during leg ``leg``."""
        import numpy as np

        return np.array([(p.lat, p.lon) for p in self.track if p.leg == leg], dtype=np.float64).reshape(-1, 2)

    @property
    def link_loss(self) -> float | None:
        """Fraction of vehicle frames lost before they reached the log (from sequence gaps), or None."""
        n = self.message_counts.get("_vehicle_frames", 0)
        return None if n == 0 else self.seq_lost / (n + self.seq_lost)


# -- tlog scanning ---------------------------------------------------------------------
_MAGIC_V1, _MAGIC_V2 = 0xFE, 0xFD
_TS_MIN, _TS_MAX = 946_684_800_000_000, 4_102_444_800_000_000  # 2000-01-01 .. 2100-01-01 in µs
_INTERESTING = frozenset(
    {
        "HEARTBEAT",
        "GLOBAL_POSITION_INT",
        "NAMED_VALUE_FLOAT",
        "MISSION_COUNT",
        "MISSION_ITEM",
        "MISSION_ITEM_INT",
        "MISSION_ACK",
        "MISSION_CURRENT",
        "MISSION_ITEM_REACHED",
        "STATUSTEXT",
    }
)


def read_log_file(path: str | Path, what: str) -> bytes:
    """The bytes of the log file ``path``; :class:`LogReadError` naming ``what`` when it is missing or unreadable."""
    p = Path(path)
    if not p.exists():
        raise LogReadError(f"{what} not found: {p}")
    if not p.is_file():
        raise LogReadError(f"{what} {p} is not a file")
    try:
        return p.read_bytes()
    except OSError as exc:
        raise LogReadError(f"cannot read {what} {p}: {exc.strerror or exc}") from None


def _frame_len(data: bytes, p: int) -> int | None:
    """Length of the MAVLink frame starting at ``p`` from its header, or None if not a frame start."""
    n = len(data)
    if p >= n:
        return None
    m = data[p]
    if m == _MAGIC_V2:
        if p + 3 > n:
            return None
        incompat = data[p + 2]
        if incompat & ~0x01:
            return None  # unknown incompatibility flags: no receiver can read it
        return 10 + data[p + 1] + 2 + (13 if incompat & 0x01 else 0)
    if m == _MAGIC_V1:
        if p + 2 > n:
            return None
        return 6 + data[p + 1] + 2
    return None


class TlogScanner:
    """Walks the records of a tlog, validating each, resynchronising after damage."""

    def __init__(self, data: bytes):
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2

        self.data = data
        self.mav = mavlink2.MAVLink(None)
        self.MAVError = mavlink2.MAVError
        self.unknown_cls = mavlink2.MAVLink_unknown
        self.skipped = 0
        self.bad = 0
        self.last_ts: int | None = None

    def _try(self, p: int, resync: bool):
        """(timestamp µs, message, end) if a valid record starts at ``p``; 'short' if cut by EOF; else None."""
        data = self.data
        n = len(data)
        if p + 8 >= n:
            return "short"
        ts = struct.unpack_from(">Q", data, p)[0]
        if resync and not (
            _TS_MIN <= ts <= _TS_MAX or (self.last_ts is not None and abs(ts - self.last_ts) < 3_600_000_000)
        ):
            return None
        flen = _frame_len(data, p + 8)
        if flen is None:
            return None
        end = p + 8 + flen
        if end > n:
            return "short"
        try:
            msg = self.mav.decode(bytearray(data[p + 8 : end]))
        except (self.MAVError, struct.error, IndexError, ValueError, TypeError, UnicodeDecodeError):
            return None
        # a message id this dialect lacks has no checkable CRC: accept it only in step with the
        # stream and when the next record starts where it should (or the file ends)
        if isinstance(msg, self.unknown_cls) and (
            resync or not (end == n or (end + 8 < n and data[end + 8] in (_MAGIC_V1, _MAGIC_V2)))
        ):
            return None
        return ts, msg, end

    def __iter__(self):
        data, n, p = self.data, len(self.data), 0
        candidates = re.compile(b"[\xfd\xfe]")
        while p < n:
            r = self._try(p, resync=False)
            if isinstance(r, tuple):
                ts, msg, p = r
                self.last_ts = ts
                yield ts, msg
                continue
            # damaged here: find the next position where a whole valid record starts
            self.bad += 1
            q, found = p + 1, None
            for m in candidates.finditer(data, p + 9):
                q = m.start() - 8
                r2 = self._try(q, resync=True)
                if isinstance(r2, tuple):
                    found = q
                    break
            if found is None:
                self.skipped += n - p
                return
            self.skipped += found - p
            p = found


def _mode_names(mav_type: int) -> dict[int, str]:
    from pymavlink import mavutil

    try:
        return dict(mavutil.mode_mapping_bynumber(mav_type) or {})
    except Exception:  # noqa: BLE001 - unknown vehicle type: numbers only
        return {}


def read_tlog(
    path: str | Path,
    *,
    u_name: str = "CUR_U",
    v_name: str = "CUR_V",
    pair_tolerance_ms: int = RULES.pair_tolerance_ms,
    max_gap_ms: int = RULES.max_gap_ms,
    vehicle_sysid: int | None = None,
) -> TelemetryLog:
    """Read a ``.tlog`` (see module docstring).

    Args:
        path: the telemetry log.
        u_name, v_name: NAMED_VALUE_FLOAT names of the eastward/northward current (m/s).
        pair_tolerance_ms: largest ``time_boot_ms`` difference between a u reading and its v reading (ms).
        max_gap_ms: largest time between the two fixes a reading's position is interpolated from (ms).
        vehicle_sysid: the vehicle's system id; default: the system sending vehicle
            HEARTBEATs (autopilot not INVALID, type not GCS), else the one sending positions.

    Raises:
        LogReadError: the file is missing or unreadable (a damaged file is read as far as possible).
    """
    path = Path(path)
    data = read_log_file(path, "telemetry log")
    scan = TlogScanner(data)
    out = TelemetryLog(path=path, kind="tlog", n_bytes=len(data))
    tally = _TlogTally(out)
    for ts, msg in scan:
        tally.add(ts, msg)
    out.bad_frames, out.skipped_bytes = scan.bad, scan.skipped
    if vehicle_sysid is None:
        vehicle_sysid = tally.vehicle_sysid()
    out.vehicle_sysid = vehicle_sysid
    if vehicle_sysid is not None:
        out.message_counts["_vehicle_frames"] = tally.frames[vehicle_sysid]
        out.seq_lost = tally.lost[vehicle_sysid]
        _Interpreter(out, vehicle_sysid, u_name, v_name, int(pair_tolerance_ms), int(max_gap_ms)).run(tally.kept)
    return out


class _TlogTally:
    """One pass over a tlog's messages: message counts and first/last UTC into ``out``; per system the
    frames, the frames lost (sequence gaps), the vehicle HEARTBEATs and positions; the messages the
    interpreter needs (``kept``: (utc s, message))."""

    def __init__(self, out: TelemetryLog):
        self.out = out
        self.kept: list[tuple[float, Any]] = []
        self.hb_count: Counter = Counter()
        self.pos_count: Counter = Counter()
        self.last_seq: dict[tuple[int, int], int] = {}
        self.frames: Counter = Counter()
        self.lost: Counter = Counter()

    def add(self, ts: int, msg) -> None:
        """One message received at ``ts`` (µs UTC)."""
        out = self.out
        out.n_messages += 1
        t = msg.get_type()
        key = (msg.get_srcSystem(), msg.get_srcComponent())
        seq = msg.get_seq()
        if key in self.last_seq:
            self.lost[key[0]] += (seq - self.last_seq[key] - 1) % 256
        self.last_seq[key] = seq
        self.frames[key[0]] += 1
        out.message_counts[t] += 1
        utc = ts * 1e-6
        out.utc_first = utc if out.utc_first is None else out.utc_first
        out.utc_last = utc
        if t in _INTERESTING:
            self.kept.append((utc, msg))
            if t == "HEARTBEAT" and msg.autopilot != 8 and msg.type != 6:  # not INVALID autopilot, not a GCS
                self.hb_count[msg.get_srcSystem()] += 1
            elif t == "GLOBAL_POSITION_INT":
                self.pos_count[msg.get_srcSystem()] += 1

    def vehicle_sysid(self) -> int | None:
        """The system sending the most vehicle HEARTBEATs, else the most positions; None if none did."""
        if not (self.hb_count or self.pos_count):
            return None
        return (self.hb_count or self.pos_count).most_common(1)[0][0]


class _Interpreter:
    """Turns the ordered vehicle/GCS messages into track, samples, uploads, legs, events."""

    def __init__(self, out: TelemetryLog, veh: int, u_name: str, v_name: str, tol_ms: int, max_gap_ms: int):
        self.out, self.veh, self.u_name, self.v_name = out, veh, u_name, v_name
        self.max_gap_ms = max_gap_ms
        self.pairer = HalfPairer(tol_ms)
        self.boots = BootCounter()
        self.leg: LegRecord | None = None
        self.upload: MissionUpload | None = None
        self.mode: int | None = None
        self.armed: int | None = None
        self.readings: list[tuple[int, Any]] = []  # (boot, Reading with meta_u = (utc, leg, source))
        self.pos: list[tuple[int, int, float, float]] = []  # (boot, tb, lat, lon)
        self.seen: set = set()

    def _boot_of(self, tb: int) -> int:
        """The boot of a vehicle time stamp (every GLOBAL_POSITION_INT and NAMED_VALUE_FLOAT, as live)."""
        if self.boots.see(tb) is not None:
            self.pairer.clear()  # the new boot reuses the old times
        return self.boots.boot

    def _event(self, utc: float, kind: str, value: int | None = None, detail: str = "") -> None:
        self.out.events.append(LogEvent(utc, kind, value, detail))

    def _complete(self, utc: float) -> None:
        leg = self.leg
        if leg is None:
            return
        leg.complete, leg.t_end = True, utc
        self._event(utc, "complete", leg.index)
        self.leg = None

    def run(self, msgs: list[tuple[float, Any]]) -> None:
        out = self.out
        for utc, m in msgs:
            t = m.get_type()
            src = m.get_srcSystem()
            if src == self.veh:
                getattr(self, "_veh_" + t.lower(), _ignore)(utc, m)
            else:
                getattr(self, "_gcs_" + t.lower(), _ignore)(utc, m)
        legs_of_readings = self._place()
        for leg in out.legs:
            leg.n_samples = sum(1 for s in out.samples if s.leg == leg.index)
            leg.n_readings = legs_of_readings.count(leg.index)

    # -- vehicle messages
    def _veh_heartbeat(self, utc: float, m) -> None:
        if m.type == 6 or m.autopilot == 8:
            return
        if self.out.vehicle_compid is None:
            self.out.vehicle_compid = m.get_srcComponent()
        if m.custom_mode != self.mode:
            self.mode = m.custom_mode
            self._event(utc, "mode", m.custom_mode, _mode_names(m.type).get(m.custom_mode, f"MODE{m.custom_mode}"))
        armed = int(bool(m.base_mode & 128))
        if armed != self.armed:
            self.armed = armed
            self._event(utc, "armed", armed)

    def _veh_global_position_int(self, utc: float, m) -> None:
        boot = self._boot_of(m.time_boot_ms)
        if m.lat == 0 and m.lon == 0:
            return  # no GPS fix yet
        k = ("pos", boot, m.time_boot_ms)
        if k in self.seen:
            return  # the same frame logged twice (two links)
        self.seen.add(k)
        lat, lon = m.lat * 1e-7, m.lon * 1e-7
        leg = self.leg.index if self.leg else -1
        self.out.track.append(TrackPoint(int(m.time_boot_ms), lat, lon, utc, leg, boot))
        self.pos.append((boot, int(m.time_boot_ms), lat, lon))

    def _veh_named_value_float(self, utc: float, m) -> None:
        name = m.name if isinstance(m.name, str) else m.name.decode(errors="replace")
        name = name.rstrip("\x00")
        boot = self._boot_of(m.time_boot_ms)
        if name not in (self.u_name, self.v_name):
            return
        k = (name, boot, m.time_boot_ms)
        if k in self.seen:
            return
        self.seen.add(k)
        meta = (utc, self.leg.index if self.leg else -1, f"mav:{m.get_srcSystem()}/{m.get_srcComponent()}")
        r = self.pairer.add("u" if name == self.u_name else "v", int(m.time_boot_ms), float(m.value), meta)
        if r is not None:
            self.readings.append((boot, r))

    def _veh_mission_ack(self, utc: float, m) -> None:
        up = self.upload
        if up is None or getattr(m, "mission_type", 0) != 0:
            return
        if m.target_system not in (0, up.gcs[0]):
            return
        # INVALID_SEQUENCE (13) answers a re-sent or out-of-order item: ArduPilot keeps the
        # transfer open and the upload goes on (it never ends a transfer with 13), so it does not
        # end the upload here, not even when it comes after the last item, before the final ACK.
        if int(m.type) == 13:
            return
        up.result, up.utc_end = int(m.type), utc
        self.upload = None
        self._event(utc, "upload", int(m.type), f"mission {up.index + 1}: {up.count} items")
        if up.accepted:
            if self.leg is not None:  # replaced before it completed
                self.leg.t_end = utc
            self.leg = LegRecord(len(self.out.legs), up.index, utc, n_waypoints=up.n_waypoints)
            self.out.legs.append(self.leg)

    def _veh_mission_current(self, utc: float, m) -> None:
        if self.leg is None:
            return
        state = getattr(m, "mission_state", 0)
        if state == 3:
            self.leg.active = True
        elif state == 5 and self.leg.active:
            self._complete(utc)

    def _veh_mission_item_reached(self, utc: float, m) -> None:
        self._event(utc, "item_reached", int(m.seq))
        if self.leg is not None:
            self.leg.active = True

    def _veh_statustext(self, utc: float, m) -> None:
        text = m.text if isinstance(m.text, str) else m.text.decode(errors="replace")
        text = text.rstrip("\x00")
        self._event(utc, "text", int(m.severity), text)
        if text.startswith("Mission Complete"):
            self._complete(utc)

    # -- GCS messages (mission upload)
    def _gcs_mission_count(self, utc: float, m) -> None:
        if getattr(m, "mission_type", 0) != 0 or m.target_system not in (0, self.veh):
            return
        up = MissionUpload(len(self.out.missions), (m.get_srcSystem(), m.get_srcComponent()), int(m.count), utc)
        self.out.missions.append(up)
        self.upload = up

    def _gcs_mission_item_int(self, utc: float, m, is_int: bool = True) -> None:
        up = self.upload
        if up is None or getattr(m, "mission_type", 0) != 0 or m.get_srcSystem() != up.gcs[0]:
            return
        if not 0 <= m.seq < up.count:
            return
        scale = 1e-7 if is_int else 1.0
        up.items_by_seq[int(m.seq)] = MissionItem(
            int(m.seq), int(m.command), int(m.frame), m.x * scale, m.y * scale, float(m.z), is_int
        )

    def _gcs_mission_item(self, utc: float, m) -> None:
        self._gcs_mission_item_int(utc, m, is_int=False)

    # -- placing the readings
    def _place(self) -> list[int]:
        """Places each reading (paired as it came) on its boot's track; returns the leg of every reading."""
        tracks: dict[int, Track] = {}
        for b, tb, la, lo in self.pos:
            tracks.setdefault(b, Track(self.max_gap_ms)).add(tb, la, lo)
        legs: list[int] = []
        for boot, r in self.readings:
            utc, leg, source = r.meta_u
            legs.append(leg)
            pos = tracks[boot].at(r.t_ms) if boot in tracks else None
            if pos is None:
                continue
            self.out.samples.append(
                Sample(r.t_ms, utc, pos.lat, pos.lon, r.u, r.v, leg, source, boot=boot, gap_ms=pos.gap_ms)
            )
        self.out.n_readings = len(legs)
        return legs


def _ignore(*_: Any) -> None:
    return None


# -- DataFlash -----------------------------------------------------------------------------
_DF_HEAD = b"\xa3\x95"


def read_dataflash(
    path: str | Path,
    *,
    u_name: str = "CUR_U",
    v_name: str = "CUR_V",
    cur_message: str = "CUR",
    pair_tolerance_ms: int = RULES.pair_tolerance_ms,
    max_gap_ms: int = RULES.max_gap_ms,
) -> TelemetryLog:
    """Read an ArduPilot DataFlash ``.bin`` log (see module docstring).

    Positions come from ``POS`` (``Lat``/``Lng``), or ``GPS`` when the log has no
    ``POS``. Samples come from ``cur_message`` records (columns ``U``, ``V``) or
    from ``NVF`` named values ``u_name``/``v_name`` (u paired with the v nearest in ``TimeUS``
    within ``pair_tolerance_ms``, in file order: :class:`passt_mav.loop.measurement.HalfPairer`), placed on the
    track at their time as in :func:`read_tlog`
    (fixes at most ``max_gap_ms`` apart; ``gap_ms`` recorded). ``time_boot_ms`` = ``TimeUS //
    1000``; a DataFlash log holds no reception time, so ``utc`` is NaN. Legs are not
    reconstructed from DataFlash (``leg`` = -1).

    Raises:
        LogReadError: the file is missing or unreadable.
    """
    path = Path(path)
    data = read_log_file(path, "DataFlash log")
    out = TelemetryLog(path=path, kind="dataflash", n_bytes=len(data))
    records = _DataflashScanner(data, out).scan()
    _df_interpret(out, records, u_name, v_name, cur_message, int(pair_tolerance_ms), int(max_gap_ms))
    return out


class _DataflashScanner:
    """Walks the records of a DataFlash log (FMT records describe the others), decoding each through
    ``DFReader``'s format classes; a record counts only when another header (or the end of the file)
    follows it, damage is skipped to the next such record. Counts go to ``out``."""

    def __init__(self, data: bytes, out: TelemetryLog):
        from pymavlink import DFReader

        self.data, self.n, self.out = data, len(data), out
        self.fmt_fmt = DFReader.DFFormat(0x80, "FMT", 89, "BBnNZ", "Type,Length,Name,Format,Columns")
        self.formats: dict[int, Any] = {0x80: self.fmt_fmt}
        self.records: dict[str, list] = {}
        self._message = DFReader.DFMessage

    def scan(self) -> dict[str, list]:
        """The decoded records (``DFMessage``) by message name, in file order."""
        p = 0
        while p < self.n:
            end = self._record(p) if self._header_ok(p) else None
            p = self._resync(p) if end is None else end
        return self.records

    def _header_ok(self, p: int) -> bool:
        """A record header of a known format starts at ``p``."""
        return p + 3 <= self.n and self.data[p : p + 2] == _DF_HEAD and self.data[p + 2] in self.formats

    def _follows_ok(self, p: int) -> bool:
        """A valid record of known length starts at ``p`` and ends at EOF or before another header."""
        if not self._header_ok(p):
            return False
        end = p + self.formats[self.data[p + 2]].len
        return end == self.n or self._header_ok(end)

    def _record(self, p: int) -> int | None:
        """The end of the record at ``p`` once kept (a FMT's format installed); None if it is damaged; the end
        of the file if the record is cut off by it."""
        fmt = self.formats[self.data[p + 2]]
        end = p + fmt.len
        if end > self.n:  # the last record, cut off by the end of the file (still being written, power cut)
            self.out.truncated_bytes = self.n - p
            return self.n
        body = self.data[p + 3 : end]
        if fmt.type == 0x80:
            if not self._install_format(body, end):
                return None
        elif not (end == self.n or self._header_ok(end)):
            return None
        else:
            self._keep(fmt, body)
        self.out.n_messages += 1
        self.out.message_counts[fmt.name] += 1
        return end

    def _install_format(self, body: bytes, end: int) -> bool:
        """Install the format a FMT record's ``body`` describes; False (the previous one kept) if it does not
        describe itself consistently or no record header follows at ``end``."""
        newfmt = _format_record(self.fmt_fmt, body)
        if newfmt is None:
            return False
        saved = self.formats.get(newfmt.type)
        self.formats[newfmt.type] = newfmt
        ok = end == self.n or self._header_ok(end)
        if not ok:
            if saved is None:
                self.formats.pop(newfmt.type, None)
            else:
                self.formats[newfmt.type] = saved
        return ok

    def _keep(self, fmt, body: bytes) -> None:
        """Decode a data record (dropped if its body does not unpack)."""
        try:
            elements = list(struct.unpack(fmt.msg_struct, body))
        except struct.error:
            return
        self.records.setdefault(fmt.name, []).append(self._message(fmt, elements, True, None))

    def _resync(self, p: int) -> int:
        """Skip the damage at ``p`` to the next header followed by another; the end of the file if there is
        none (a tail shorter than any record counts as truncated, not skipped)."""
        out, n = self.out, self.n
        out.bad_frames += 1
        q = self.data.find(_DF_HEAD, p + 1)
        while q != -1 and not self._follows_ok(q):
            q = self.data.find(_DF_HEAD, q + 1)
        if q == -1:
            if n - p < 3 + 256:  # no header after it and shorter than any record: a cut-off tail
                out.bad_frames -= 1
                out.truncated_bytes = n - p
            else:
                out.skipped_bytes += n - p
            return n
        out.skipped_bytes += q - p
        return q


def _format_record(fmt_fmt, body: bytes):
    """The ``DFFormat`` a FMT record's ``body`` describes, None if it does not describe itself consistently."""
    from pymavlink import DFReader

    try:
        ftype, flen, name, fmt, cols = struct.unpack(fmt_fmt.msg_struct, body)
        f = DFReader.DFFormat(ftype, DFReader.null_term(name), flen, DFReader.null_term(fmt), DFReader.null_term(cols))
        if struct.calcsize(f.msg_struct) + 3 != flen:
            return None
        return f
    except Exception:  # noqa: BLE001 - an FMT that does not describe itself consistently is damage
        return None


def _df_interpret(
    out: TelemetryLog, records: dict[str, list], u_name: str, v_name: str, cur_message: str, tol: int, max_gap_ms: int
) -> None:
    nan = float("nan")
    pos_name = "POS" if records.get("POS") else "GPS"
    for m in records.get(pos_name, []):
        try:
            lat, lon, tus = float(m.Lat), float(m.Lng), int(m.TimeUS)
        except (AttributeError, TypeError, ValueError):
            continue
        if pos_name == "GPS" and getattr(m, "Status", 3) < 3:
            continue  # no 3D fix
        if lat == 0 and lon == 0:
            continue
        out.track.append(TrackPoint(tus // 1000, lat, lon, nan))
    out.track.sort(key=lambda p: p.time_boot_ms)
    track = Track(max_gap_ms)
    for p in out.track:
        track.add(p.time_boot_ms, p.lat, p.lon)

    pairs: list[tuple[int, float, float]] = []  # (tb, u, v)
    for m in records.get(cur_message, []):
        try:
            pairs.append((int(m.TimeUS) // 1000, float(m.U), float(m.V)))
        except (AttributeError, TypeError, ValueError):
            continue
    pairer = HalfPairer(tol)
    for m in records.get("NVF", []):
        try:
            name, tb, val = str(m.Name), int(m.TimeUS) // 1000, float(m.Value)
        except (AttributeError, TypeError, ValueError):
            continue
        if name in (u_name, v_name) and (r := pairer.add("u" if name == u_name else "v", tb, val)) is not None:
            pairs.append((r.t_ms, r.u, r.v))
    pairs.sort(key=lambda x: x[0])
    out.n_readings = len(pairs)
    out.reading_times = [tb for tb, _, _ in pairs]
    for tb, u, v in pairs:
        pos = track.at(tb)
        if pos is None:
            continue
        out.samples.append(Sample(tb, nan, pos.lat, pos.lon, u, v, -1, "dataflash", gap_ms=pos.gap_ms))
