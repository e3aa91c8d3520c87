"""The controller's marks of a flying leg in the telemetry log: its end, the operator's pause and resume.

A mark is a STATUSTEXT from the controller to the vehicle (:func:`~passt_mav.runs.legs.leg_statustext`,
``PASST leg I end|pause|resume``): the link's telemetry log records it in order with every frame, and ArduPilot
writes it into its DataFlash log as a MSG. It is what lets a replay (:func:`~passt_mav.runs.legs.rebuild_from_tlog`)
tell the wait of an operator's Pause, after which the leg flies on, from the wait at a leg's end: both begin with
the same mode command (the vehicle's ``wait_mode``, LOITER or HOLD).
"""

from __future__ import annotations

import contextlib
import logging

from passt_mav.errors import MavlinkError
from passt_mav.runs.legs import leg_statustext

__all__ = ["mark_leg", "close_leg"]

log = logging.getLogger(__name__)


def mark_leg(link, i: int, mark: str) -> bool:
    """Send leg ``i``'s ``mark`` (``end``, ``pause`` or ``resume``) on ``link``; whether it was sent. A log record,
    not a command: a failed send (the link down) is logged, never raised (the commands around it report)."""
    try:
        link.statustext(leg_statustext(i, mark))
    except MavlinkError as exc:
        log.warning("leg %d: %s mark not sent: %s", i, mark, exc)
        return False
    return True


def close_leg(collector, link=None) -> None:
    """No reading arriving from now on belongs to a leg (a run that stops with a leg in flight; a stop can come
    between the swap and the flight). With ``link``, a leg that was open is marked ``end`` in the telemetry log at
    that very moment (under the link's dispatch lock: no reading is logged and routed in between), so a replay
    assigns the readings as the store does; without it, or in an older log, the replay ends the leg at the next
    mode command."""
    if collector is None:
        return
    if link is None or collector.leg is None:
        collector.leg = None
        return
    with getattr(link, "dispatch_lock", None) or contextlib.nullcontext():
        i, collector.leg = int(collector.leg), None
        mark_leg(link, i, "end")
