"""Telemetry stream rates of one vehicle: SET_MESSAGE_INTERVAL per message, REQUEST_DATA_STREAM groups.

Works on a link's public side (``command_long``, ``send``, ``target_system``, ``target_component``):
see :meth:`passt_mav.mavlink.link.Link.request_streams`. Rates are in Hz.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from passt_mav.errors import CommandRejected, LinkTimeout, UserError

__all__ = ["STREAM_GROUPS", "request_data_stream", "request_streams"]

log = logging.getLogger(__name__)

#: messages that are not streams: ArduPilot refuses SET_MESSAGE_INTERVAL for them (TIMESYNC: result 2
#: and "No ap_message for mavlink id (111)"); the link sends TIMESYNC requests itself instead
_NOT_STREAMS = frozenset({"TIMESYNC"})
#: REQUEST_DATA_STREAM stream ids of the messages the controller uses (ArduPilot's stream groups,
#: ``MAVn_POSITION``, ``MAVn_EXT_STAT``, ``MAVn_EXTRA3``): the fallback where SET_MESSAGE_INTERVAL is refused
STREAM_GROUPS = {
    "GLOBAL_POSITION_INT": mavlink2.MAV_DATA_STREAM_POSITION,
    "MISSION_CURRENT": mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS,
    "EKF_STATUS_REPORT": mavlink2.MAV_DATA_STREAM_EXTRA3,
    "SYSTEM_TIME": mavlink2.MAV_DATA_STREAM_EXTRA3,
}


def request_streams(link, rates: Iterable[tuple[str, float]], quiet_others: bool) -> dict[str, bool]:
    """SET_MESSAGE_INTERVAL on ``link`` for each ``(MESSAGE_NAME, hz)``; returns name -> accepted.

    With ``quiet_others`` every data stream is stopped first. A refusal is logged, not raised; a
    refused message of :data:`STREAM_GROUPS` is requested by its stream group at the same rate
    (REQUEST_DATA_STREAM has no answer: the message's arrival is the check).
    """
    out = {}
    rates = list(rates)
    if quiet_others and rates:  # (no rates: leave the vehicle's streams as they are)
        # REQUEST_DATA_STREAM has no answer and the stop is idempotent: sent three times, a lossy
        # radio (3 % loss) leaves every stream running with p = 3e-5 instead of 3 % (seen once at
        # 19200 baud in the radio test: the vehicle kept all its streams)
        for _ in range(3):
            request_data_stream(link, mavlink2.MAV_DATA_STREAM_ALL, 0)
    for name, hz in rates:
        msgid = getattr(mavlink2, f"MAVLINK_MSG_ID_{name}", None)
        if msgid is None:
            raise UserError(f"unknown MAVLink message {name!r} in stream_rates_hz")
        if name in _NOT_STREAMS:
            log.debug("%s is not a stream (ArduPilot refuses it); measured with requests instead", name)
            continue
        interval_us = -1 if hz <= 0 else 1e6 / hz
        try:
            link.command_long(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, msgid, interval_us, retries=2)
            out[name] = True
        except (CommandRejected, LinkTimeout) as exc:
            out[name] = False
            group = STREAM_GROUPS.get(name)
            if group is None or hz <= 0:
                log.warning("stream %s at %.1f Hz not set: %s", name, hz, exc)
                continue
            log.warning(
                "stream %s at %.1f Hz not set (%s): requesting its stream group %d instead", name, hz, exc, group
            )
            request_data_stream(link, group, hz)
    return out


def request_data_stream(link, stream_id: int, hz: float) -> None:
    """REQUEST_DATA_STREAM to ``link``'s vehicle (``hz`` <= 0 stops the stream; rates are whole Hz, at least 1)."""
    rate = max(1, round(hz)) if hz > 0 else 0
    link.send(
        mavlink2.MAVLink_request_data_stream_message(
            link.target_system, link.target_component or 0, int(stream_id), rate, 1 if rate else 0
        )
    )
