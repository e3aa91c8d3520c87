"""Current samples from telemetry: NAMED_VALUE_FLOAT u/v placed on the vehicle's track.

The boat's Lua script sends ``gcs:send_named_float("CUR_U", u)`` and ``("CUR_V", v)``
(m/s, east/north; shared/ARDUPILOT_ROVER.md). Each NAMED_VALUE_FLOAT carries the
autopilot's ``time_boot_ms`` (ms), read separately for each half: the halves of one
reading are paired when at most ``pair_tolerance_ms`` apart, and the reading takes its
u half's time. The reading's position is the vehicle's track at that time: linear
interpolation between the GLOBAL_POSITION_INT fixes before and after it, when they are
at most ``max_gap_ms`` apart (:class:`geo.track.Track`). Both rules, and the reboot rule
below, are :mod:`passt_mav.loop.measurement`'s, which the log readers and the report follow too.

:class:`SampleCollector` emits one record once the u half, the v half and the fix
after the reading are there. A reading whose next fix has not arrived yet is held
until it does, or until vehicle time has run ``max_gap_ms`` past the fix before it
(then no fix can place it: it is dropped and counted, ``counts["gap"]``). Halves
seen twice (retransmission, a reconnect replaying a buffer, two links) are dropped;
halves that never find their partner expire after ``expire_ms`` of vehicle time.
Records go to ``on_sample(record)``:

``{"time_boot_ms": int, "utc": float (epoch s), "lat": deg, "lon": deg, "u": m/s,
"v": m/s, "gap_ms": int, "source": str, "boot": int}`` plus ``"leg"`` when
:attr:`SampleCollector.leg` is set (the leg open when the reading arrived). ``gap_ms``
is the time between the two fixes the position was interpolated from (0: a fix at the
reading's own time).

:attr:`SampleCollector.counts`: ``readings`` (complete u/v pairs), ``emitted``, ``gap``
(no fixes within ``max_gap_ms`` around it), ``duplicates``, ``expired`` (lone halves),
``reboots``. ``emitted / readings`` is the fraction of readings used.

UTC comes from SYSTEM_TIME (``time_unix_usec - time_boot_ms``); before the vehicle
has GPS time, from the wall clock at receipt.

Reboots. ``time_boot_ms`` going back by more than ``reboot_back_ms`` is a reboot of the
autopilot: the collector forgets its keys and its track (the new boot reuses the old
times; readings held for a fix are dropped and counted as ``gap``), counts
:attr:`SampleCollector.boot` up and gives later records ``"boot": n`` (the store keys
samples by ``(source, boot, time_boot_ms)``, so the new boot's readings are not duplicates).
:attr:`SampleCollector.boots` keeps per boot the vehicle's UTC at boot (when known) and
the wall time the boot was first seen; ``on_reboot(boot, last_tb_ms, first_tb_ms)`` is
called from the reader thread.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable

from geo.track import Track
from passt_mav.loop.measurement import RULES, BootCounter, HalfPairer
from passt_mav.mavlink.clock import SYSTEM_CLOCK, Clock, Timeout, clock_of

__all__ = ["SampleCollector"]


def _name(m) -> str:
    n = m.name
    if isinstance(n, (bytes, bytearray)):
        n = bytes(n).decode("ascii", "replace")
    return n.rstrip("\x00").strip()


class SampleCollector:
    """Pairs current readings with positions; see the module docstring.

    Args:
        on_sample: called with each record (from the link's reader thread: keep it quick).
        u_name, v_name: NAMED_VALUE_FLOAT names of the east / north components.
        max_gap_ms: largest time between the two fixes a reading's position is interpolated from (ms).
        expire_ms: drop unmatched halves older than this (vehicle time, ms).
        pair_tolerance_ms: largest time between the u and v halves of one reading (ms).
        source: the record's ``source`` field (e.g. "mavlink:tcp:127.0.0.1:5760").
        reboot_back_ms: ``time_boot_ms`` going back by more than this is a reboot.
        on_reboot: ``(boot, last_tb_ms, first_tb_ms)`` callback on a reboot (reader thread).
        boot_base: added to the boot number in records (a resumed run continues the stored numbering).
        clock: the wall clock of the records' ``wall`` and UTC stamps and of :meth:`wait_placed` (default the
            machine's; :meth:`attach` takes the link's).
    """

    TYPES = ("NAMED_VALUE_FLOAT", "GLOBAL_POSITION_INT", "SYSTEM_TIME")

    def __init__(
        self,
        on_sample: Callable[[dict], None],
        *,
        u_name: str = "CUR_U",
        v_name: str = "CUR_V",
        max_gap_ms: int = RULES.max_gap_ms,
        expire_ms: int = 10_000,
        source: str = "mavlink",
        reboot_back_ms: int = RULES.reboot_back_ms,
        on_reboot: Callable[[int, int, int], None] | None = None,
        boot_base: int = 0,
        pair_tolerance_ms: int = RULES.pair_tolerance_ms,
        clock: Clock = SYSTEM_CLOCK,
    ):
        if u_name == v_name:
            raise ValueError("u_name and v_name must differ")
        self.on_sample = on_sample
        self.u_name, self.v_name = u_name, v_name
        self.expire_ms = int(expire_ms)
        self.track = Track(max_gap_ms)  # this boot's fixes (time_boot_ms, lat, lon)
        self.source = source
        self.leg: int | None = None
        self._lock = threading.Lock()
        self.pairer = HalfPairer(pair_tolerance_ms, keep_ms=self.expire_ms)  # halves waiting for their partner
        self._seen: dict[tuple[int, str], None] = {}  # (time_boot_ms, name) already taken
        self._held: dict[int, tuple[float, float, float | None, int | None]] = {}  # tb -> (u, v, rx, leg)
        self._leg_counts: collections.Counter = collections.Counter()  # (leg, what) -> n
        self._utc_offset: float | None = None  # unix s - boot s
        self._newest = 0
        #: readings, emitted, gap, duplicates, expired, reboots
        self.counts: collections.Counter[str] = collections.Counter()
        self._link = None
        self.reboot_back_ms = int(reboot_back_ms)
        self._boot_counter = BootCounter(self.reboot_back_ms)
        self.on_reboot = on_reboot
        self.boot = 0  # reboots seen since attach
        self.boot_base = int(boot_base)  # records carry boot_base + boot
        #: per boot: {"utc_boot": vehicle UTC at boot (s) or None, "wall": wall time first seen, "last_tb": ms}
        self.clock = clock
        self.boots: list[dict] = [{"utc_boot": None, "wall": clock.wall(), "last_tb": 0}]

    # -- wiring ------------------------------------------------------------------------------
    def attach(self, link) -> SampleCollector:
        """Listen on a :class:`~passt_mav.mavlink.link.Link` (reader thread)."""
        self._link = link
        self.clock = clock_of(link, self.clock)
        link.add_listener(self.handle, self.TYPES)
        return self

    def detach(self) -> None:
        if self._link is not None:
            self._link.remove_listener(self.handle)
            self._link = None

    # -- input --------------------------------------------------------------------------------
    def handle(self, m) -> None:
        """Feed any message; only NAMED_VALUE_FLOAT, GLOBAL_POSITION_INT and SYSTEM_TIME matter."""
        with self._lock:
            rb, out = self._take(m, m.get_type())
        if rb is not None and self.on_reboot is not None:
            self.on_reboot(*rb)
        for rec in out:
            self.on_sample(rec)

    def _take(self, m, typ: str) -> tuple[tuple[int, int, int] | None, list[dict]]:
        """(reboot seen or None, records completed) for one message (lock held)."""
        out: list[dict] = []
        if typ == "SYSTEM_TIME":
            # (reboots are judged on positions and readings only: this offset is kept until one is)
            if m.time_unix_usec > 0:
                self._utc_offset = m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3
                if self.boots[-1]["utc_boot"] is None and int(m.time_boot_ms) >= self._newest - self.reboot_back_ms:
                    self.boots[-1]["utc_boot"] = self._utc_offset
            return None, out
        if typ not in ("GLOBAL_POSITION_INT", "NAMED_VALUE_FLOAT"):
            return None, out
        tb = int(m.time_boot_ms)
        rb = self._check_reboot(tb)  # before any early return: a reboot's first fix has no position yet
        rx = getattr(m, "_timestamp", None)
        if typ == "GLOBAL_POSITION_INT":
            if not (m.lat == 0 and m.lon == 0):  # 0/0: no GPS fix yet
                self.track.add(tb, m.lat / 1e7, m.lon / 1e7)
        else:
            name = _name(m)
            if name not in (self.u_name, self.v_name):
                return rb, out
            key = (tb, name)
            if key in self._seen:
                self.counts["duplicates"] += 1
                return rb, out
            self._seen[key] = None
            r = self.pairer.add("u" if name == self.u_name else "v", tb, float(m.value))
            if r is not None:
                self._count("readings", self.leg)
                self._held[r.t_ms] = (r.u, r.v, rx, self.leg)
        out += self._place()
        self._expire()
        return rb, out

    def flush(self) -> list[dict]:
        """Decide every held reading now (end of a mission: no later fix will come); returns the records.

        Records are also passed to ``on_sample``. A reading the current fixes cannot place is dropped (``gap``).
        """
        with self._lock:
            out = self._place(final=True)
        for rec in out:
            self.on_sample(rec)
        return out

    def held(self, leg: int | None = None) -> int:
        """Readings waiting for the fix after them (of leg ``leg``, or all when None)."""
        with self._lock:
            return sum(1 for x in self._held.values() if leg is None or x[3] == leg)

    def wait_placed(self, leg: int | None, timeout: float) -> bool:
        """Wait up to ``timeout`` wall seconds until no reading of ``leg`` waits for a fix; True if none does.
        On a lockstep link (:class:`~passt_mav.mavlink.link.Lockstep`) the vehicle's clock steps meanwhile."""
        deadline = Timeout(self.clock, timeout)
        link = self._link
        while self.held(leg):
            if deadline.expired():
                return False
            if link is not None:
                link.idle(0.02)
            else:
                self.clock.sleep(0.02)
        return True

    def leg_counts(self, leg: int | None) -> dict[str, int]:
        """``readings``, ``emitted`` and ``gap`` of the readings that arrived while :attr:`leg` was ``leg``."""
        with self._lock:
            return {k: int(self._leg_counts.get((leg, k), 0)) for k in ("readings", "emitted", "gap")}

    # -- internals (lock held) ------------------------------------------------------------------
    def _check_reboot(self, tb: int) -> tuple[int, int, int] | None:
        """Returns ``(boot, last_tb_ms, first_tb_ms)`` when ``tb`` starts a new boot, else None."""
        last = self._boot_counter.see(tb)
        if last is not None:
            # vehicle time went back: a reboot (passt_mav.loop.measurement.Rules.reboot_back_s). The old keys
            # would shadow the new boot's readings at the same times.
            self.counts["reboots"] += 1
            self.pairer.clear()
            self._seen.clear()
            for t in list(self._held):  # the old boot's fix after them will never come
                self._count("gap", self._held.pop(t)[3])
            self.track.clear()
            self._newest = tb
            self._utc_offset = None
            self.boots[-1]["last_tb"] = last
            self.boot = self._boot_counter.boot
            self.boots.append({"utc_boot": None, "wall": self.clock.wall(), "last_tb": tb})
            return self.boot, last, tb
        self._newest = max(self._newest, tb)  # (= self._boot_counter.newest)
        self.boots[-1]["last_tb"] = self._newest
        return None

    def _count(self, what: str, leg: int | None) -> None:
        self.counts[what] += 1
        self._leg_counts[(leg, what)] += 1

    def _place(self, final: bool = False) -> list[dict]:
        """Records of the held readings the track now places; drops those it never can."""
        out: list[dict] = []
        for tb in sorted(self._held):
            pos = self.track.at(tb)
            if pos is None and not final and self.track.may_bracket(tb, self._newest):
                continue
            u, v, rx, leg = self._held.pop(tb)
            if pos is None:
                self._count("gap", leg)
                continue
            if self._utc_offset is not None:
                utc = self._utc_offset + tb / 1e3
            else:
                utc = rx if rx is not None else self.clock.wall()
            rec = {
                "time_boot_ms": tb,
                "utc": utc,
                "lat": pos.lat,
                "lon": pos.lon,
                "u": u,
                "v": v,
                "gap_ms": pos.gap_ms,
                "source": self.source,
                "boot": self.boot_base + self.boot,
            }
            if leg is not None:
                rec["leg"] = leg
            self._count("emitted", leg)
            out.append(rec)
        # fixes are kept as long as halves are (a late half may complete an older reading)
        self.track.forget_before(min(self._held, default=self._newest) - self.expire_ms)
        return out

    def _expire(self) -> None:
        self.pairer.expire(self._newest - self.expire_ms)
        self.counts["expired"] = self.pairer.expired
        # keys of duplicates are remembered longer than halves (a reconnect may replay a minute)
        keep = self._newest - 6 * self.expire_ms
        if len(self._seen) > 4096:
            self._seen = {k: None for k in self._seen if k[0] >= keep}
