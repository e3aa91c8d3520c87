"""A leg's link figures: the part of :class:`~passt_mav.vehicle.session.VehicleSession` that measures the link
(round trip, loss, the bytes the vehicle sent per second of its clock) between two points of a leg.

A mixin: it uses the session's ``link``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from passt_mav.mavlink.link import Link

__all__ = ["LinkFigures"]


class LinkFigures:
    """Counters at a leg's start (:meth:`link_snapshot`), figures since then (:meth:`link_record`)."""

    if TYPE_CHECKING:  # the session's, which this mixin uses (module docstring)
        link: Link

    def link_snapshot(self) -> tuple:
        """Counters to measure a leg's link figures from (:meth:`link_record`)."""
        st = self.link.stats
        return st.received, st.drops, st.vehicle_bytes, self.link.vehicle_uptime_s()

    def link_record(self, before: tuple) -> dict:
        """Link figures since ``before``; ``vehicle_bytes_per_s``: bytes the vehicle sent us per second of its
        own clock (the telemetry radio's budget: baud / 10 bytes/s each way), None without a vehicle clock."""
        st = self.link.stats
        rec, drops = st.received - before[0], st.drops - before[1]
        nbytes, t1 = st.vehicle_bytes - before[2], self.link.vehicle_uptime_s()
        rtt = self.link.rtt
        bps = nbytes / (t1 - before[3]) if t1 is not None and before[3] is not None and t1 - before[3] > 1.0 else None
        return {
            "rtt_ms": None if rtt is None else round(rtt * 1000.0, 3),
            "loss": (drops / (rec + drops)) if rec + drops else 0.0,
            "messages": int(rec),
            "drops": int(drops),
            "vehicle_bytes": int(nbytes),
            "vehicle_bytes_per_s": None if bps is None else round(bps, 1),
        }
