"""How a leg's flow turns: the control-flow exceptions of the vehicle side, in one leaf module.

None of them is an error (each is an outcome or a request the controller expects and handles):

* :class:`Paused` - the vehicle left AUTO and did not come back in time; :class:`LinkWindowOver` (a
  :class:`Paused`): the link stayed lost for the whole link-loss window. The run stops, status ``paused``.
* :class:`Rebooted` - the autopilot rebooted: the leg in flight resumes.
* :class:`Ended` - the operator (or the spent safety budget) ended the mission; status ``ended``.
* :class:`Replan` - plan the leg again from where the boat is.
* :class:`Stopped` - a stop signal arrived (:mod:`~passt_mav.vehicle.signals`); status ``stopped``.
* :class:`MachineFault` (a :class:`Paused`) - the machine failed the run's sample store (disk full, read-only,
  removed: :mod:`~passt_mav.vehicle.machine_faults`); status ``stopped``, ``stopped_by`` what failed.

and :func:`utc_now`, the UTC stamp of the events they cause. This module imports nothing of the project, so
every module of the vehicle side (the session and its mixins, the controller and its mixins) imports it at
the top without a circle; the old homes (``session``, ``console``, ``operator``, ``signals``) re-export them.
"""

from __future__ import annotations

import datetime as _dt
import signal

__all__ = ["Paused", "LinkWindowOver", "MachineFault", "Rebooted", "Ended", "Replan", "Stopped", "utc_now"]


def utc_now() -> str:
    """Now as ISO-8601 UTC, to the second (``2026-01-01T12:00:00Z``)."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


class Paused(Exception):
    """The vehicle left AUTO and did not come back in time (or rebooted with on_reboot: hold)."""


class LinkWindowOver(Paused):
    """The link stayed lost for the whole link-loss window (``vehicle.link_loss_window_s``)."""


class MachineFault(Paused):
    """The machine failed the run's sample store: ``reason``, one line (``disk full: /run/x/samples.sqlite``)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class Rebooted(Exception):
    """The autopilot rebooted: handled by the leg in flight."""


class Ended(Exception):  # noqa: N818 - an outcome, like Paused
    """The operator ended the mission; the vehicle is in ``mode`` (``HOLD`` or ``RTL``) already."""

    def __init__(self, text: str, mode: str):
        super().__init__(text)
        self.mode = mode


class Replan(Exception):  # noqa: N818 - a request, not an error
    """Plan the leg again from where the boat is (:meth:`~passt_mav.vehicle.operator.OperatorLegs._leg`);
    ``status``: what its attempt is called (``replanned by the operator``, ``rejected by the operator``)."""

    def __init__(self, status: str = "replanned by the operator"):
        super().__init__(status)
        self.status = status


class Stopped(BaseException):  # noqa: N818 - like KeyboardInterrupt: not caught by ``except Exception``
    """A stop signal arrived (``signum``; ``name`` e.g. ``SIGTERM``)."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        self.name = signal.Signals(self.signum).name
        super().__init__(f"stopped by {self.name}")
