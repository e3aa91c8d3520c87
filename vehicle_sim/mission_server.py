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
storage is initialised (first ``storage_ready_s``), gets NO_SPACE; an item while no
upload is running gets ERROR.

Download: MISSION_REQUEST_LIST -> MISSION_COUNT (type 0 counts home) ->
MISSION_REQUEST_INT -> MISSION_ITEM_INT (int32 degE7 exactly as stored); the legacy
MISSION_REQUEST is answered with a float MISSION_ITEM (and a one-time warning).

Stored frames: the ``_INT`` global frames are stored as their plain equivalents
(5 -> 0, 6 -> 3, 11 -> 10), as ArduPilot returns them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["Item", "MissionStore", "MissionServer", "GLOBAL_FRAMES"]

M = mavlink2
#: frames whose x/y are latitude/longitude
GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})
_INT_TO_PLAIN = {5: 0, 6: 3, 11: 10}
TYPES = (0, 1, 2)


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
    def from_msg(cls, m) -> "Item":
        """From a MISSION_ITEM_INT or MISSION_ITEM message."""
        frame = int(m.frame)
        if m.get_type() == "MISSION_ITEM" and frame in GLOBAL_FRAMES:
            # float degrees -> degE7, rounded (ArduPilot multiplies by 1e7)
            x, y = int(round(float(m.x) * 1e7)), int(round(float(m.y) * 1e7))
        else:
            x, y = int(m.x), int(m.y)
        x = max(-(2**31), min(2**31 - 1, x))
        y = max(-(2**31), min(2**31 - 1, y))
        return cls(int(m.seq), _INT_TO_PLAIN.get(frame, frame), int(m.command), int(m.current), int(m.autocontinue),
                   float(m.param1), float(m.param2), float(m.param3), float(m.param4), x, y, float(m.z),
                   int(getattr(m, "mission_type", 0)))

    def to_int_msg(self, target_system: int, target_component: int):
        return M.MAVLink_mission_item_int_message(
            target_system, target_component, self.seq, self.frame, self.command, self.current, self.autocontinue,
            self.param1, self.param2, self.param3, self.param4, self.x, self.y, self.z, self.mission_type)

    def to_float_msg(self, target_system: int, target_component: int):
        g = self.frame in GLOBAL_FRAMES
        return M.MAVLink_mission_item_message(
            target_system, target_component, self.seq, self.frame, self.command, self.current, self.autocontinue,
            self.param1, self.param2, self.param3, self.param4,
            self.x / 1e7 if g else float(self.x), self.y / 1e7 if g else float(self.y), self.z, self.mission_type)


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
        return Item(0, 0, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.0, 0.0, 0.0,
                    int(round(lat * 1e7)), int(round(lon * 1e7)), float(alt), 0)

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
    """

    def __init__(self, store: MissionStore, config, send: Callable, text: Callable, home: Callable,
                 on_change: Callable[[int], None] | None = None, sysid: int = 1, compid: int = 1):
        self.store, self.cfg = store, config
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
    HANDLED = frozenset({"MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_REQUEST_LIST",
                         "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_CLEAR_ALL", "MISSION_ACK"})

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
        if t < self.cfg.storage_ready_s:
            # ArduPilot answers NO_SPACE until its storage is initialised; a retry later succeeds
            self.uploads.pop(mtype, None)
            self._ack(link, msg, mtype, M.MAV_MISSION_NO_SPACE)
            return
        count = int(msg.count)
        if count > self.store.capacity[mtype]:
            self.uploads.pop(mtype, None)
            self._ack(link, msg, mtype, M.MAV_MISSION_NO_SPACE)
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
        self._send(link, M.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                         self.store.count(mtype), mtype))

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
                self._send(up.link, M.MAVLink_mission_ack_message(up.sysid, up.compid, M.MAV_MISSION_OPERATION_CANCELLED, mtype))
                self._on_change(mtype)
                continue
            if up.want_request:
                self._pump(mtype, t)
            elif t - up.last_req > self.cfg.mission_rerequest_s:
                self._request(up, mtype, t)
