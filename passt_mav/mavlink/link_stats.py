"""What one MAVLink link received and how long its round trip takes: counters, frame loss, RTT samples.

:class:`LinkAccounting` is fed by the link's reader thread (every frame, every TIMESYNC answer) and by
the threads that send TIMESYNC requests or time a command. All times are wall-clock seconds on the link's
clock (:meth:`passt_mav.mavlink.clock.Clock.now`).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

from passt_mav.mavlink.clock import SYSTEM_CLOCK, Clock

__all__ = ["LinkAccounting", "LinkStats"]


@dataclass
class LinkStats:
    """Counters of one link (since :meth:`Link.connect`)."""

    received: int = 0
    sent: int = 0
    bad: int = 0
    drops: int = 0  # frames missing from the vehicle's sequence numbers
    vehicle_bytes: int = 0  # bytes of the frames received from the vehicle's system (the link budget it uses)
    rtt_s: float | None = None
    by_type: collections.Counter = field(default_factory=collections.Counter)

    @property
    def loss(self) -> float:
        """Fraction of the vehicle's frames that never arrived (from sequence gaps)."""
        total = self.received + self.drops
        return self.drops / total if total else 0.0


class LinkAccounting:
    """The counters of one link (:attr:`stats`), its frame loss from sequence gaps, and its round trip.

    Attributes:
        stats: the :class:`LinkStats` since the last :meth:`new_stats`.
        rtt_samples: the last 16 round-trip times, seconds (kept across :meth:`new_stats`).

    Args:
        clock: the link's clock (TIMESYNC requests: when sent, and their ``ts1``).
    """

    def __init__(self, clock: Clock = SYSTEM_CLOCK):
        self.clock = clock
        self.stats = LinkStats()
        self.rtt_samples: collections.deque[float] = collections.deque(maxlen=16)
        self._last_seq: dict[tuple[int, int], int] = {}
        self._timesync_pending: dict[int, float] = {}

    def new_stats(self) -> None:
        """Start counting afresh (a new connect attempt); the round-trip samples stay."""
        self.stats = LinkStats()

    def restart_sequences(self) -> None:
        """Forget the last sequence number of every sender: a new transport (or a rebooted vehicle) restarts
        them, and frames missed during an outage are not loss on the link."""
        self._last_seq.clear()

    def count(self, msg, typ: str, target_system: int | None) -> bool:
        """Count one received frame ``msg`` of type ``typ``; returns whether it is from the vehicle.

        Sequence gaps count as drops for the vehicle's system (every system while ``target_system`` is
        None); the bytes of the vehicle's frames add up in ``vehicle_bytes``.
        """
        st = self.stats
        st.received += 1
        st.by_type[typ] += 1
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if target_system is None or src[0] == target_system:
            last = self._last_seq.get(src)
            if last is not None:
                st.drops += (msg.get_seq() - last - 1) % 256
            self._last_seq[src] = msg.get_seq()
        from_vehicle = target_system is not None and src[0] == target_system
        if from_vehicle:
            st.vehicle_bytes += len(msg.get_msgbuf())
        return from_vehicle

    @property
    def rtt(self) -> float | None:
        """Median measured round-trip time, seconds (None before any sample)."""
        if not self.rtt_samples:
            return None
        s = sorted(self.rtt_samples)
        return s[len(s) // 2]

    def add_rtt(self, dt: float) -> None:
        """One round-trip sample of ``dt`` seconds; ``stats.rtt_s`` becomes the new median."""
        self.rtt_samples.append(dt)
        self.stats.rtt_s = self.rtt

    def timesync_request(self) -> int:
        """Record a TIMESYNC request about to be sent (dropping those unanswered for 30 s); returns its ts1
        (UTC ns)."""
        now = self.clock.now()
        for k in [k for k, t in self._timesync_pending.items() if now - t > 30.0]:
            self._timesync_pending.pop(k, None)  # requests the vehicle never answered
        ts1 = self.clock.wall_ns()
        self._timesync_pending[ts1] = now
        return ts1

    def timesync_answered(self, ts1: int, now: float) -> None:
        """The answer to the request ``ts1`` arrived at ``now`` (the clock's wall s): one RTT sample (none for a
        request that is not ours or was answered already)."""
        sent = self._timesync_pending.pop(ts1, None)
        if sent is not None:
            self.add_rtt(now - sent)

    def timesync_abandoned(self, ts1: int) -> None:
        """Stop waiting for the answer to the request ``ts1``."""
        self._timesync_pending.pop(ts1, None)
