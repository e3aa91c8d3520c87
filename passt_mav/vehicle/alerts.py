"""The vehicle's own alarms as the live view's alerts: its fence breaches and failsafes (docs/console.md).

:class:`VehicleAlerts` listens on a boat's link (the reader thread) for what the autopilot says about itself:

* FENCE_STATUS with ``breach_status`` set: one ``fence_breach`` alert per breach (the breach's type and
  count; a breach counted while the last is not cleared is a new one too), one ``fence_clear`` when it clears.
  :meth:`VehicleAlerts.request_fence_status` asks for FENCE_STATUS at 1 Hz: the controller's quieted streams
  (``LinkConfig.quiet_other_streams``) would leave only the one a vehicle sends at the moment of a breach;
* STATUSTEXT from the vehicle (its system id) of severity ALERT or worse (<= 1), or WARNING or worse (<= 4)
  whose text names a failsafe, a fence or a breach (ArduPilot's "GCS Failsafe", "Failsafe - Continuing Auto
  Mode", "Fence breach", ...): a ``vehicle_alert``. (CRITICAL alone is not enough: ArduPilot says its
  pre-arm refusals at CRITICAL, "Arm: System not initialised", while the controller retries the arming.) The same text again within :data:`REPEAT_S` wall
  seconds is not repeated.

Mode changes that are not the controller's are reported where they matter, by the leg in flight (a pilot
taking over: :meth:`~passt_mav.vehicle.session.VehicleSession.pause`). Nothing here sends to the vehicle.
"""

from __future__ import annotations

from passt_mav.mavlink.clock import clock_of

__all__ = ["VehicleAlerts", "REPEAT_S"]

#: wall seconds within which the same STATUSTEXT is not reported again
REPEAT_S = 30.0
_WORDS = ("failsafe", "fence", "breach")


class VehicleAlerts:
    """Fence breaches and failsafes on ``link`` to the live view's events, through ``journal`` (a
    :class:`~passt_mav.vehicle.session.Journal`). :meth:`attach` / :meth:`detach` start and stop listening.
    ``clock``: ``() -> wall s`` of the repeat window (default the link's clock's ``now``)."""

    def __init__(self, link, journal, clock=None):
        self.link, self.journal = link, journal
        self.clock = clock_of(link).now if clock is None else clock
        self._breach = 0  # the last FENCE_STATUS breach_status
        self._count = 0  # and its breach_count
        self._said: dict[str, float] = {}

    def attach(self) -> None:
        self.link.add_listener(self.on_message, ("STATUSTEXT", "FENCE_STATUS"))

    def request_fence_status(self) -> None:
        """FENCE_STATUS at 1 Hz of the vehicle's time, asked for again after a reboot or a reconnect
        (:meth:`~passt_mav.mavlink.Link.keep_stream`); a vehicle whose fence is disabled sends none."""
        self.link.keep_stream("FENCE_STATUS", 1.0)

    def detach(self) -> None:
        self.link.remove_listener(self.on_message)

    def on_message(self, m) -> None:
        """One STATUSTEXT or FENCE_STATUS (from the reader thread)."""
        target = self.link.target_system
        if target is not None and m.get_srcSystem() != target:
            return  # another ground station's text, or our own echoed by a router
        if m.get_type() == "FENCE_STATUS":
            self._fence(m)
        else:
            self._statustext(m)

    def _fence(self, m) -> None:
        breach, count = int(m.breach_status), int(m.breach_count)
        if breach and (not self._breach or count > self._count):
            kinds = {0: "none", 1: "minimum", 2: "maximum", 3: "boundary"}
            what = kinds.get(int(m.breach_type), f"type {int(m.breach_type)}")
            self.journal.note(
                "fence_breach",
                f"the vehicle reports a fence breach ({what}, breach {int(m.breach_count)}): its own fence action applies",
            )
        elif not breach and self._breach:
            self.journal.note("fence_clear", "the vehicle is back inside its fence")
        self._breach, self._count = breach, count

    def _statustext(self, m) -> None:
        text = m.text if isinstance(m.text, str) else bytes(m.text).decode("ascii", "replace")
        text, sev = text.rstrip("\x00"), int(m.severity)
        low = text.lower()
        if not (sev <= 1 or (sev <= 4 and any(w in low for w in _WORDS))):
            return
        now = self.clock()
        if now - self._said.get(text, -1e9) < REPEAT_S:
            return
        self._said[text] = now
        self.journal.note("vehicle_alert", f"the vehicle says: {text} (severity {sev})")
