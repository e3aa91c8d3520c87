"""No traceback from any ``passt-mav`` command on a network or file error (issue 28, item 2).

Each command that takes a connection or a path is walked with a bad one: the command must end
with exit code 2 and exactly one line on stderr, ``passt-mav: error: ...``, naming the address or
path. ``run`` retries a vehicle it cannot reach with back-off until ``--ready-timeout``, one line
per attempt naming the address, for each way of not reaching it: refused, unknown host,
unreachable, no answer, no such serial device, and a port where something else listens (silent,
or talking another protocol).
"""

from __future__ import annotations

import errno
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from simclient import free_port

from passt_mav.cli import main

REPO = Path(__file__).resolve().parent.parent
MISSION = str(REPO / "missions" / "north_atlantic.yaml")
FAST = ("--set", "model=persistence", "--set", "gp.background=0", "--no-report")


def _one_line_exit_2(capsys, argv, *needles):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert rc == 2, (out, err)
    lines = err.strip().splitlines()
    # one error line, the last; before it at most a command's own notes (e.g. plan's "note: ...")
    assert lines and lines[-1].startswith("passt-mav: error: "), err
    assert all(ln.startswith("note: ") for ln in lines[:-1]), err
    for n in needles:
        assert n in lines[-1], (n, lines[-1])
    assert "Traceback" not in out + err
    return out, lines[-1]


class _Server:
    """A TCP server on 127.0.0.1 that accepts and then stays silent or sends ``reply`` forever."""

    def __init__(self, reply: bytes = b""):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.port = self.sock.getsockname()[1]
        self.reply, self.conns, self.stop = reply, [], threading.Event()
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        self.sock.settimeout(0.05)
        while not self.stop.is_set():
            try:
                c, _ = self.sock.accept()
                self.conns.append(c)
            except OSError:
                pass
            for c in self.conns:
                if self.reply:
                    try:
                        c.send(self.reply)
                    except OSError:
                        pass

    def close(self):
        self.stop.set()
        for c in self.conns:
            c.close()
        self.sock.close()


def _unreachable(*_a, **_k):
    raise OSError(errno.EHOSTUNREACH, "No route to host")


def _no_answer(*_a, **_k):
    raise TimeoutError("timed out")


@pytest.mark.parametrize(
    "case", ["refused", "unknown-host", "unreachable", "no-answer", "no-serial-device", "silent-port", "other-protocol"]
)
def test_run_retries_with_one_line_per_attempt_then_one_line_and_exit_2(case, capsys, tmp_path, monkeypatch):
    server = None
    if case in ("silent-port", "other-protocol"):
        server = _Server(b"HTTP/1.1 400 Bad Request\r\n\r\n" if case == "other-protocol" else b"")
        address = f"tcp:127.0.0.1:{server.port}"
    elif case == "unknown-host":
        address = "tcp:no-such-host.invalid:5760"
    elif case == "no-serial-device":
        address = str(tmp_path / "ttyUSB9") + ",57600"
    else:
        address = f"tcp:127.0.0.1:{free_port()}"
    if case in ("unreachable", "no-answer"):
        from passt_mav.mavlink import link as link_mod

        monkeypatch.setattr(link_mod.socket, "create_connection", _unreachable if case == "unreachable" else _no_answer)
    cause = {
        "refused": "connection refused",
        "unknown-host": "unknown host",
        "unreachable": "unreachable",
        "no-answer": "no answer within",
        "no-serial-device": "no such serial device",
        "silent-port": "nothing arrived",
        "other-protocol": "no MAVLink frame",
    }[case]
    try:
        out, err = _one_line_exit_2(
            capsys,
            ["run", MISSION, "--connect", address, "--ready-timeout", "1.2", "--out", tmp_path / "run", *FAST],
            f"no vehicle at {address}",
            cause,
        )
    finally:
        if server is not None:
            server.close()
    attempts = [ln for ln in out.splitlines() if "retrying in" in ln]
    assert len(attempts) >= 1 and all(ln.startswith(f"{address}: ") and cause in ln for ln in attempts), out
    assert "attempts over" in err  # gave up after retrying, not at the first failure
    assert not (tmp_path / "run").exists()  # nothing flown, nothing written: not even an empty run folder


def test_run_refused_from_the_shell_prints_one_line_and_exits_2(tmp_path):
    """The issue's case as a user types it: nothing listens on the port."""
    port = free_port()
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "passt_mav.cli",
            "run",
            MISSION,
            "--connect",
            f"tcp:127.0.0.1:{port}",
            "--ready-timeout",
            "1",
            "--out",
            str(tmp_path / "run"),
            *FAST,
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == [p.stderr.strip()] and "Traceback" not in p.stdout + p.stderr
    assert p.stderr.startswith(f"passt-mav: error: no vehicle at tcp:127.0.0.1:{port}") and "refused" in p.stderr


def test_a_failed_connection_writes_nothing(capsys, tmp_path, monkeypatch):
    """No vehicle: the default run folder (runs/ in the working directory) is not made, a --out folder
    made for the run is gone again, and a --out folder that was there before stays, as it was."""
    monkeypatch.chdir(tmp_path)
    address = f"tcp:127.0.0.1:{free_port()}"
    argv = ["run", MISSION, "--connect", address, "--ready-timeout", "0.5", *FAST]
    _one_line_exit_2(capsys, argv, f"no vehicle at {address}")
    assert sorted(tmp_path.iterdir()) == []
    _one_line_exit_2(capsys, [*argv, "--out", tmp_path / "a" / "b" / "run"], f"no vehicle at {address}")
    assert sorted(tmp_path.iterdir()) == []
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("kept")
    _one_line_exit_2(capsys, [*argv, "--out", tmp_path / "mine"], f"no vehicle at {address}")
    assert sorted(p.name for p in (tmp_path / "mine").rglob("*")) == ["notes.txt"]


def test_file_errors_of_every_command_are_one_line(capsys, tmp_path):
    nope = tmp_path / "nope"
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [
        (["run", nope.with_suffix(".yaml")], "no such mission file"),
        (["run", MISSION, "--connect", "tcp:127.0.0.1:5760", "--resume", "--out", nope], str(nope)),
        (["replay", nope], str(nope)),
        (["replay", afile], str(afile)),
        (["report", nope], str(nope)),
        (["report", tmp_path], "not a run directory"),
        (["plan", nope.with_suffix(".yaml"), "--out", tmp_path / "o"], "no such mission file"),
        (["plan", MISSION, "--state", nope.with_suffix(".nc"), "--model", "none", "--out", tmp_path / "o"], "nope.nc"),
        (["plan", MISSION, "--model", "none", "--out", afile / "sub"], str(afile)),
        (["data", "import", nope.with_suffix(".nc"), "--out", tmp_path / "x.nc"], "nope.nc"),
        (["data", "info", nope.with_suffix(".nc")], "nope.nc"),
        (
            ["model", "evaluate", "--data", nope.with_suffix(".nc"), "--model", "persistence", "--out", tmp_path / "o"],
            "nope.nc",
        ),
        (
            [
                "model",
                "evaluate",
                "--data",
                "builtin:ocean",
                "--model",
                nope.with_suffix(".pt"),
                "--out",
                tmp_path / "o",
            ],
            "nope",
        ),
        (["model", "train", "--data", nope.with_suffix(".nc"), "--model", "dmd", "--out", tmp_path / "o"], "nope.nc"),
        (["evaluate", "--data", nope.with_suffix(".nc"), "--model", "persistence", "--out", tmp_path / "o"], "nope.nc"),
        (["demo", "--field", nope.with_suffix(".nc")], "nope.nc"),
        (["bench", "--dir", nope], str(nope)),
        (["export", nope], str(nope)),
        (["export", tmp_path], "not a run directory"),
        (["export", tmp_path, "--format", "shp"], "unknown export format"),
    ]
    for argv, needle in cases:
        _one_line_exit_2(capsys, argv, needle)


def test_a_new_run_into_an_old_run_directory_is_refused(capsys, tmp_path):
    # a second run's samples would go into the first run's sample store and both runs' legs would
    # count them (found: a demo into a reused --out reported 4365 samples of 2181 readings)
    old = tmp_path / "old"
    old.mkdir()
    (old / "summary.json").write_text('{"status": "complete"}')
    before = sorted((p.name, p.read_bytes()) for p in old.iterdir())
    for argv in (
        ["run", MISSION, "--connect", "tcp:127.0.0.1:5760", "--out", old],
        ["demo", "--out", old, "--no-view"],
    ):
        _one_line_exit_2(capsys, argv, "already holds a run")
    assert sorted((p.name, p.read_bytes()) for p in old.iterdir()) == before  # nothing written, nothing lost


def test_a_bad_identity_is_one_line(capsys, tmp_path):
    _one_line_exit_2(capsys, ["run", MISSION, "--source-system", "0", "--out", tmp_path / "r"], "--source-system")
