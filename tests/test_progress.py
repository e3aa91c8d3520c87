"""passt_mav.progress (issue 29 item 3): a tqdm bar on a terminal, plain lines in a log (at most one per
10 % or 30 s, one per second at most), nothing when quiet; and a command's log holds the plain lines."""

from __future__ import annotations

import io
import json

import pytest

from passt_mav import progress as P
from passt_mav.progress import progress


class Clock:
    """A fake time.monotonic that moves only when told."""

    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock(monkeypatch):
    c = Clock()
    monkeypatch.setattr(P.time, "monotonic", c)
    return c


class FakeTTY(io.StringIO):
    def isatty(self) -> bool:
        return True


def lines(buf: io.StringIO) -> list[str]:
    return buf.getvalue().splitlines()


def test_plain_lines_every_10_percent_with_eta(clock):
    buf = io.StringIO()
    for _ in progress(range(50), "work", "item", stream=buf):
        clock.t += 2.0  # 2 s an item: every line passes the 1 s floor
    out = lines(buf)
    assert out[0] == "work: 0/50 items"
    # 10 %, 20 % ... 90 % (the 100 % line is the closing one)
    assert [ln.split("(")[1].split(")")[0] for ln in out[1:-1]] == [f"{p} %" for p in range(10, 100, 10)]
    assert out[1] == "work: 5/50 items (10 %), 10 s elapsed, ETA 90 s"
    assert out[-1] == "work: 50/50 items done in 100 s"
    assert len(out) == 11


def test_fast_work_never_floods_the_log(clock):
    buf = io.StringIO()
    for _ in progress(range(100000), "fast", "item", stream=buf):
        clock.t += 1e-6  # 0.1 s in all: below the one-line-per-second floor
    assert len(lines(buf)) == 2


def test_slow_work_gets_a_line_every_30_s(clock):
    buf = io.StringIO()
    with progress(1000, "slow", "trial", stream=buf) as p:
        for _ in range(10):  # 1 % per 31 s: the 30 s rule, not the 10 % one
            clock.t += 31.0
            p.update()
    out = lines(buf)
    assert len(out) == 1 + 10 + 1 and "10/1000 trials (1 %)" in out[-2]
    assert out[-2].endswith("5.2 min elapsed, ETA 8.5 h")


def test_unknown_length_reports_elapsed_time_with_its_note(clock):
    buf = io.StringIO()
    p = progress(None, "waiting for the vehicle", "s", stream=buf, every_s=5.0)
    for _ in range(12):
        clock.t += 1.0
        p.note("EKF has no position")
        p.tick()
    p.close("ready")
    out = lines(buf)
    assert out[0] == "waiting for the vehicle: started"
    assert out[1:3] == [
        "waiting for the vehicle: 5 s elapsed (EKF has no position)",
        "waiting for the vehicle: 10 s elapsed (EKF has no position)",
    ]
    assert out[-1] == "waiting for the vehicle: ready (EKF has no position)" and len(out) == 4


def test_a_terminal_gets_a_tqdm_bar_not_lines(monkeypatch):
    import sys

    tty = FakeTTY()
    monkeypatch.setattr(sys, "stderr", tty)  # the default stream, judged by its isatty()
    p = progress(range(20), "train", "epoch")
    assert p.tty and p._bar is not None
    for _ in p:
        p.note("loss 1.0e-03")
    text = tty.getvalue()
    assert "\r" in text and "train" in text and "epoch" in text  # tqdm redraws the line in place
    assert "0/20 epochs" not in text.replace("\r", "\n").splitlines()[0:1]  # no plain start line
    assert "done in" not in text


def test_not_a_terminal_is_judged_by_isatty(monkeypatch):
    import sys

    buf = io.StringIO()  # isatty() False
    monkeypatch.setattr(sys, "stderr", buf)
    p = progress(3, "x", "it")
    assert not p.tty and p._bar is None
    p.close()
    assert lines(buf) == ["x: 0/3 it", "x: 0/3 it done in 0 s"]


def test_quiet_shows_nothing_on_either(monkeypatch):
    for stream in (io.StringIO(), FakeTTY()):
        for _ in progress(range(5), "q", "it", quiet=True, stream=stream):
            pass
        assert stream.getvalue() == ""


def test_evaluate_writes_plain_progress_lines_to_a_log(tmp_path, capsys):
    """`passt-mav evaluate` with stderr not a terminal (captured): plain lines, no carriage returns."""
    from test_evaluate import make_field

    from passt_mav.cli import main

    nc = make_field(T=30).to_netcdf(tmp_path / "synth.nc")
    rc = main(
        [
            "evaluate",
            "--data",
            str(nc),
            "--model",
            "persistence",
            "--trials",
            "2",
            "--path-lengths",
            "10,20",
            "--steps",
            "20",
            "--json",
            "--out",
            str(tmp_path / "eval"),
        ]
    )
    out, err = capsys.readouterr()
    assert rc == 0 and json.loads(out)["out"]
    plain = [ln for ln in err.splitlines() if ln.startswith("evaluate: ")]
    assert plain[0] == "evaluate: 0/4 trials" and plain[-1].startswith("evaluate: 4/4 trials done in ")
    assert "\r" not in err
