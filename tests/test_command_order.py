"""The operator's commands are taken in the order given, whenever they arrive, in every wait.

Two cases an operator met on the live page: Pause and Resume clicked a second apart, both read in one turn of
the controller (the Resume was dropped while the controller waited in the Pause, which then timed out and
stopped the run); and a Resume sent while a pilot held the boat out of AUTO (never read: the pilot's wait did
not look at the page).
"""

from __future__ import annotations

import threading
import time

from test_console import AUTO, LOITER, WALL_S, _answer, _flying, lockstep_session

from passt_mav.mavlink.vehicle import ROVER_MODES
from passt_mav.runs.commands import CommandReader, append_command
from passt_mav.runs.live import read_events

MANUAL = ROVER_MODES["MANUAL"]


def test_the_reader_hands_out_commands_one_at_a_time_and_keeps_the_rest(tmp_path):
    for action in ("pause", "resume", "skip"):
        append_command(tmp_path, {"boat": 0, "action": action}, source="test")
    append_command(tmp_path, {"boat": 1, "action": "end"}, source="test")  # another boat's
    reader = CommandReader(tmp_path, 0, skip_existing=False)
    for cmd in reader.take():  # a caller that acts on the pause and waits in it ...
        assert cmd["action"] == "pause"
        inner = [c["action"] for c in reader.take()]  # ... takes the resume (and the rest) from the same queue
        break
    assert inner == ["resume", "skip"]
    append_command(tmp_path, {"boat": "all", "action": "end"}, source="test")
    taken = reader.take()
    assert next(taken)["action"] == "end"
    append_command(tmp_path, {"boat": 0, "action": "replan"}, source="test")
    # a caller that stops early leaves the rest for the next wait, in order; poll() hands them out first
    assert [c["action"] for c in reader.poll()] == ["replan"]


def _send_when(ctl, cond, cmds: list[dict], root, sent: list) -> threading.Thread:
    """From a thread: ``cmds`` appended back to back once ``cond(ctl)`` holds (their records into ``sent``)."""

    def run():
        end = time.monotonic() + WALL_S
        while time.monotonic() < end:
            if cond(ctl):
                sent.extend(append_command(root, c, source="test") for c in cmds)
                return
            time.sleep(0.002)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_a_resume_sent_right_after_its_pause_resumes_it(tmp_path):
    with lockstep_session(tmp_path) as (_sim, make, rd):
        ctl = make(legs=2, pause_timeout_s=WALL_S)
        sent: list[dict] = []
        th = _send_when(ctl, _flying, [{"boat": 0, "action": "pause"}, {"boat": 0, "action": "resume"}], rd.root, sent)
        summary = ctl.run()
        th.join(5)
    assert summary["status"] == "complete" and len(summary["legs"]) == 2
    answers = [_answer(rd.root, r["id"]) for r in sent]
    assert [a["level"] for a in answers] == ["ok", "ok"], answers
    assert "paused: LOITER" in answers[0]["text"] and "resumed: AUTO" in answers[1]["text"]


def test_a_resume_from_the_page_ends_a_pilots_hold(tmp_path):
    with lockstep_session(tmp_path) as (sim, make, rd):
        ctl = make(legs=2, pause_timeout_s=WALL_S)
        ap = sim.autopilot

        def piloted(c) -> bool:  # a pilot switched to MANUAL mid-leg and the controller noticed it
            if _flying(c) and ap.mode == AUTO:
                ap.set_mode(MANUAL)
            return any(e.get("kind") == "pilot_takeover" for e in read_events(rd.root)[0])

        sent: list[dict] = []
        th = _send_when(ctl, piloted, [{"boat": 0, "action": "resume"}], rd.root, sent)
        summary = ctl.run()
        th.join(5)
    assert summary["status"] == "complete" and len(summary["legs"]) == 2
    (ans,) = [_answer(rd.root, r["id"]) for r in sent]
    assert ans["level"] == "ok" and "resumed: AUTO" in ans["text"], ans
    assert any("back in AUTO" in e for e in summary["events"])
    assert sim.autopilot.mode == LOITER  # the run's end: the boat keeps station (vehicle.on_end: loiter)
