"""Current samples from telemetry: NAMED_VALUE_FLOAT u/v paired with the position fix.

The boat's Lua script sends ``gcs:send_named_float("CUR_U", u)`` and ``("CUR_V", v)``
(m/s, east/north; shared/ARDUPILOT_ROVER.md). Each NAMED_VALUE_FLOAT carries the
autopilot's ``time_boot_ms``; the sample's position is the GLOBAL_POSITION_INT with
the same ``time_boot_ms`` (or the nearest one within ``tolerance_ms``).

:class:`SampleCollector` emits one record the moment the u half, the v half and a
position are all there; halves seen twice (retransmission, a reconnect replaying
a buffer, two links) are dropped; halves that never find their partner expire
after ``expire_ms`` of vehicle time. Records go to ``on_sample(record)``:

``{"time_boot_ms": int, "utc": float (epoch s), "lat": deg, "lon": deg, "u": m/s,
"v": m/s, "source": str, "boot": int}`` plus ``"leg"`` when :attr:`SampleCollector.leg` is set.

UTC comes from SYSTEM_TIME (``time_unix_usec - time_boot_ms``); before the vehicle
has GPS time, from the wall clock at receipt.

Reboots. ``time_boot_ms`` going back by more than ``reboot_back_ms`` is a reboot of the
autopilot: the collector forgets its keys (the new boot reuses the old times), counts
:attr:`SampleCollector.boot` up and gives later records ``"boot": n`` (the store keys
samples by ``(source, boot, time_boot_ms)``, so the new boot's readings are not duplicates).
:attr:`SampleCollector.boots` keeps per boot the vehicle's UTC at boot (when known) and
the wall time the boot was first seen; ``on_reboot(boot, last_tb_ms, first_tb_ms)`` is
called from the reader thread.
"""

from __future__ import annotations

import bisect
import collections
import threading
import time
from typing import Callable

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
        tolerance_ms: largest |time_boot_ms difference| between a reading and its position.
        expire_ms: drop unmatched halves / positions older than this (vehicle time).
        source: the record's ``source`` field (e.g. "mavlink:tcp:127.0.0.1:5760").
        reboot_back_ms: ``time_boot_ms`` going back by more than this is a reboot.
        on_reboot: ``(boot, last_tb_ms, first_tb_ms)`` callback on a reboot (reader thread).
        boot_base: added to the boot number in records (a resumed run continues the stored numbering).
    """

    TYPES = ("NAMED_VALUE_FLOAT", "GLOBAL_POSITION_INT", "SYSTEM_TIME")

    def __init__(self, on_sample: Callable[[dict], None], *, u_name: str = "CUR_U", v_name: str = "CUR_V",
                 tolerance_ms: int = 100, expire_ms: int = 10_000, source: str = "mavlink",
                 reboot_back_ms: int = 3000, on_reboot: Callable[[int, int, int], None] | None = None,
                 boot_base: int = 0):
        if u_name == v_name:
            raise ValueError("u_name and v_name must differ")
        self.on_sample = on_sample
        self.u_name, self.v_name = u_name, v_name
        self.tolerance_ms, self.expire_ms = int(tolerance_ms), int(expire_ms)
        self.source = source
        self.leg: int | None = None
        self._lock = threading.Lock()
        self._halves: dict[int, dict[str, float]] = {}       # time_boot_ms -> {"u": .., "v": ..}
        self._seen: dict[tuple[int, str], None] = {}         # (time_boot_ms, name) already taken
        self._emitted: set[int] = set()
        self._pos_t: list[int] = []                          # sorted time_boot_ms of recent fixes
        self._pos: dict[int, tuple[float, float]] = {}
        self._utc_offset: float | None = None                # unix s - boot s
        self._newest = 0
        self.counts = collections.Counter()                  # emitted, duplicates, expired, reboots
        self._link = None
        self.reboot_back_ms = int(reboot_back_ms)
        self.on_reboot = on_reboot
        self.boot = 0                                        # reboots seen since attach
        self.boot_base = int(boot_base)                      # records carry boot_base + boot
        #: per boot: {"utc_boot": vehicle UTC at boot (s) or None, "wall": wall time first seen, "last_tb": ms}
        self.boots: list[dict] = [{"utc_boot": None, "wall": time.time(), "last_tb": 0}]

    # -- wiring ------------------------------------------------------------------------------
    def attach(self, link) -> "SampleCollector":
        """Listen on a :class:`~passt_mav.mavlink.link.Link` (reader thread)."""
        self._link = link
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
        if typ == "GLOBAL_POSITION_INT":
            if m.lat == 0 and m.lon == 0:
                return rb, out  # no GPS fix yet
            if tb not in self._pos:
                bisect.insort(self._pos_t, tb)
            self._pos[tb] = (m.lat / 1e7, m.lon / 1e7)
            # readings waiting for a position near this one
            for t in [t for t in self._halves if abs(t - tb) <= self.tolerance_ms]:
                out += self._try_emit(t, getattr(m, "_timestamp", None))
        else:
            name = _name(m)
            if name not in (self.u_name, self.v_name):
                return rb, out
            key = (tb, name)
            if key in self._seen or tb in self._emitted:
                self.counts["duplicates"] += 1
                return rb, out
            self._seen[key] = None
            self._halves.setdefault(tb, {})["u" if name == self.u_name else "v"] = float(m.value)
            out += self._try_emit(tb, getattr(m, "_timestamp", None))
        self._expire()
        return rb, out

    # -- internals (lock held) ------------------------------------------------------------------
    def _check_reboot(self, tb: int) -> tuple[int, int, int] | None:
        """Returns ``(boot, last_tb_ms, first_tb_ms)`` when ``tb`` starts a new boot, else None."""
        if self._newest - tb > self.reboot_back_ms:
            # vehicle time went back: a reboot (a link delivers in order; a few seconds back is no
            # reordering). The old keys would shadow the new boot's readings at the same times.
            last = self._newest
            self.counts["reboots"] += 1
            self._halves.clear(), self._seen.clear(), self._emitted.clear(), self._pos.clear()
            self._pos_t.clear()
            self._newest = tb
            self._utc_offset = None
            self.boots[-1]["last_tb"] = last
            self.boot += 1
            self.boots.append({"utc_boot": None, "wall": time.time(), "last_tb": tb})
            return self.boot, last, tb
        self._newest = max(self._newest, tb)
        self.boots[-1]["last_tb"] = self._newest
        return None

    def _nearest_pos(self, tb: int) -> tuple[float, float] | None:
        i = bisect.bisect_left(self._pos_t, tb)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(self._pos_t) and abs(self._pos_t[j] - tb) <= self.tolerance_ms:
                if best is None or abs(self._pos_t[j] - tb) < abs(best - tb):
                    best = self._pos_t[j]
        return None if best is None else self._pos[best]

    def _try_emit(self, tb: int, rx_time: float | None) -> list[dict]:
        h = self._halves.get(tb)
        if h is None or "u" not in h or "v" not in h:
            return []
        pos = self._nearest_pos(tb)
        if pos is None:
            return []
        del self._halves[tb]
        self._emitted.add(tb)
        if self._utc_offset is not None:
            utc = self._utc_offset + tb / 1e3
        else:
            utc = rx_time if rx_time is not None else time.time()
        rec = {"time_boot_ms": tb, "utc": utc, "lat": pos[0], "lon": pos[1], "u": h["u"], "v": h["v"],
               "source": self.source, "boot": self.boot_base + self.boot}
        if self.leg is not None:
            rec["leg"] = self.leg
        self.counts["emitted"] += 1
        return [rec]

    def _expire(self) -> None:
        old = self._newest - self.expire_ms
        for t in [t for t in self._halves if t < old]:
            del self._halves[t]
            self.counts["expired"] += 1
        cut = bisect.bisect_left(self._pos_t, old)
        for t in self._pos_t[:cut]:
            del self._pos[t]
        del self._pos_t[:cut]
        # keys of duplicates are remembered longer than halves (a reconnect may replay a minute)
        keep = self._newest - 6 * self.expire_ms
        if len(self._seen) > 4096:
            self._seen = {k: None for k in self._seen if k[0] >= keep}
            self._emitted = {t for t in self._emitted if t >= keep}
