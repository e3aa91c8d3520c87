"""Real ArduPilot Rover SITL for tests: start, kill -9, restart, stop (marker ``sitl``).

The firmware build and its ``start-sitl`` script live in ``../shared/sitl/`` beside the checkout
(override with the env var ``ARDUROVER_DIR``). Every instance gets a free instance number N (so
several pytest processes can run SITL at once), its own fresh work directory and is always killed
at teardown.

API (fixtures in ``tests/conftest.py``)::

    @pytest.mark.sitl
    def test_x(sitl):                      # one instance, defaults: speedup 10, home 40.0,-63.0
        link = Link(LinkConfig(sitl.connect, connect_timeout_s=60)).connect()
        ...

    @pytest.mark.sitl
    def test_y(sitl_factory, tmp_path):    # options, or several boats
        a = sitl_factory(speedup=20, params=tmp_path / "x.parm", scripts=LUA_DIR, sysid=3)
        a.kill9(); a.restart()             # crash and reboot keeping eeprom.bin (params + mission)

:class:`Sitl` attributes: ``instance`` (N), ``port`` (5760 + 10·N), ``connect``
(``"tcp:127.0.0.1:PORT"``, the pymavlink/LinkConfig string), ``pid`` (the ``ardurover``
process), ``workdir`` (holds ``eeprom.bin``, ``sitl.log``, ``scripts/``), ``speedup``, ``home``
(lat, lon degrees), ``sysid``. Methods: ``alive()``, ``kill9()`` (SIGKILL, like a brown-out),
``restart()`` (start again on the same instance and work directory: parameters and the stored
mission survive, like a reboot), ``stop()`` (idempotent), ``log_tail()``. ``mavlink()`` opens a
plain pymavlink connection (source 255/190) for tests that script the protocol by hand.

Rules from ``../shared/sitl/README.md`` this module follows: every socket stays on loopback
(``start-sitl`` preloads the shim), a parent process stays alive while SITL runs (``start-sitl``
leaves a waiting shell behind), and the port is never "probed" by connecting: SERIAL0 serves
exactly one client and SITL does not boot until it comes. Free instances are found by a lock file
per instance (``fcntl.flock``, released by the kernel if pytest dies) plus a bind test of the four
ports N uses (5760+10N .. +3).

SITL boots in simulated time only once a client is connected; at speedup 10 it takes ~3 s wall
to be armable and ~5 s wall for an EKF position (~45 s simulated).
"""

from __future__ import annotations

import atexit
import errno
import fcntl
import os
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SITL_DIR = Path(os.environ.get("ARDUROVER_DIR", REPO.parent / "shared" / "sitl"))
BASE_PORT = 5760
HOME = (40.0, -63.0)
# Instance numbers tried; 0 is left to a user's own SITL on 5760.
_INSTANCES = range(1, 90)
_LOCK_DIR = Path(tempfile.gettempdir()) / "passt_mav_sitl_locks"


def unavailable_reason() -> str | None:
    """Why SITL tests cannot run here, or None when they can."""
    for name in ("ardurover", "start-sitl", "bind_loopback.so"):
        p = SITL_DIR / name
        if not p.exists():
            return f"ArduPilot SITL not found: {p} is missing (set ARDUROVER_DIR or put the build in ../shared/sitl)"
    if not os.access(SITL_DIR / "ardurover", os.X_OK):
        return f"{SITL_DIR / 'ardurover'} is not executable"
    return None


def _port_free(port: int) -> bool:
    """True when nothing listens on or holds 127.0.0.1:port (bind test; never connects)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        # SO_REUSEADDR: a TIME_WAIT left by an earlier test must not make the port look busy
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _claim_instance() -> tuple[int, object]:
    """Lock a free instance number; returns (N, open lock file). The lock lives as long as the file."""
    _LOCK_DIR.mkdir(parents=True, exist_ok=True)
    for n in _INSTANCES:
        f = open(_LOCK_DIR / f"instance-{n}.lock", "w")  # noqa: SIM115 - held open while the lock is held
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            f.close()
            if e.errno in (errno.EAGAIN, errno.EACCES):
                continue
            raise
        port = BASE_PORT + 10 * n
        if all(_port_free(port + k) for k in range(4)):
            return n, f
        f.close()  # releases the lock: someone outside our lock scheme uses these ports
    raise RuntimeError(f"no free SITL instance in {_INSTANCES} (ports {BASE_PORT}+10N..+3 all busy)")


_LIVE: list[Sitl] = []


@atexit.register
def _kill_leftovers() -> None:  # pragma: no cover - only when a test forgot teardown
    for s in _LIVE:
        s.stop()


@dataclass
class Sitl:
    """One running ArduRover SITL (motorboat). Build it with :func:`start`."""

    workdir: Path
    instance: int
    speedup: float = 10.0
    home: tuple[float, float] = HOME
    params: Path | None = None
    scripts: Path | None = None
    sysid: int = 1
    pid: int = 0
    _lock: object = field(default=None, repr=False)

    @property
    def port(self) -> int:
        return BASE_PORT + 10 * self.instance

    @property
    def connect(self) -> str:
        return f"tcp:127.0.0.1:{self.port}"

    # -- lifecycle -------------------------------------------------------------------
    def _params_file(self) -> Path | None:
        """The --params file: the caller's file plus MAV_SYSID when asked for another system id."""
        if self.sysid == 1:
            return self.params
        p = self.workdir / "sysid.parm"
        text = Path(self.params).read_text() if self.params else ""
        p.write_text(text + f"\nMAV_SYSID {self.sysid}\n")
        return p

    def _start(self, wipe: bool) -> None:
        cmd = [
            str(SITL_DIR / "start-sitl"),
            str(self.workdir),
            "-I",
            str(self.instance),
            "--speedup",
            f"{self.speedup:g}",
            "--home",
            f"{self.home[0]},{self.home[1]}",
        ]
        params = self._params_file()
        if params is not None:
            cmd += ["--params", str(params)]
        if self.scripts is not None:
            cmd += ["--scripts", str(self.scripts)]
        if wipe:
            cmd.append("--wipe")
        # generous: on 2 busy cores the script's own 30 s wait is the real limit
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        if r.returncode != 0:
            raise RuntimeError(f"start-sitl failed ({r.returncode}): {r.stderr.strip()} {self.log_tail()}")
        pid, port = r.stdout.split()
        assert int(port) == self.port, (port, self.port)
        self.pid = int(pid)
        if self not in _LIVE:
            _LIVE.append(self)

    def alive(self) -> bool:
        if not self.pid:
            return False
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        # a zombie is not alive; the waiting shell reaps it, but look anyway
        try:
            return Path(f"/proc/{self.pid}/stat").read_text().split()[2] != "Z"
        except OSError:
            return False

    def _wait_gone(self, timeout: float = 10.0) -> None:
        end = time.monotonic() + timeout
        while self.alive() and time.monotonic() < end:
            time.sleep(0.05)
        # the listener must be gone too before the same port is reused
        while not all(_port_free(self.port + k) for k in range(4)) and time.monotonic() < end:
            time.sleep(0.05)

    def kill9(self) -> None:
        """SIGKILL the autopilot (a crash or brown-out); ``restart()`` brings it back."""
        if self.alive():
            os.kill(self.pid, signal.SIGKILL)
        self._wait_gone()

    def restart(self) -> None:
        """Start again on the same instance and work directory (eeprom.bin kept: params and mission)."""
        if self.alive():
            self.kill9()
        self._start(wipe=False)

    def stop(self) -> None:
        """Kill the autopilot and free the instance. Safe to call twice."""
        if self.pid and self.alive():
            try:
                os.kill(self.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            end = time.monotonic() + 5
            while self.alive() and time.monotonic() < end:
                time.sleep(0.05)
            if self.alive():
                os.kill(self.pid, signal.SIGKILL)
            self._wait_gone()
        if self._lock is not None:
            self._lock.close()
            self._lock = None
        if self in _LIVE:
            _LIVE.remove(self)

    def log_tail(self, n: int = 20) -> str:
        p = self.workdir / "sitl.log"
        try:
            return "\n".join(p.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def mavlink(self, timeout: float = 60.0):
        """A plain pymavlink connection (source 255/190) after the first vehicle HEARTBEAT."""
        from pymavlink import mavutil

        os.environ.setdefault("MAVLINK20", "1")
        m = mavutil.mavlink_connection(self.connect, source_system=255, source_component=190, autoreconnect=False)
        hb = m.wait_heartbeat(timeout=timeout)
        if hb is None:
            m.close()
            raise RuntimeError(f"no HEARTBEAT from SITL on {self.connect} in {timeout} s\n{self.log_tail()}")
        return m


def start(
    workdir: Path,
    *,
    speedup: float = 10.0,
    home: tuple[float, float] = HOME,
    params: Path | str | None = None,
    scripts: Path | str | None = None,
    sysid: int = 1,
) -> Sitl:
    """Start SITL in a fresh ``workdir`` on a free instance; the caller must ``stop()`` it.

    ``params``: an ArduPilot .parm file loaded after rover.parm and motorboat.parm; ``scripts``: a
    folder whose ``*.lua`` run on the vehicle (SCR_ENABLE=1); ``sysid``: MAV_SYSID; ``home``:
    lat, lon in degrees (altitude 0, heading 0).
    """
    reason = unavailable_reason()
    if reason:
        raise RuntimeError(reason)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    n, lock = _claim_instance()
    s = Sitl(
        workdir=workdir,
        instance=n,
        speedup=speedup,
        home=home,
        params=Path(params) if params else None,
        scripts=Path(scripts) if scripts else None,
        sysid=sysid,
        _lock=lock,
    )
    try:
        s._start(wipe=True)
    except BaseException:
        s.stop()
        raise
    return s
