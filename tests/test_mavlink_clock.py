"""The vehicle side's one clock: a link owns it, its users ask it; lockstep budgets and speed-up conversions."""

from __future__ import annotations

import pytest

from passt_mav.mavlink import Link, LinkConfig
from passt_mav.mavlink.clock import SYSTEM_CLOCK, Clock, StepBudget, Timeout, clock_of, vehicle_seconds, wall_seconds
from passt_mav.mavlink.samples import SampleCollector
from passt_mav.vehicle.alerts import REPEAT_S, VehicleAlerts
from passt_mav.vehicle.session import Deadline


class FakeClock:
    """A clock that moves only when told (``sleep`` moves it too)."""

    def __init__(self, t: float = 1000.0):
        self.t, self.slept = t, []

    def now(self) -> float:
        return self.t

    def wall(self) -> float:
        return 1.7e9 + self.t

    def wall_ns(self) -> int:
        return int(self.wall() * 1e9)

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.t += seconds


def test_a_link_owns_one_clock_and_its_waits_ask_it():
    """Without lockstep ``Link.idle`` sleeps on the link's clock; the time since the last heartbeat is counted on it."""
    clock = FakeClock()
    link = Link(LinkConfig(), clock=clock)
    assert isinstance(clock, Clock) and link.clock is clock and clock_of(link) is clock
    assert Link(LinkConfig()).clock is SYSTEM_CLOCK
    link.idle(0.25)
    assert clock.slept == [0.25]
    assert link.seconds_since_heartbeat == float("inf")
    collector = SampleCollector(lambda r: None, clock=clock)
    assert collector.boots[0]["wall"] == clock.wall()
    assert collector.wait_placed(None, 5.0)  # nothing held: no wait at all
    assert clock.slept == [0.25]


def test_timeout_counts_wall_seconds_on_its_clock():
    clock = FakeClock(10.0)
    t = Timeout(clock, 2.0)
    assert (t.t0, t.end, t.left(), t.expired()) == (10.0, 12.0, 2.0, False)
    clock.t = 12.0
    assert t.left() == 0.0 and t.expired() and t.elapsed() == 2.0


def test_a_lockstep_wait_counts_the_vehicle_seconds_it_stepped():
    """A wait of 2 wall s at a pace of 50 may step 100 vehicle s, whatever the wall clock says; None: no bound."""
    b = StepBudget(2.0, 50.0)
    assert b.budget == 100.0 and not b.spent()
    for _ in range(199):
        b.stepped(0.5)
    assert not b.spent()
    b.stepped(0.5)
    assert b.spent()
    assert StepBudget(None, 50.0).budget == float("inf") and StepBudget(-1.0, 50.0).budget == 0.0


@pytest.mark.parametrize(
    "vehicle_s, speedup, at_least, want",
    [(600.0, 20.0, 0.0, 30.0), (3.0, 100.0, 0.3, 0.3), (120.0, 2.0, 30.0, 60.0), (1.0, 0.0, 0.0, 1e6)],
)
def test_speedup_conversions(vehicle_s, speedup, at_least, want):
    assert wall_seconds(vehicle_s, speedup, at_least=at_least) == pytest.approx(want)
    assert vehicle_seconds(2.5, 20.0) == 50.0


def test_the_leg_backstop_runs_on_the_links_clock():
    """:class:`Deadline` asks the link's clock: a vehicle clock that stops fires the backstop after
    ``STALL_WALL_S`` of that clock, with no patching of the time module."""

    class FakeLink:
        up = 50.0

        def __init__(self, clock):
            self.clock = clock

        def vehicle_uptime_s(self):
            return self.up

    clock = FakeClock()
    link = FakeLink(clock)
    d = Deadline(link, budget_s=60.0, speedup=20.0)
    assert d.clock is clock
    clock.t += 100.0
    link.up = 60.0  # the vehicle's clock moves: progress
    assert not d.passed()
    clock.t += Deadline.STALL_WALL_S + 1.0  # then stands still
    assert d.wall_passed() and d.stalled_s == Deadline.STALL_WALL_S + 1.0


def test_vehicle_alerts_repeat_window_on_the_links_clock():
    from types import SimpleNamespace

    clock = FakeClock()
    notes = []
    journal = SimpleNamespace(note=lambda kind, text: notes.append(kind))
    link = SimpleNamespace(target_system=None, clock=clock)
    va = VehicleAlerts(link, journal)
    msg = SimpleNamespace(get_srcSystem=lambda: 1, get_type=lambda: "STATUSTEXT", text="GCS Failsafe", severity=2)
    va.on_message(msg)
    va.on_message(msg)
    clock.t += REPEAT_S
    va.on_message(msg)
    assert notes == ["vehicle_alert", "vehicle_alert"]
