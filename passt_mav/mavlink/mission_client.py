"""MAVLink mission protocol, client side: upload, download, read-back verification.

Written to shared/ARDUPILOT_ROVER.md (ArduPilot Rover 4.x):

* seq 0 is home: upload a placeholder there (:func:`with_home`), waypoints from 1;
* the vehicle asks with MISSION_REQUEST (id 40) *or* MISSION_REQUEST_INT; both
  are answered with MISSION_ITEM_INT (coordinates int32 degE7);
* success is only MISSION_ACK ACCEPTED; any other result raises
  :class:`MissionRejected` naming it, except NO_SPACE while the vehicle is still
  initialising (retried) and INVALID_SEQUENCE mid-transfer (the transfer goes on);
* the vehicle paces the transfer and re-requests on silence; the client resends
  MISSION_COUNT while no request comes, re-sends the last requested item on
  silence, and every call is bounded by an overall deadline (:class:`LinkTimeout`);
* an upload that fails midway leaves a mix of old and new items on the vehicle,
  so :meth:`MissionClient.upload_verified` reads the list back and compares.

A lost final ACK is recovered like MAVProxy does: the last item is re-sent; a
vehicle that has already closed the transfer answers ERROR, and the upload is
then confirmed (or refuted) by reading the mission back.

The vehicle does not store items verbatim (ARDUPILOT_ROVER.md, "The vehicle does not
store items verbatim"): :func:`rover_stored` is the one description of what Rover 4.7
keeps of an item (table :data:`ROVER_STORAGE`), and the read-back comparison uses it,
so it compares what the firmware keeps and never a field it drops. A transfer the
vehicle cancels (MISSION_ACK OPERATION_CANCELLED after its own 8 s timeout, e.g. under
heavy loss) is restarted from MISSION_COUNT, up to ``cancel_restarts`` times.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import replace

from passt_mav.errors import CommandRejected, LinkTimeout, MissionRejected, MissionVerifyError
from passt_mav.mavlink.link import Link, mavlink2, result_name
from passt_mav.mavlink.modes import ROVER_MODES
from passt_mav.mission.items import GLOBAL_FRAMES, MAV_FRAME_GLOBAL, MAV_MISSION_TYPE_MISSION, MissionItem

__all__ = [
    "MissionClient",
    "MissionWatch",
    "with_home",
    "to_msg",
    "from_msg",
    "UploadResult",
    "rover_stored",
    "ROVER_STORAGE",
    "differences",
]

log = logging.getLogger(__name__)
M = mavlink2
_ACCEPTED = M.MAV_MISSION_ACCEPTED


# -- what ArduPilot Rover 4.7 stores of an item ----------------------------------------------------
# AP_Mission packs an item into a 15-byte command: each param goes through a C conversion to a
# small field (or is dropped), and only "location" commands keep x/y/z and an altitude frame.
# Measured on the SITL build in ../shared/sitl (tests/test_sitl_differential.py checks this
# table against it item by item); the command list follows AP_Mission::mavlink_int_to_mission_cmd.


def _f32(v: float) -> float:
    """A float param stored as float32 (NaN stays NaN)."""
    return struct.unpack("<f", struct.pack("<f", v))[0] if math.isfinite(v) else v


def _int_wrap(bits: int, signed: bool) -> Callable[[float], float]:
    def conv(v: float) -> float:
        # C float -> small int: truncation toward zero, then the bits that fit (65535 for -1 as u16,
        # 4464 for 70000, as the firmware returns them); NaN/inf are undefined in C: 0 here
        if not math.isfinite(v):
            return 0.0
        n = int(v) & ((1 << bits) - 1)
        if signed and n >= 1 << (bits - 1):
            n -= 1 << bits
        return float(n)

    return conv


def _sign(v: float) -> float:
    return -1.0 if v < 0 else 1.0  # loiter direction kept as a flag: radius 10 reads back 1


def _positive(v: float) -> float:
    return 1.0 if v > 0 else 0.0  # e.g. LOITER_TIME param4 "xtrack" kept as a flag


def _signed_abs(conv: Callable[[float], float]) -> Callable[[float], float]:
    return lambda v: -conv(abs(v)) if v < 0 else conv(abs(v))  # magnitude in a field, sign as "ccw"


_U8, _U16, _I8, _I16 = _int_wrap(8, False), _int_wrap(16, False), _int_wrap(8, True), _int_wrap(16, True)
_F = _f32
_0 = None  # dropped: reads back 0

#: MAV_CMD -> (keeps a location (x, y, z, altitude frame), (param1..param4 conversions or None = dropped)).
#: Commands not listed are refused by Rover with MAV_MISSION_UNSUPPORTED.
ROVER_STORAGE: dict[int, tuple[bool, tuple]] = {
    16: (True, (_U16, _0, _0, _0)),  # NAV_WAYPOINT: hold s; radius/pass-by/yaw dropped
    17: (True, (_0, _0, _signed_abs(_U16), _0)),  # NAV_LOITER_UNLIM: radius (sign = ccw)
    18: (True, (_U8, _0, _signed_abs(_U8), _positive)),  # NAV_LOITER_TURNS: turns, radius in one byte each
    19: (True, (_U16, _0, _sign, _positive)),  # NAV_LOITER_TIME: time s; param3 only its sign
    20: (False, (_0, _0, _0, _0)),  # NAV_RETURN_TO_LAUNCH: nothing, not even frame/x/y
    21: (True, (_U16, _0, _0, _sign)),  # NAV_LAND
    22: (True, (_U16, _0, _0, _0)),  # NAV_TAKEOFF
    82: (True, (_U16, _0, _0, _0)),  # NAV_SPLINE_WAYPOINT: hold s
    93: (False, (_F, _I8, _I8, _I8)),  # NAV_DELAY: s, hour/min/sec UTC
    112: (False, (_F, _0, _0, _0)),  # CONDITION_DELAY: s
    114: (False, (_F, _0, _0, _0)),  # CONDITION_DISTANCE: m
    115: (False, (_F, _F, _I8, _U8)),  # CONDITION_YAW
    177: (False, (_U16, _I16, _0, _0)),  # DO_JUMP: target seq, repeat count
    178: (False, (_U8, _F, _F, _0)),  # DO_CHANGE_SPEED: type, m/s, throttle %
    179: (True, (_U16, _0, _0, _0)),  # DO_SET_HOME
    181: (False, (_U8, _U8, _0, _0)),  # DO_SET_RELAY
    182: (False, (_U8, _I16, _F, _0)),  # DO_REPEAT_RELAY
    183: (False, (_U16, _U16, _0, _0)),  # DO_SET_SERVO: channel, PWM
    184: (False, (_U16, _U16, _I16, _F)),  # DO_REPEAT_SERVO
    189: (True, (_0, _0, _0, _0)),  # DO_LAND_START
    194: (False, (_U16, _0, _0, _0)),  # DO_SET_REVERSE
    201: (True, (_U16, _0, _0, _0)),  # DO_SET_ROI
    206: (False, (_F, _0, _0, _0)),  # DO_SET_CAM_TRIGG_DIST
    207: (False, (_U16, _0, _0, _0)),  # DO_FENCE_ENABLE
    211: (False, (_U8, _U8, _0, _0)),  # DO_GRIPPER
    215: (False, (_U16, _0, _0, _0)),  # DO_SET_RESUME_REPEAT_DIST
}
#: altitude frame a location command is stored and read back in (the _INT frames and MISSION fold)
_STORED_FRAME = {0: 0, 2: 0, 5: 0, 3: 3, 6: 3, 10: 10, 11: 10}


def _alt_cm(z: float) -> float:
    """Altitude kept in whole centimetres (float32 metres * 100, truncated), read back as metres."""
    return _f32(math.trunc(_f32(_f32(z) * 100.0)) / 100.0) if math.isfinite(z) else z


def rover_stored(item: MissionItem) -> MissionItem:
    """What Rover 4.7 stores for ``item`` and returns on download (mission type 0; others unchanged).

    Per :data:`ROVER_STORAGE`: each param converted to the field it is kept in, dropped params 0;
    location commands keep lat/lon (degE7) and the altitude in cm with frame 0/3/10 (GLOBAL,
    RELATIVE_ALT, TERRAIN: the _INT frames and MISSION fold into these); other commands read back
    frame 0 with x = y = z = 0; ``current`` 0, ``autocontinue`` 1. A command Rover does not know
    (it refuses it with UNSUPPORTED) is returned unchanged.
    """
    if item.mission_type != MAV_MISSION_TYPE_MISSION or item.command not in ROVER_STORAGE:
        return item
    located, convs = ROVER_STORAGE[item.command]
    p = [0.0 if c is None else c(float(v)) for c, v in zip(convs, (item.param1, item.param2, item.param3, item.param4))]
    if located:
        # x/y travel and are kept as int32 degE7
        frame = _STORED_FRAME.get(item.frame, item.frame)
        lat, lon, alt = item.x_int / 1e7, item.y_int / 1e7, _alt_cm(item.alt)
    else:
        frame, lat, lon, alt = MAV_FRAME_GLOBAL, 0.0, 0.0, 0.0
    return replace(
        item,
        frame=frame,
        current=0,
        autocontinue=1,
        param1=p[0],
        param2=p[1],
        param3=p[2],
        param4=p[3],
        lat=lat,
        lon=lon,
        alt=alt,
    )


def with_home(
    waypoints: Sequence[MissionItem],
    home: tuple[float, float] = (0.0, 0.0),
    mission_type: int = MAV_MISSION_TYPE_MISSION,
) -> list[MissionItem]:
    """Items ready to upload: a home placeholder at seq 0 (mission type 0 only) and
    ``waypoints`` renumbered from 1. ArduPilot overwrites seq 0 with its own home."""
    out = []
    if mission_type == MAV_MISSION_TYPE_MISSION:
        out.append(MissionItem(0, frame=MAV_FRAME_GLOBAL, lat=home[0], lon=home[1], mission_type=mission_type))
    for w in waypoints:
        out.append(
            MissionItem(
                len(out),
                w.frame,
                w.command,
                0,
                w.autocontinue,
                w.param1,
                w.param2,
                w.param3,
                w.param4,
                w.lat,
                w.lon,
                w.alt,
                mission_type,
            )
        )
    return out


def to_msg(item: MissionItem, target_system: int | None, target_component: int):
    """MISSION_ITEM_INT for ``item`` (lat/lon -> int32 degE7 for global frames)."""
    return M.MAVLink_mission_item_int_message(
        target_system,
        target_component,
        item.seq,
        item.frame,
        item.command,
        item.current,
        item.autocontinue,
        item.param1,
        item.param2,
        item.param3,
        item.param4,
        item.x_int,
        item.y_int,
        item.alt,
        item.mission_type,
    )


def from_msg(m) -> MissionItem:
    """MissionItem from a MISSION_ITEM_INT (or float MISSION_ITEM)."""
    g = int(m.frame) in GLOBAL_FRAMES
    if m.get_type() == "MISSION_ITEM_INT":
        lat, lon = (m.x / 1e7, m.y / 1e7) if g else (float(m.x), float(m.y))
    else:
        lat, lon = float(m.x), float(m.y)
    return MissionItem(
        int(m.seq),
        int(m.frame),
        int(m.command),
        int(m.current),
        int(m.autocontinue),
        float(m.param1),
        float(m.param2),
        float(m.param3),
        float(m.param4),
        lat,
        lon,
        float(m.z),
        int(getattr(m, "mission_type", 0)),
    )


class UploadResult:
    """What an upload did: ``count`` items, ``ack_lost`` (ACCEPTED never seen; confirmed by
    read-back), ``no_space_retries``, ``cancel_restarts`` (transfers restarted after the vehicle
    cancelled them), ``count_sends``, ``items_sent`` (incl. resends), ``seconds``, ``opaque_id``
    (the final MISSION_ACK's ``opaque_id``: the vehicle's id of the stored mission; 0 = not sent)."""

    def __init__(self, **kw):
        self.opaque_id = kw.get("opaque_id", 0)
        self.count = kw.get("count", 0)
        self.ack_lost = kw.get("ack_lost", False)
        self.no_space_retries = kw.get("no_space_retries", 0)
        self.cancel_restarts = kw.get("cancel_restarts", 0)
        self.count_sends = kw.get("count_sends", 0)
        self.items_sent = kw.get("items_sent", 0)
        self.seconds = kw.get("seconds", 0.0)

    def __repr__(self) -> str:
        return "UploadResult(" + ", ".join(f"{k}={v!r}" for k, v in vars(self).items()) + ")"


class MissionClient:
    """Mission protocol over a connected :class:`Link`.

    Args:
        link: a connected link.
        item_timeout_s: wait for the next request/reply (default: the link's reply timeout).
        retries: resends of MISSION_COUNT / one item request / the last item before giving up
            (default: the link's retries, at least 10: at 20 % loss each way a round trip
            fails 36 % of the time, and 0.36**11 is about 1e-5). The overall deadline bounds it all.
        no_space_retries, no_space_delay_s: NO_SPACE retries while the vehicle is initialising.
        boot_grace_s: a vehicle up for less than this (time_boot_ms), or in INITIALISING
            (custom mode 16), is "still initialising": its NO_SPACE is retried. Later a
            NO_SPACE is a real capacity limit and raised at once.
        cancel_restarts: a transfer the vehicle cancelled (OPERATION_CANCELLED: its own 8 s item
            timeout ran out, e.g. under heavy loss) is started again from MISSION_COUNT this many times.
    """

    def __init__(
        self,
        link: Link,
        *,
        item_timeout_s: float | None = None,
        retries: int | None = None,
        no_space_retries: int = 5,
        no_space_delay_s: float = 1.0,
        boot_grace_s: float = 30.0,
        cancel_restarts: int = 3,
    ):
        self.link = link
        self.item_timeout_s = item_timeout_s
        self.retries = max(link.config.retries, 10) if retries is None else retries
        self.cancel_restarts = cancel_restarts
        self.no_space_retries = no_space_retries
        self.no_space_delay_s = no_space_delay_s
        self.boot_grace_s = boot_grace_s

    # -- helpers --------------------------------------------------------------------------------
    @property
    def _t_item(self) -> float:
        return self.item_timeout_s if self.item_timeout_s is not None else self.link.reply_timeout

    def _deadline(self, n: int, timeout: float | None) -> float:
        if timeout is None:
            # the vehicle's own pace (~48 items/s on ArduPilot) with generous slack, plus NO_SPACE retries
            timeout = (
                4 * (self.retries + 1) * self._t_item
                + n * (0.1 + self._t_item / 4)
                + self.no_space_retries * self.no_space_delay_s
            )
        return self.link.clock.now() + timeout

    def _initialising(self) -> bool:
        hb = self.link.latest("HEARTBEAT")
        if hb is not None and hb.custom_mode == ROVER_MODES["INITIALISING"]:
            return True
        up = self.link.vehicle_uptime_s()
        return up is None or up < self.boot_grace_s

    def _ours(self, m, mission_type: int) -> bool:
        return int(getattr(m, "mission_type", 0)) == mission_type and self.link.for_us(m)

    def _recent_text(self, since: float) -> str:
        return "; ".join(t for when, sev, t in list(self.link.texts) if when >= since and sev <= M.MAV_SEVERITY_WARNING)

    def _reject(self, result: int, since: float, detail: str = "") -> MissionRejected:
        text = self._recent_text(since)
        return MissionRejected(
            result, result_name("MAV_MISSION_RESULT", result), "; ".join(x for x in (detail, text) if x)
        )

    # -- upload ---------------------------------------------------------------------------------
    def upload(
        self,
        items: Sequence[MissionItem],
        mission_type: int = MAV_MISSION_TYPE_MISSION,
        *,
        timeout: float | None = None,
    ) -> UploadResult:
        """Upload ``items`` (seq 0..n-1; for mission type 0, seq 0 is the home placeholder).

        Returns an :class:`UploadResult` once the vehicle answered MISSION_ACK ACCEPTED.
        Raises :class:`MissionRejected` (any other result), :class:`LinkTimeout` (no
        answer, or the overall deadline passed) or ValueError (badly numbered items).
        """
        items = list(items)
        for i, it in enumerate(items):
            if it.seq != i:
                raise ValueError(f"item {i} has seq {it.seq}; items must be numbered 0..n-1 (see with_home)")
            if it.mission_type != mission_type:
                raise ValueError(f"item {i} has mission_type {it.mission_type}, uploading type {mission_type}")
        types = ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK")
        with self.link.subscribe(types) as sub:
            tr = _Upload(self, items, mission_type, timeout, sub)
            tr.send_count()
            while True:
                remaining = tr.deadline - self.link.clock.now()
                if remaining <= 0:
                    raise LinkTimeout(
                        f"mission upload of {tr.n} items not finished within the deadline "
                        f"({self.link.clock.now() - tr.t0:.1f} s; last item sent {tr.last_seq})"
                    )
                m = sub.get(min(self._t_item, remaining))
                if m is None:
                    tr.on_silence()
                elif not self._ours(m, mission_type):
                    continue
                elif m.get_type() != "MISSION_ACK":
                    tr.on_request(int(m.seq))
                elif (res := tr.on_ack(m)) is not None:
                    return res

    # -- download -------------------------------------------------------------------------------
    def download(
        self, mission_type: int = MAV_MISSION_TYPE_MISSION, *, timeout: float | None = None
    ) -> list[MissionItem]:
        """Read the list back: MISSION_REQUEST_LIST -> COUNT -> REQUEST_INT/ITEM_INT per item -> ACK.

        For mission type 0 item 0 is the vehicle's home. Raises MissionRejected / LinkTimeout.
        """
        link = self.link
        ts, tc = link.target_system, link.target_component
        t0 = link.clock.now()
        deadline = self._deadline(0, timeout)
        with link.subscribe(("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK")) as sub:

            def wait(pred, send, what):
                error = None
                for _ in range(self.retries + 1):
                    send()
                    end = min(link.clock.now() + self._t_item, deadline)
                    while (m := sub.get(end - link.clock.now())) is not None:
                        if not self._ours(m, mission_type):
                            continue
                        if m.get_type() == "MISSION_ACK":
                            if m.type == M.MAV_MISSION_ERROR:
                                # ArduPilot answers an item that arrives while no upload runs with
                                # ERROR: the echo of our upload's last item, resent as its ACCEPTED
                                # crossed it, can land in the read-back that follows. Asked again,
                                # as after silence; reported if the vehicle keeps answering ERROR
                                error = m.type
                                break
                            if m.type != _ACCEPTED:
                                raise self._reject(m.type, t0, f"while downloading ({what})")
                            continue
                        if pred(m):
                            return m
                    if link.clock.now() >= deadline:
                        break
                if error is not None:
                    raise self._reject(error, t0, f"while downloading ({what})")
                raise LinkTimeout(f"mission download: no {what}" + (" (link lost)" if link.lost else ""))

            cm = wait(
                lambda m: m.get_type() == "MISSION_COUNT",
                lambda: link.send(M.MAVLink_mission_request_list_message(ts, tc, mission_type)),
                "MISSION_COUNT",
            )
            count = int(cm.count)
            if timeout is None:
                deadline = max(deadline, self._deadline(count, None))
            out = []
            for seq in range(count):
                m = wait(
                    lambda m, s=seq: m.get_type() == "MISSION_ITEM_INT" and m.seq == s,
                    lambda s=seq: link.send(M.MAVLink_mission_request_int_message(ts, tc, s, mission_type)),
                    f"item {seq}/{count}",
                )
                out.append(from_msg(m))
            link.send(M.MAVLink_mission_ack_message(ts, tc, _ACCEPTED, mission_type))
        return out

    def upload_verified(
        self,
        items: Sequence[MissionItem],
        mission_type: int = MAV_MISSION_TYPE_MISSION,
        *,
        timeout: float | None = None,
    ) -> list[MissionItem]:
        """Upload, then read back and compare (command, frame, lat/lon to 1e-7 deg, params, alt;
        seq 0 of mission type 0 is home and skipped). Returns the list read back.

        Raises :class:`MissionVerifyError` naming the first differing items.
        """
        self.upload(items, mission_type, timeout=timeout)
        got = self.download(mission_type, timeout=timeout)
        bad = differences(list(items), got, mission_type)
        if bad:
            raise MissionVerifyError(f"mission read back differs from the upload: {bad}")
        return got

    # -- other operations -----------------------------------------------------------------------
    def clear(self, mission_type: int = MAV_MISSION_TYPE_MISSION, *, timeout: float | None = None) -> None:
        """MISSION_CLEAR_ALL for one mission type; waits for MISSION_ACK ACCEPTED."""
        link = self.link
        t0 = link.clock.now()
        deadline = self._deadline(0, timeout)
        with link.subscribe("MISSION_ACK") as sub:
            for _ in range(self.retries + 1):
                link.send(M.MAVLink_mission_clear_all_message(link.target_system, link.target_component, mission_type))
                end = min(link.clock.now() + self._t_item, deadline)
                while (m := sub.get(end - link.clock.now())) is not None:
                    if self._ours(m, mission_type):
                        if m.type != _ACCEPTED:
                            raise self._reject(m.type, t0, "clearing the mission")
                        return
                if link.clock.now() >= deadline:
                    break
        raise LinkTimeout("no MISSION_ACK for MISSION_CLEAR_ALL" + (" (link lost)" if link.lost else ""))

    def set_current(self, seq: int, *, timeout: float | None = None) -> None:
        """Make item ``seq`` current: MAV_CMD_DO_SET_MISSION_CURRENT (224); a vehicle that does
        not support it gets MISSION_SET_CURRENT, confirmed by MISSION_CURRENT.seq."""
        link = self.link
        try:
            link.command_long(M.MAV_CMD_DO_SET_MISSION_CURRENT, seq, 0, timeout=timeout)
            return
        except CommandRejected as exc:
            if exc.result != M.MAV_RESULT_UNSUPPORTED:
                raise
        for _ in range(self.retries + 1):
            link.send(M.MAVLink_mission_set_current_message(link.target_system, link.target_component, seq))
            try:
                link.wait("MISSION_CURRENT", lambda m: m.seq == seq, timeout=timeout or self._t_item)
                return
            except LinkTimeout:
                continue
        raise LinkTimeout(f"MISSION_CURRENT never showed seq {seq}")


class _Upload:
    """One upload's transfer state (:meth:`MissionClient.upload`): what was requested and sent, silences,
    and the vehicle's answers (requests and MISSION_ACKs)."""

    def __init__(self, client: MissionClient, items: list[MissionItem], mission_type: int, timeout: float | None, sub):
        self.client, self.items, self.mission_type, self.timeout, self.sub = client, items, mission_type, timeout, sub
        self.link = client.link
        self.n = len(items)
        self.t0 = self.link.clock.now()
        self.deadline = client._deadline(self.n, timeout)
        self.res = UploadResult(count=self.n)
        self.requested = False  # a request of this transfer has arrived
        self.last_seq = -1  # last item requested and sent
        self.silent = 0  # consecutive silent periods
        self.last_resends = 0
        self.stale_errors = 0  # ERROR acks ignored before the first request (see on_ack)

    def send_count(self) -> None:
        self.res.count_sends += 1
        link = self.link
        link.send(M.MAVLink_mission_count_message(link.target_system, link.target_component, self.n, self.mission_type))

    def send_item(self, seq: int) -> None:
        self.res.items_sent += 1
        self.link.send(to_msg(self.items[seq], self.link.target_system, self.link.target_component))

    def on_silence(self) -> None:
        """No answer for an item timeout: send again what the vehicle may have missed."""
        self.silent += 1
        if self.silent > self.client.retries:
            raise LinkTimeout(
                f"vehicle silent during mission upload (item {self.last_seq + 1}/{self.n})"
                + (" (link lost)" if self.link.lost else "")
            )
        if not self.requested:
            self.send_count()
        elif self.last_seq == self.n - 1:
            self.last_resends += 1
            self.send_item(self.n - 1)  # the final ACK may be lost: the vehicle answers ERROR if it is done
        else:
            self.send_item(self.last_seq)  # our item may be lost (the vehicle re-requests too)

    def on_request(self, seq: int) -> None:
        if 0 <= seq < self.n:
            self.silent, self.requested, self.last_seq = 0, True, seq
            self.send_item(seq)

    def on_ack(self, m) -> UploadResult | None:
        """MISSION_ACK ``m``: the result once the transfer is over, None while it goes on; raises a refusal."""
        n, res, client = self.n, self.res, self.client
        result = int(m.type)
        if result == _ACCEPTED:
            if n == 0 or self.last_seq == n - 1:
                res.seconds = self.link.clock.now() - self.t0
                res.opaque_id = int(getattr(m, "opaque_id", 0) or 0)
                return res
            return None  # a stale ACK from an earlier transfer
        if result == M.MAV_MISSION_INVALID_SEQUENCE and self.requested:
            return None  # a duplicate item after a lost request: ArduPilot goes on with the transfer
        if result == M.MAV_MISSION_ERROR and self.last_seq == n - 1 and (self.last_resends or self.silent):
            return self._ack_lost(result)
        if result == M.MAV_MISSION_ERROR and not self.requested and self.stale_errors < client.retries:
            # ERROR answers an item that arrived while no upload ran; before the vehicle asked for any
            # item of this transfer it answers an earlier one (our last item, resent as its ACCEPTED
            # crossed it). Ignored a few times; a vehicle that keeps answering ERROR is reported
            self.stale_errors += 1
            return None
        if (
            result == M.MAV_MISSION_OPERATION_CANCELLED
            and self.requested
            and res.cancel_restarts < client.cancel_restarts
        ):
            # the vehicle gave up waiting (its 8 s item timeout); the stored list is now a
            # mix of old and new items, so start the whole transfer again
            res.cancel_restarts += 1
            log.info(
                "mission upload cancelled by the vehicle at item %d/%d; restarting (%d)",
                self.last_seq + 1,
                n,
                res.cancel_restarts,
            )
            self.sub.drain()
            self.requested, self.last_seq, self.silent, self.last_resends = False, -1, 0, 0
            if self.timeout is None:
                self.deadline = client._deadline(n, None)  # a fresh transfer gets a fresh budget
            self.send_count()
            return None
        if result == M.MAV_MISSION_NO_SPACE and not self.requested:
            self._no_space(result)
            return None
        raise client._reject(result, self.t0)

    def _ack_lost(self, result: int) -> UploadResult:
        """ERROR after our last item was sent again: the vehicle closed the transfer and its ACK was lost."""
        got = self.client.download(
            self.mission_type, timeout=max(self.deadline - self.link.clock.now(), self.client._t_item * 4)
        )
        bad = differences(self.items, got, self.mission_type)
        if bad:
            raise self.client._reject(result, self.t0, f"final ACK lost and the read-back differs: {bad}")
        self.res.ack_lost = True
        self.res.seconds = self.link.clock.now() - self.t0
        log.info("mission upload: final ACK lost, confirmed by read-back")
        return self.res

    def _no_space(self, result: int) -> None:
        """NO_SPACE before any request: a vehicle still initialising is asked again, else it is its capacity."""
        client, res = self.client, self.res
        if client._initialising() and res.no_space_retries < client.no_space_retries:
            res.no_space_retries += 1
            log.info(
                "NO_SPACE while the vehicle initialises; retry %d in %.1f s",
                res.no_space_retries,
                client.no_space_delay_s,
            )
            self.link.clock.sleep(min(client.no_space_delay_s, max(self.deadline - self.link.clock.now(), 0)))
            self.sub.drain()
            self.silent = 0
            self.send_count()
            return
        detail = (
            f"still NO_SPACE after {res.no_space_retries} retries"
            if res.no_space_retries
            else f"the vehicle has no room for {self.n} items (capacity limit)"
        )
        raise client._reject(result, self.t0, detail)


class MissionWatch:
    """Signs that another ground station changed the vehicle's mission (a listener on the link).

    Three signs, all from the vehicle's own messages (mission type 0):

    * the vehicle's mission id changed: ``MISSION_CURRENT.mission_id`` (MAVLink's opaque id of the
      stored plan) differs from the ``opaque_id`` of our last upload's MISSION_ACK. Only where the
      firmware fills it: ArduPilot Rover 4.7 SITL sends neither (its MISSION_CURRENT payload ends
      after ``mission_state``, its MISSION_ACK after ``type``), and pymavlink 2.4's dialect has no
      such field, so there this sign is silent;
    * ``MISSION_CURRENT.total`` is not the count we uploaded (``total`` excludes home);
    * through a router (MAVProxy, mavlink-router) the vehicle's replies to other ground stations
      reach us too: a MISSION_ACK ACCEPTED addressed to another system/component ends *their*
      upload; their MISSION_REQUESTs show an upload in progress (``foreign_peer`` says who).

    None of these sees a same-length upload on a direct link to ArduPilot 4.7; the controller's
    read-back does (see :meth:`passt_mav.vehicle.session.VehicleSession.swap`).
    """

    def __init__(self, link: Link):
        self.link = link
        self.expected_total: int | None = None  # items after home of our last upload
        self.expected_id = 0  # opaque id of our last upload (0 = none sent)
        self.total: int | None = None
        self.mission_id = 0
        self.foreign_uploads = 0  # MISSION_ACK ACCEPTED to another GCS (seen through a router)
        self.foreign_requests = 0  # MISSION_REQUEST(_INT) to another GCS: an upload in progress
        self.foreign_peer: tuple[int, int] | None = None
        link.add_listener(self._on, ("MISSION_CURRENT", "MISSION_ACK", "MISSION_REQUEST", "MISSION_REQUEST_INT"))

    def close(self) -> None:
        self.link.remove_listener(self._on)

    def _on(self, m) -> None:
        if self.link.target_system is None or m.get_srcSystem() != self.link.target_system:
            return
        if int(getattr(m, "mission_type", 0)) != MAV_MISSION_TYPE_MISSION:
            return
        if m.get_type() == "MISSION_CURRENT":
            self.total = int(m.total)
            self.mission_id = int(getattr(m, "mission_id", 0) or 0)
            return
        if self.link.for_us(m):
            return
        self.foreign_peer = (int(m.target_system), int(m.target_component))
        if m.get_type() == "MISSION_ACK":
            if int(m.type) == _ACCEPTED:
                self.foreign_uploads += 1
        else:
            self.foreign_requests += 1

    def expect(self, n_items: int, opaque_id: int = 0) -> tuple[int, int]:
        """After our own verified upload of ``n_items`` (home included). Returns a mark for :meth:`changed`."""
        self.expected_total, self.expected_id = int(n_items) - 1, int(opaque_id)
        self.total = None  # a MISSION_CURRENT from before the upload says nothing about it
        return self.mark()

    def mark(self) -> tuple[int, int]:
        return self.foreign_uploads, self.foreign_requests

    def changed(self, mark: tuple[int, int]) -> str:
        """'' while nothing says the mission changed since ``mark``; else why it may have."""
        who = "" if self.foreign_peer is None else f" (system {self.foreign_peer[0]} component {self.foreign_peer[1]})"
        if self.foreign_uploads > mark[0]:
            return f"another ground station{who} uploaded a mission"
        if self.foreign_requests > mark[1]:
            return f"another ground station{who} is uploading a mission"
        if self.expected_id and self.mission_id and self.mission_id != self.expected_id:
            return f"the vehicle's mission id changed ({self.expected_id} -> {self.mission_id})"
        if self.expected_total is not None and self.total is not None and self.total != self.expected_total:
            return f"the vehicle now holds {self.total} items, we uploaded {self.expected_total}"
        return ""


def differences(sent: list[MissionItem], got: list[MissionItem], mission_type: int) -> str:
    """'' if the vehicle holds what it would store of ``sent`` (:func:`rover_stored`, within wire
    tolerance), else a short description of what differs."""
    if len(sent) != len(got):
        return f"{len(got)} items on the vehicle, {len(sent)} uploaded"
    bad = []
    for a, b in zip(sent, got):
        if mission_type == MAV_MISSION_TYPE_MISSION and a.seq == 0:
            continue  # home: the vehicle writes its own
        # what the vehicle keeps of each (rover_stored), never a field it drops; lat/lon to 1e-7 deg
        if not rover_stored(a).same_as(rover_stored(b)):
            bad.append(f"seq {a.seq}: sent {a}, vehicle has {b}")
    return "; ".join(bad[:3]) + (f" (+{len(bad) - 3} more)" if len(bad) > 3 else "")
