"""`passt-mav demo` stopped by SIGTERM: exit 143, its vehicle-sim child stopped, summary.json ``stopped``.

A supervisor (systemd, a CI job's timeout, a shell's ``kill``) ends a demo with SIGTERM to the demo's own
process only. Before, the demo died at once (its default SIGTERM action), summary.json was left ``running`` or
never written, and the vehicle-sim child it had started went on listening. Whether the signal comes while
the simulator starts or while a leg flies, the child must be gone when the demo exits.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.long(reason="two demo subprocesses stopped by SIGTERM, ~30 s wall on two cores")

WALL_S = 120.0  # a bound on each wait, far above what it takes (the demo flies in lockstep)


def _start(out):
    return subprocess.Popen(
        [sys.executable, "-m", "passt_mav.cli", "demo", "--legs", "2", "--out", str(out), "--no-report", "--no-view"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def _read_until(proc, pattern: str) -> re.Match:
    """Lines of the demo's output until one matches ``pattern`` (its match)."""
    end = time.monotonic() + WALL_S
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            break
        if m := re.search(pattern, line):
            return m
    raise AssertionError(f"the demo never printed {pattern!r}")


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.parametrize("when", ["starting", "flying"])
def test_sigterm_stops_the_demo_and_its_simulator(tmp_path, when):
    out = tmp_path / "demo"
    proc = _start(out)
    try:
        port = int(_read_until(proc, r"starting vehicle-sim on tcp:127\.0\.0\.1:(\d+)").group(1))
        if when == "flying":
            _read_until(proc, r"^leg 1/2")  # a leg's progress: the mission has begun
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=WALL_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, rest
    assert not _listening(port), "vehicle-sim is still listening after the demo exited"
    if when == "flying":
        summary = json.loads((out / "summary.json").read_text())
        assert summary["status"] == "stopped"
        assert "demo: stopped after" in rest
    else:
        assert "before the mission began" in rest
