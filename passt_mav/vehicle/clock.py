"""One boat's clock for a run: the vehicle's time since boot -> field time, across reboots and resumes.

The rules are in :mod:`passt_mav.vehicle.controller`'s docstring ("Clock"): a :class:`RunClock` chooses
``t_boot0`` once the vehicle is ready (:meth:`RunClock.choose`: ``utc``, ``boot`` or ``auto``),
keeps a ``t_boot0`` for every later boot (:meth:`RunClock.with_boots`, from the
:class:`~passt_mav.mavlink.SampleCollector`'s boots) and, on ``--resume``, takes the boots of the
earlier sessions from the sample store and the old summary (:meth:`RunClock.resume_boots`,
:meth:`RunClock.restore`).
"""

from __future__ import annotations

import datetime as _dt
from typing import TYPE_CHECKING

from passt_mav.errors import MavlinkError, UserError
from passt_mav.loop.legstep import FieldClock, utc_epoch
from passt_mav.loop.measurement import RULES
from passt_mav.mavlink.clock import Timeout, wall_seconds

if TYPE_CHECKING:
    from passt_mav.mavlink.samples import SampleCollector

__all__ = ["RunClock"]


class RunClock:
    """Vehicle time -> field time for one boat (module docstring).

    Args:
        field: the mission's field (times, time origin).
        field_config: the mission's ``field:`` (``clock``, ``time_scale`` in seconds per field time unit).
        link: the boat's :class:`~passt_mav.mavlink.Link` (SYSTEM_TIME, time since boot).
        journal: :class:`~passt_mav.vehicle.session.Journal` (what the clock chose, and why).
        t_boot0: field time at vehicle boot until :meth:`choose` (``field.times[t0]`` or ``--field-time-at-boot``).
        forced: ``--field-time-at-boot`` was given (the clock is not chosen from the vehicle's UTC).
        speedup: simulated / wall seconds of the vehicle.
    """

    def __init__(self, field, field_config, link, journal, *, t_boot0: float, forced: bool, speedup: float):
        self.field, self.link, self.journal = field, link, journal
        self.mode = getattr(field_config, "clock", "auto")
        self.clock = FieldClock(float(t_boot0), float(field_config.time_scale))
        self.forced = bool(forced)
        #: the clock came from the run being resumed (a boot clock cannot be read again from the vehicle)
        self.fixed = False
        self.speedup = max(float(speedup), 1e-6)
        #: the SampleCollector counting this session's boots (set when it is attached)
        self.collector: SampleCollector | None = None
        # resume: samples of earlier sessions keep their boot numbers; this session's boots count from
        # boot_base (so a vehicle rebooted while we were away cannot reuse their keys), and
        # old_anchors holds t_boot0 of boots 0..boot_base-1 (from the old summary)
        self.boot_base = 0
        self.old_anchors: list[float] = []
        #: (last time_boot_ms stored, uptime s now) when the vehicle rebooted while no controller ran
        self.rebooted_since: tuple[int, float] | None = None

    # -- choosing ---------------------------------------------------------------------------------
    def choose(self) -> None:
        """Set :attr:`clock` once the vehicle is ready (the controller's docstring, "Clock")."""
        if self.forced or self.fixed or self.mode == "boot":
            self.say()
            return
        why = self._try_utc()
        if why is None:
            self.say()
            return
        if self.mode == "utc":
            raise UserError(
                f"field.clock is utc but {why}; set field.clock: boot (or give --field-time-at-boot) "
                "to map the vehicle's time since boot instead"
            )
        self.journal.say(f"clock: {why}; field time at vehicle boot = snapshot t0 ({self.clock.t_boot0:g})")
        self.journal.events.append(f"clock: boot ({why})")

    def _try_utc(self) -> str | None:
        """Set a UTC clock from the vehicle's SYSTEM_TIME; None when set, else why not."""
        origin, scale = self.field.time_origin, self.clock.time_scale
        if origin is None:
            return "the field has no UTC time origin"
        # SYSTEM_TIME comes at 1 Hz of vehicle time by default (0.2 Hz in LEAN_STREAMS)
        utc_boot = self._vehicle_utc_boot(wall_seconds(6.0, self.speedup, at_least=1.0))
        if utc_boot is None:
            return "the vehicle sends no UTC (SYSTEM_TIME time_unix_usec = 0)"
        t_boot0 = (utc_boot - utc_epoch(origin)) / scale
        up = self.link.vehicle_uptime_s() or 0.0
        t_now = t_boot0 + up / scale
        times = self.field.times
        if not times[0] <= t_now <= times[-1]:
            when = _dt.datetime.fromtimestamp(utc_boot + up, _dt.UTC).isoformat(timespec="seconds")
            return (
                f"the vehicle's UTC {when} lies outside the field's snapshots ({origin} + "
                f"{times[0]:g}..{times[-1]:g} s)"
            )
        self.clock = FieldClock(float(t_boot0), scale, source="utc")
        return None

    def _vehicle_utc_boot(self, timeout: float) -> float | None:
        """The vehicle's UTC at boot (SYSTEM_TIME ``time_unix_usec/1e6 - time_boot_ms/1e3``), None without one."""
        deadline = Timeout(self.link.clock, timeout)
        while True:
            st = self.link.latest("SYSTEM_TIME")
            if st is not None and st.time_unix_usec > 0:
                return st.time_unix_usec / 1e6 - st.time_boot_ms / 1e3
            if deadline.expired():
                return None
            self.link.idle(0.02)

    def say(self) -> None:
        c = self.clock
        up = self.link.vehicle_uptime_s()
        now = "" if up is None else f", now {float(c.field_time(up * 1000.0)):.1f}"
        self.journal.say(f"clock: {c.source}; field time at vehicle boot {c.t_boot0:.1f}{now}")

    # -- resume --------------------------------------------------------------------------------------
    def resume_boots(self, recs, old_clock: dict) -> None:
        """On resume: boot numbering and earlier boots' anchors from the stored samples ``recs`` and the old
        summary's ``clock``."""
        if not recs:
            return
        b_last = max(int(r.boot or 0) for r in recs)
        tb_last = max(int(r.time_boot_ms) for r in recs if int(r.boot or 0) == b_last)
        anchors = [float(old_clock.get("t_boot0", self.clock.t_boot0))]
        anchors += [float(x) for x in old_clock.get("later_boots") or []]
        anchors += [anchors[-1]] * (b_last + 1 - len(anchors))  # boots the old summary never recorded
        self.old_anchors = anchors[: b_last + 1]
        self.boot_base = b_last + 1
        up = self.link.vehicle_uptime_s()
        if up is not None and up * 1000.0 + RULES.reboot_back_ms < tb_last:  # the measurement rules' reboot
            self.rebooted_since = (tb_last, up)
            self.journal.events.append(
                f"resume: the vehicle rebooted since the run stopped (uptime {up:.0f} s, "
                f"last sample at {tb_last / 1000:.0f} s)"
            )

    def restore(self, old_clock: dict) -> None:
        """On resume: keep the old run's boot clock (a UTC clock is read again from the vehicle), for the boot
        the vehicle was on when the run stopped (see :meth:`resume_boots`)."""
        if "t_boot0" not in old_clock or old_clock.get("source", "boot") != "boot":
            return
        t_boot0 = self.old_anchors[-1] if self.old_anchors else float(old_clock["t_boot0"])
        if self.rebooted_since is not None:
            tb_last, _ = self.rebooted_since
            # no clock to tell how long it was off: continue from the last sample (the gap is not counted)
            t_boot0 += tb_last / 1000.0 / self.clock.time_scale
            self.journal.say(
                f"WARNING: the vehicle rebooted since the run stopped and the mission maps time since "
                f"boot: field time continues from the last sample ({t_boot0:.1f}); the time it was "
                "off is not counted"
            )
        self.clock = FieldClock(t_boot0, float(old_clock.get("time_scale", self.clock.time_scale)))
        self.fixed = True

    # -- reading ---------------------------------------------------------------------------------------
    def with_boots(self) -> FieldClock:
        """:attr:`clock` with a ``t_boot0`` for every boot (earlier sessions', then the collector's)."""
        boots = list(self.collector.boots) if self.collector is not None else []
        if len(boots) <= 1 and not self.old_anchors:
            return self.clock
        full = self.old_anchors + self._session_anchors(boots)
        return FieldClock(full[0], self.clock.time_scale, self.clock.source, tuple(full[1:]))

    def _session_anchors(self, boots: list[dict]) -> list[float]:
        """``t_boot0`` of each boot this session has seen (the first is :attr:`clock`'s)."""
        if len(boots) <= 1:
            return [self.clock.t_boot0]
        c, scale = self.clock, self.clock.time_scale
        anchors = [c.t_boot0]
        for k in range(1, len(boots)):
            b0, bk = boots[0].get("utc_boot"), boots[k].get("utc_boot")
            if c.source == "utc" and bk is not None and self.field.time_origin is not None:
                anchors.append((bk - utc_epoch(self.field.time_origin)) / scale)
            elif b0 is not None and bk is not None:
                anchors.append(c.t_boot0 + (bk - b0) / scale)
            else:
                # no clock on the vehicle: continue from the last time seen (the down time is not counted)
                prev = boots[k - 1]
                anchors.append(anchors[-1] + (prev["last_tb"] - boots[k].get("first_tb", 0)) / 1000.0 / scale)
        return anchors

    def boot(self) -> int:
        """The run's number of the boot the vehicle is on."""
        return self.boot_base + (self.collector.boot if self.collector is not None else 0)

    def reading(self) -> tuple[int, int]:
        """The vehicle's newest ``time_boot_ms`` and the run's boot number it belongs to."""
        up = self.link.vehicle_uptime_s()
        if up is None:
            raise MavlinkError("no vehicle time (time_boot_ms) received yet")
        return int(round(up * 1000.0)), self.boot()

    def field_time_now(self) -> float | None:
        """The field time the vehicle's clock says now (None before its first time stamp)."""
        up = self.link.vehicle_uptime_s()
        if up is None:
            return None
        return round(float(self.with_boots().field_time(up * 1000.0, self.boot())), 3)
