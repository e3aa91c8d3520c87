"""The live view: a local web page that follows a mission while it flies, and reopens a finished run.

It reads only the run directory (:mod:`passt_mav.runs.live` describes what the controller writes
for it), so ``passt-mav run --view`` starts it as a **subprocess**: a crashed or slow view never
stops, nor steals time from, the mission. ``passt-mav view RUN_DIR`` serves a finished run the same way.

Built on Starlette + uvicorn (maintained ASGI library and server; no hand-written HTTP) with
server-sent events, and Leaflet 1.9.4 (npm, BSD-2-Clause) vendored under ``static/vendor/leaflet``
with no tile layer: the page loads nothing from outside 127.0.0.1 (or the ``--view-host``).
Every server has a token, made at start and printed in the address: the page's commands need it, and
binding to anything but loopback needs it for reading too (:mod:`passt_mav.view.gate`, docs/console.md).
"""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ViewProcess", "start_view", "view_address", "new_token", "check_port"]

TOKEN_ENV = "PASST_VIEW_TOKEN"


def new_token() -> str:
    """A random token for one server (144 bits, URL-safe)."""
    return secrets.token_urlsafe(18)


def view_address(host: str, port: int, token: str | None) -> str:
    """The page's address on ``host``:``port`` with the token (the one to open: it may command)."""
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")


def check_port(host: str, port: int = 0) -> int:
    """``port`` if it is free on ``host`` (0: any free one); OSError naming it when it is taken."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise OSError(f"cannot bind {host}:{port}: {exc.strerror or exc}") from None
        return s.getsockname()[1]


@dataclass
class ViewProcess:
    """A view server running in a subprocess (:func:`start_view`)."""

    proc: subprocess.Popen
    url: str
    port: int
    token: str | None = None

    @property
    def base(self) -> str:
        """The server's address without the token (``http://HOST:PORT/``)."""
        return self.url.split("?", 1)[0]

    def stop(self, grace_s: float = 0.0) -> None:
        """Let the page get the last changes for ``grace_s``, then stop the server."""
        if grace_s > 0 and self.proc.poll() is None:
            time.sleep(grace_s)
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)


def start_view(
    root: str | Path,
    *,
    port: int = 0,
    host: str = "127.0.0.1",
    log_file: str | Path | None = None,
    wait_s: float = 30.0,
) -> ViewProcess:
    """Serve the run in ``root`` from a subprocess (``python -m passt_mav.view``); returns once it answers.

    Raises ``OSError`` when it does not listen within ``wait_s`` (the mission goes on without it).
    """
    token = new_token()
    port = check_port(host, int(port))
    env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}
    env[TOKEN_ENV] = token  # not on the command line, where ps shows it
    out = open(log_file, "ab") if log_file else subprocess.DEVNULL  # noqa: SIM115 - handed to the server process
    cmd = [sys.executable, "-m", "passt_mav.view", str(root), "--host", host, "--port", str(port), "--exit-with-parent"]
    proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
    end = time.monotonic() + wait_s
    probe = "127.0.0.1" if host in ("0.0.0.0", "") else ("::1" if host == "::" else host)
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise OSError(f"the live view exited with code {proc.returncode} (see {log_file or 'its output'})")
        with socket.socket(socket.AF_INET6 if ":" in probe else socket.AF_INET) as s:
            s.settimeout(0.3)
            if s.connect_ex((probe, port)) == 0:
                return ViewProcess(proc, view_address(host, port, token), port, token)
        time.sleep(0.1)
    proc.terminate()
    raise OSError(f"the live view did not listen on {host}:{port} within {wait_s:.0f} s")
