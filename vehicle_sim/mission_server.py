"""Mission protocol server with ArduPilot's semantics (see shared/ARDUPILOT_ROVER.md).

Per mission type (0 mission, 1 fence, 2 rally) a separate list; mission_type is
echoed in every reply. For type 0, seq 0 is home: whatever is uploaded there is
replaced by home, and a download returns it as frame 0 (GLOBAL).

Upload (GCS -> vehicle): MISSION_COUNT -> the stored list is truncated to the new
count at once -> MISSION_REQUEST (id 40, not _INT) for seq 0, 1, ... -> each
MISSION_ITEM_INT (or MISSION_ITEM, with a STATUSTEXT asking for _INT) overwrites in
place -> MISSION_ACK ACCEPTED after the last. Requests are paced at the vehicle's
own rate (``mission_request_interval_s``, ArduPilot asks for ~48 items/s),
re-sent after ``mission_rerequest_s`` of silence; the upload is cancelled
(MISSION_ACK OPERATION_CANCELLED + "Mission upload timeout") after
``mission_timeout_s``. Out-of-sequence items get INVALID_SEQUENCE (the transfer
continues); a second GCS (other sysid/compid) mid-transfer gets DENIED, as does a
download of the type being uploaded; a count above capacity, and any count before
storage is initialised (first ``storage_ready_s``), gets NO_SPACE and the warning
"Only N items are supported" (N = 0 while initialising); an item while no
upload is running gets ERROR.

Download: MISSION_REQUEST_LIST -> MISSION_COUNT (type 0 counts home) ->
MISSION_REQUEST_INT -> MISSION_ITEM_INT (int32 degE7 exactly as stored); the legacy
MISSION_REQUEST is answered with a float MISSION_ITEM (and a one-time warning).

Stored form (``normalise``, on by default): like Rover 4.7 the vehicle keeps an item in
its own packed form, not verbatim (ARDUPILOT_ROVER.md table; :data:`STORED_FIELDS`):
each param is cast to the small field the firmware keeps it in (uint16 hold time,
uint8 speed type, a loiter radius reduced to its sign, ...) or dropped (reads back 0);
only location commands keep x/y/z, with the altitude in whole centimetres and the
frame folded to 0 / 3 / 10 (GLOBAL, RELATIVE_ALT, TERRAIN); every other command reads
back frame 0 with x = y = z = 0; ``autocontinue`` reads back 1. Items the firmware
refuses are refused with its MISSION_ACK result and no STATUSTEXT, ending the
transfer: an unknown command UNSUPPORTED, a location command in another frame
UNSUPPORTED_FRAME, latitude beyond 90° INVALID_PARAM5_X, longitude beyond 180°
INVALID_PARAM6_Y, a NaN or >= 83 km altitude INVALID_PARAM7, a NaN param k
INVALID_PARAMk (except a waypoint's param4 yaw), a DO_JUMP whose target is 0 or not in the
list ERROR. With
``MissionServer.normalise = False`` items are stored verbatim (only the ``_INT``
frames folded), which the differential test uses to show it would catch the difference.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, replace

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["Item", "MissionStore", "MissionServer", "GLOBAL_FRAMES", "STORED_FIELDS", "firmware_form"]

M = mavlink2
#: frames whose x/y are latitude/longitude
GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})
_INT_TO_PLAIN = {5: 0, 6: 3, 11: 10}
TYPES = (0, 1, 2)


# What Rover 4.7's AP_Mission keeps of each param, per command (measured on the SITL build in
# ../shared/sitl: an item packs into 15 bytes, so most params live in small integer fields):
#   "f" float32 | "u8"/"u16"/"i8"/"i16" C cast (truncate toward zero, keep the low bits)
#   "sign" -1 if < 0 else 1 | "flag" 1 if > 0 else 0 | "+u8"/"+u16" magnitude in the field, sign kept
#   "" dropped (reads back 0)
#: command -> (stores a location, kinds of param1..param4)
STORED_FIELDS: dict[int, tuple[bool, tuple[str, str, str, str]]] = {
    16: (True, ("u16", "", "", "")),  # NAV_WAYPOINT: hold time; acceptance radius is WP_RADIUS
    17: (True, ("", "", "+u16", "")),  # NAV_LOITER_UNLIM
    18: (True, ("u8", "", "+u8", "flag")),  # NAV_LOITER_TURNS
    19: (True, ("u16", "", "sign", "flag")),  # NAV_LOITER_TIME: the radius keeps only its direction
    20: (False, ("", "", "", "")),  # NAV_RETURN_TO_LAUNCH
    21: (True, ("u16", "", "", "sign")),  # NAV_LAND
    22: (True, ("u16", "", "", "")),  # NAV_TAKEOFF
    82: (True, ("u16", "", "", "")),  # NAV_SPLINE_WAYPOINT
    93: (False, ("f", "i8", "i8", "i8")),  # NAV_DELAY
    112: (False, ("f", "", "", "")),  # CONDITION_DELAY
    114: (False, ("f", "", "", "")),  # CONDITION_DISTANCE
    115: (False, ("f", "f", "i8", "u8")),  # CONDITION_YAW
    177: (False, ("u16", "i16", "", "")),  # DO_JUMP
    178: (False, ("u8", "f", "f", "")),  # DO_CHANGE_SPEED
    179: (True, ("u16", "", "", "")),  # DO_SET_HOME
    181: (False, ("u8", "u8", "", "")),  # DO_SET_RELAY
    182: (False, ("u8", "i16", "f", "")),  # DO_REPEAT_RELAY
    183: (False, ("u16", "u16", "", "")),  # DO_SET_SERVO
    184: (False, ("u16", "u16", "i16", "f")),  # DO_REPEAT_SERVO
    189: (True, ("", "", "", "")),  # DO_LAND_START
    194: (False, ("u16", "", "", "")),  # DO_SET_REVERSE
    201: (True, ("u16", "", "", "")),  # DO_SET_ROI
    206: (False, ("f", "", "", "")),  # DO_SET_CAM_TRIGG_DIST
    207: (False, ("u16", "", "", "")),  # DO_FENCE_ENABLE
    211: (False, ("u8", "u8", "", "")),  # DO_GRIPPER
    215: (False, ("u16", "", "", "")),  # DO_SET_RESUME_REPEAT_DIST
}
#: frames a location command may use, and the frame it reads back in
_LOCATION_FRAMES = {0: 0, 2: 0, 5: 0, 3: 3, 6: 3, 10: 10, 11: 10}
_ALT_MAX_M = 83000.0  # ArduPilot's LOCATION_ALT_MAX_M (24-bit centimetres)


def _as_f32(v: float) -> float:
    return struct.unpack("<f", struct.pack("<f", v))[0] if math.isfinite(v) else v


def _cast(kind: str, v: float) -> float:
    if kind == "":
        return 0.0
    if kind == "f":
        return _as_f32(v)
    if kind == "sign":
        return -1.0 if v < 0 else 1.0
    if kind == "flag":
        return 1.0 if v > 0 else 0.0
    if kind[0] == "+":
        mag = _cast(kind[1:], abs(v))
        return -mag if v < 0 else mag
    if not math.isfinite(v):
        return 0.0  # undefined in C; the firmware's result is not modelled
    bits = int(kind[1:])
    n = int(v) % (1 << bits)
    if kind[0] == "i" and n >= 1 << (bits - 1):
        n -= 1 << bits
    return float(n)


def firmware_form(item: Item, count: int) -> Item | int:
    """The item as Rover 4.7 stores it (mission type 0) in a list of ``count`` items, or the
    MAV_MISSION_RESULT refusing it."""
    if item.mission_type != 0:
        return item
    spec = STORED_FIELDS.get(item.command)
    if spec is None:
        return M.MAV_MISSION_UNSUPPORTED
    located, kinds = spec
    raw = (item.param1, item.param2, item.param3, item.param4)
    for k, v in enumerate(raw):
        # NaN is refused in every param except a waypoint's yaw (param4, "unchanged")
        if math.isnan(v) and not (item.command == 16 and k == 3):
            return M.MAV_MISSION_INVALID_PARAM1 + k
    if item.command == 177 and not 1 <= _cast("u16", float(item.param1)) < count:
        return M.MAV_MISSION_ERROR  # a jump must land inside the list being uploaded, never on home
    params = [_cast(k, float(v)) for k, v in zip(kinds, (item.param1, item.param2, item.param3, item.param4))]
    if located:
        if item.frame not in _LOCATION_FRAMES:
            return M.MAV_MISSION_UNSUPPORTED_FRAME
        if abs(item.x) > 900000000:
            return M.MAV_MISSION_INVALID_PARAM5_X
        if abs(item.y) > 1800000000:
            return M.MAV_MISSION_INVALID_PARAM6_Y
        if not math.isfinite(item.z) or abs(item.z) >= _ALT_MAX_M:
            return M.MAV_MISSION_INVALID_PARAM7
        # altitude kept as int32 centimetres: float32 metres x 100, truncated toward zero
        cm = math.trunc(_as_f32(_as_f32(item.z) * 100.0))
        frame, x, y, z = _LOCATION_FRAMES[item.frame], item.x, item.y, _as_f32(cm / 100.0)
    else:
        frame, x, y, z = 0, 0, 0, 0.0
    return replace(
        item,
        frame=frame,
        current=0,
        autocontinue=1,
        param1=params[0],
        param2=params[1],
        param3=params[2],
        param4=params[3],
        x=x,
        y=y,
        z=z,
    )


@dataclass(frozen=True)
class Item:
    """One stored item, in MISSION_ITEM_INT terms (x, y = degE7 for global frames)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = 0

    @property
    def lat(self) -> float:
        return self.x / 1e7

    @property
    def lon(self) -> float:
        return self.y / 1e7

    @classmethod
    def from_msg(cls, m) -> Item:
        """From a MISSION_ITEM_INT or MISSION_ITEM message."""
        frame = int(m.frame)
        if m.get_type() == "MISSION_ITEM" and frame in GLOBAL_FRAMES:
            # float degrees -> degE7, rounded (ArduPilot multiplies by 1e7)
            x, y = int(round(float(m.x) * 1e7)), int(round(float(m.y) * 1e7))
        else:
            x, y = int(m.x), int(m.y)
        x = max(-(2**31), min(2**31 - 1, x))
        y = max(-(2**31), min(2**31 - 1, y))
        return cls(
            int(m.seq),
            _INT_TO_PLAIN.get(frame, frame),
            int(m.command),
            int(m.current),
            int(m.autocontinue),
            float(m.param1),
            float(m.param2),
            float(m.param3),
            float(m.param4),
            x,
            y,
            float(m.z),
            int(getattr(m, "mission_type", 0)),
        )

    def to_int_msg(self, target_system: int, target_component: int):
        return M.MAVLink_mission_item_int_message(
            target_system,
            target_component,
            self.seq,
            self.frame,
            self.command,
            self.current,
            self.autocontinue,
            self.param1,
            self.param2,
            self.param3,
            self.param4,
            self.x,
            self.y,
            self.z,
            self.mission_type,
        )

    def to_float_msg(self, target_system: int, target_component: int):
        g = self.frame in GLOBAL_FRAMES
        return M.MAVLink_mission_item_message(
            target_system,
            target_component,
            self.seq,
            self.frame,
            self.command,
            self.current,
            self.autocontinue,
            self.param1,
            self.param2,
            self.param3,
            self.param4,
            self.x / 1e7 if g else float(self.x),
            self.y / 1e7 if g else float(self.y),
            self.z,
            self.mission_type,
        )


class MissionStore:
    """The three stored lists. ``items[0]`` of type 0 is always home."""

    def __init__(self, capacity: tuple[int, int, int]):
        self.capacity = tuple(int(c) for c in capacity)
        self.items: dict[int, list[Item]] = {t: [] for t in TYPES}
        self.items[0] = [self.home_item(0.0, 0.0, 0.0)]
        #: bumped on every change of a list (executors watch it)
        self.version = {t: 0 for t in TYPES}

    @staticmethod
    def home_item(lat: float, lon: float, alt: float) -> Item:
        return Item(
            0,
            0,
            M.MAV_CMD_NAV_WAYPOINT,
            0,
            1,
            0.0,
            0.0,
            0.0,
            0.0,
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            float(alt),
            0,
        )

    def set_home(self, lat: float, lon: float, alt: float) -> None:
        self.items[0][0] = self.home_item(lat, lon, alt)

    def count(self, mtype: int) -> int:
        return len(self.items[mtype])

    def truncate(self, mtype: int, n: int) -> None:
        lst = self.items[mtype]
        keep = max(n, 1) if mtype == 0 else n  # home is never removed
        del lst[keep:]
        self.version[mtype] += 1

    def put(self, item: Item) -> None:
        lst = self.items[item.mission_type]
        if item.seq < len(lst):
            lst[item.seq] = item
        else:
            lst.append(item)  # uploads arrive in sequence, so this is seq == len
        self.version[item.mission_type] += 1

    def clear(self, mtype: int) -> None:
        self.truncate(mtype, 0)


@dataclass
class _Upload:
    link: object
    sysid: int
    compid: int
    count: int
    next_seq: int = 0
    last_rx: float = 0.0
    last_req: float = -1e9
    want_request: bool = True
    warned_float: bool = False


class MissionServer:
    """Answers mission-protocol messages; see the module docstring.

    Args:
        store: the lists.
        config: a :class:`SimConfig` (capacities, timings).
        send: ``send(link, msg)`` queues a message on one link.
        text: ``text(link, severity, str)`` sends a STATUSTEXT (link None = all).
        home: ``home() -> (lat, lon, alt)`` the current home.
        on_change: ``on_change(mission_type)`` after an upload completes or a clear.
        sysid, compid: our identity (messages addressed elsewhere are ignored).
        normalise: store items in Rover 4.7's form and refuse what it refuses (:func:`firmware_form`);
            False stores them verbatim (settable later as the attribute of the same name).
    """

    def __init__(
        self,
        store: MissionStore,
        config,
        send: Callable,
        text: Callable,
        home: Callable,
        on_change: Callable[[int], None] | None = None,
        sysid: int = 1,
        compid: int = 1,
        normalise: bool = True,
    ):
        self.store, self.cfg = store, config
        self.normalise = bool(normalise)
        self._send, self._text, self._home = send, text, home
        self._on_change = on_change or (lambda _t: None)
        self.sysid, self.compid = sysid, compid
        self.uploads: dict[int, _Upload] = {}
        self._warned_request = False
        # download replies go out at the vehicle's pace too (ArduPilot answers one request per loop)
        self._dl_queue: list[tuple[object, object]] = []
        self._dl_last = -1e9
        self._now = 0.0

    # -- helpers ----------------------------------------------------------------
    def _ack(self, link, msg, mtype: int, result: int) -> None:
        self._send(link, M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), result, mtype))

    def _for_us(self, msg) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

    def item_for_download(self, mtype: int, seq: int) -> Item:
        it = self.store.items[mtype][seq]
        if mtype == 0 and seq == 0:
            lat, lon, alt = self._home()
            it = self.store.home_item(lat, lon, alt)
        return replace(it, seq=seq, current=0, mission_type=mtype)

    # -- message handling -----------------------------------------------------------
    HANDLED = frozenset(
        {
            "MISSION_COUNT",
            "MISSION_ITEM_INT",
            "MISSION_ITEM",
            "MISSION_REQUEST_LIST",
            "MISSION_REQUEST_INT",
            "MISSION_REQUEST",
            "MISSION_CLEAR_ALL",
            "MISSION_ACK",
        }
    )

    def handle(self, link, msg, t: float) -> bool:
        """Process one message; True if it was a mission-protocol message."""
        typ = msg.get_type()
        if typ not in self.HANDLED:
            return False
        if not self._for_us(msg):
            return True
        mtype = int(getattr(msg, "mission_type", 0))
        if typ == "MISSION_CLEAR_ALL":
            self._clear_all(link, msg, mtype)
            return True
        if typ == "MISSION_ACK":
            return True  # end of a download: nothing to do (ArduPilot keeps no download state)
        if mtype not in TYPES:
            self._ack(link, msg, mtype, M.MAV_MISSION_UNSUPPORTED)
            return True
        self._now = t
        getattr(self, "_on_" + typ.lower())(link, msg, mtype, t)
        return True

    def _is_owner(self, up: _Upload, msg) -> bool:
        return msg.get_srcSystem() == up.sysid and msg.get_srcComponent() == up.compid

    def _on_mission_count(self, link, msg, mtype, t):
        up = self.uploads.get(mtype)
        if up is not None and not self._is_owner(up, msg):
            self._ack(link, msg, mtype, M.MAV_MISSION_DENIED)
            return
        count = int(msg.count)
        # ArduPilot answers NO_SPACE until its storage is initialised (capacity 0 then; a retry
        # later succeeds), and above its capacity; both with the same warning
        capacity = 0 if t < self.cfg.storage_ready_s else self.store.capacity[mtype]
        if count > capacity:
            self.uploads.pop(mtype, None)
            self._ack(link, msg, mtype, M.MAV_MISSION_NO_SPACE)
            self._text(link, M.MAV_SEVERITY_WARNING, f"Only {capacity} items are supported")
            return
        self.store.truncate(mtype, count)
        if count == 0:
            self.uploads.pop(mtype, None)
            self._ack(link, msg, mtype, M.MAV_MISSION_ACCEPTED)
            self._on_change(mtype)
            return
        self.uploads[mtype] = _Upload(link, msg.get_srcSystem(), msg.get_srcComponent(), count, last_rx=t)
        self._pump(mtype, t)

    def _on_mission_item_int(self, link, msg, mtype, t):
        self._item(link, msg, mtype, t)

    def _on_mission_item(self, link, msg, mtype, t):
        self._item(link, msg, mtype, t)

    def _item(self, link, msg, mtype, t):
        if mtype == 0 and int(msg.current) in (2, 3):
            return  # guided-mode goto; the autopilot handles it before us
        up = self.uploads.get(mtype)
        if up is None:
            self._ack(link, msg, mtype, M.MAV_MISSION_ERROR)
            return
        if not self._is_owner(up, msg):
            self._ack(link, msg, mtype, M.MAV_MISSION_DENIED)
            return
        if int(msg.seq) != up.next_seq:
            self._ack(link, msg, mtype, M.MAV_MISSION_INVALID_SEQUENCE)
            return
        item = Item.from_msg(msg)
        if self.normalise:
            stored = firmware_form(replace(item, mission_type=mtype), up.count)
            if isinstance(stored, int):
                # the firmware refuses the item and ends the transfer (no STATUSTEXT); the list stays
                # truncated to the count, holding whatever arrived before
                del self.uploads[mtype]
                self._ack(link, msg, mtype, stored)
                self._on_change(mtype)
                return
            item = stored
        if mtype == 0 and item.seq == 0:
            lat, lon, alt = self._home()
            item = self.store.home_item(lat, lon, alt)  # seq 0 is home, whatever was sent
        self.store.put(replace(item, mission_type=mtype, current=0))
        if msg.get_type() == "MISSION_ITEM" and not up.warned_float:
            up.warned_float = True
            self._text(link, M.MAV_SEVERITY_WARNING, "got MISSION_ITEM; GCS should send MISSION_ITEM_INT")
        up.next_seq += 1
        up.last_rx = t
        if up.next_seq >= up.count:
            del self.uploads[mtype]
            self._ack(link, msg, mtype, M.MAV_MISSION_ACCEPTED)
            self._on_change(mtype)
            return
        up.want_request = True
        self._pump(mtype, t)

    def _on_mission_request_list(self, link, msg, mtype, t):
        if mtype in self.uploads:
            self._ack(link, msg, mtype, M.MAV_MISSION_DENIED)
            return
        self._send(
            link,
            M.MAVLink_mission_count_message(
                msg.get_srcSystem(), msg.get_srcComponent(), self.store.count(mtype), mtype
            ),
        )

    def _download_item(self, link, msg, mtype, as_float: bool):
        if mtype in self.uploads:
            self._ack(link, msg, mtype, M.MAV_MISSION_DENIED)
            return
        seq = int(msg.seq)
        if seq >= self.store.count(mtype):
            self._ack(link, msg, mtype, M.MAV_MISSION_INVALID_SEQUENCE)
            return
        it = self.item_for_download(mtype, seq)
        ts, tc = msg.get_srcSystem(), msg.get_srcComponent()
        reply = it.to_float_msg(ts, tc) if as_float else it.to_int_msg(ts, tc)
        if not self._dl_queue and self._now - self._dl_last >= self.cfg.mission_request_interval_s - 1e-9:
            self._dl_last = self._now
            self._send(link, reply)
        elif len(self._dl_queue) < 64:  # a flood of requests is answered at pace, the excess dropped
            self._dl_queue.append((link, reply))

    def _on_mission_request_int(self, link, msg, mtype, t):
        self._download_item(link, msg, mtype, as_float=False)

    def _on_mission_request(self, link, msg, mtype, t):
        if not self._warned_request:
            self._warned_request = True
            self._text(link, M.MAV_SEVERITY_WARNING, "got MISSION_REQUEST; use MISSION_REQUEST_INT!")
        self._download_item(link, msg, mtype, as_float=True)

    def _clear_all(self, link, msg, mtype):
        types = TYPES if mtype == M.MAV_MISSION_TYPE_ALL else ((mtype,) if mtype in TYPES else ())
        if not types:
            self._ack(link, msg, mtype, M.MAV_MISSION_UNSUPPORTED)
            return
        for ty in types:
            up = self.uploads.get(ty)
            if up is not None and not self._is_owner(up, msg):
                self._ack(link, msg, mtype, M.MAV_MISSION_DENIED)
                return
        for ty in types:
            self.uploads.pop(ty, None)
            self.store.clear(ty)
            self._on_change(ty)
        self._ack(link, msg, mtype, M.MAV_MISSION_ACCEPTED)

    # -- timers -------------------------------------------------------------------
    def _pump(self, mtype: int, t: float) -> None:
        up = self.uploads.get(mtype)
        if up is None:
            return
        if up.want_request and t - up.last_req >= self.cfg.mission_request_interval_s - 1e-9:
            self._request(up, mtype, t)

    def _request(self, up: _Upload, mtype: int, t: float) -> None:
        up.want_request = False
        up.last_req = t
        self._send(up.link, M.MAVLink_mission_request_message(up.sysid, up.compid, up.next_seq, mtype))

    def update(self, t: float) -> None:
        """Paced requests and download replies, re-requests after silence, cancellation after the timeout."""
        self._now = t
        if self._dl_queue and t - self._dl_last >= self.cfg.mission_request_interval_s - 1e-9:
            self._dl_last = t
            link, reply = self._dl_queue.pop(0)
            self._send(link, reply)
        for mtype in list(self.uploads):
            up = self.uploads[mtype]
            if t - up.last_rx > self.cfg.mission_timeout_s:
                del self.uploads[mtype]
                self._text(up.link, M.MAV_SEVERITY_WARNING, "Mission upload timeout")
                self._send(
                    up.link,
                    M.MAVLink_mission_ack_message(up.sysid, up.compid, M.MAV_MISSION_OPERATION_CANCELLED, mtype),
                )
                self._on_change(mtype)
                continue
            if up.want_request:
                self._pump(mtype, t)
            elif t - up.last_req > self.cfg.mission_rerequest_s:
                self._request(up, mtype, t)
