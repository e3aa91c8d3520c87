"""The live view (issue 29): the record writer, the run-directory reader, the server, ``passt-mav view``.

The browser test of the whole thing (``passt-mav demo --boats 3 --view``) is in test_view_browser.py.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

import geo
from passt_mav.fields.field import FlowField
from passt_mav.runs.live import KINDS, RecordWriter, read_events, read_statuses
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore

GRID = geo.RegionGrid(40.0, -63.0, 40.45, -62.45, 10, 12)


def make_live_run(root) -> RunDir:
    """A small run directory as the controller leaves it mid-mission: meta, one boat's status and
    events, leg 0 complete (estimate, std, reward map), leg 1 flying, samples of both."""
    rd = RunDir(root).create()
    land = np.zeros(GRID.shape, bool)
    land[-2:, -3:] = True
    w = RecordWriter(rd.root)
    w.field_time = lambda: 1234.5
    w.meta(
        {
            "mission": "t",
            "grid": GRID.describe(),
            "land": land.astype(int).tolist(),
            "geofence_margin_m": 500.0,
            "boats": 1,
            "legs_per_boat": 3,
            "truth_known": True,
            "skill_warning": "model worse than persistence",
        }
    )
    w.event("leg_start", "leg 1/3 started")
    w.event("link_lost", "leg 0: link lost")
    w.event("link_back", "leg 0: link back")
    lat, lon = GRID.cell_to_latlon(5, 6)
    w.status(
        {
            "sysid": 1,
            "lat": float(lat),
            "lon": float(lon),
            "heading_deg": 90.0,
            "mode": "AUTO",
            "armed": True,
            "link_lost": False,
            "rtt_ms": 3.0,
            "loss_pct": 0.0,
            "leg": 1,
            "leg_k": 2,
            "legs_n": 3,
            "flying": True,
            "samples_leg": 4,
            "leg_end_s": 600.0,
            "leg_end_wall_s": 4.0,
        }
    )
    uv = np.stack([np.full(GRID.shape, 0.3), np.full(GRID.shape, -0.1)]).astype(np.float32)
    uv[:, land] = np.nan
    for i, status in ((0, "complete"), (1, "flying")):
        rd.write_leg(
            i,
            {
                "index": i,
                "status": status,
                "path": [[1, 1], [2, 2], [3, 3]],
                "t_start": 100.0 * i,
                "t_end": 100.0 * (i + 1),
                "rmse_passt": 0.02 if status == "complete" else None,
                "rmse_model": 0.05 if status == "complete" else None,
                "reward_map": np.tile(np.linspace(0, 1, GRID.cols), (GRID.rows, 1)).tolist(),
            },
        )
    FlowField(uv[None], GRID, np.array([100.0]), None).to_netcdf(
        rd.estimate_file(0), std=np.full((1, 2) + GRID.shape, 0.05, np.float32)
    )
    with SampleStore(rd.samples_db) as st:
        st.append_many(
            [
                {
                    "time_boot_ms": 1000 * k,
                    "utc": 1.0e9 + k,
                    "lat": 40.1 + 0.01 * k,
                    "lon": -62.9,
                    "u": 0.3,
                    "v": -0.1,
                    "leg": 0 if k < 5 else 1,
                    "source": "mav:1/1",
                }
                for k in range(9)
            ]
        )
    return rd


# -- the record writer ------------------------------------------------------------------------------
def test_record_writer_writes_events_and_status_and_never_raises(tmp_path):
    rd = make_live_run(tmp_path / "run")
    events, off = read_events(rd.root)
    assert [e["kind"] for e in events] == ["leg_start", "link_lost", "link_back"]
    assert [e["level"] for e in events] == ["info", "alert", "ok"] and all(e["field_time"] == 1234.5 for e in events)
    assert off == (rd.root / "events.jsonl").stat().st_size
    assert read_statuses(rd.root)[0]["mode"] == "AUTO"
    # a half-written last line waits for its newline
    with open(rd.root / "events.jsonl", "a") as f:
        f.write('{"kind": "reb')
    assert read_events(rd.root, off) == ([], off)
    # a run directory that cannot be written (a file in its place): nothing raises into the mission
    bad = tmp_path / "not_a_dir"
    bad.write_text("x")
    w = RecordWriter(bad)
    w.field_time = lambda: 1 / 0
    w.event("link_lost", "x")
    w.status({"lat": 1.0})
    w.meta({"a": 1})
    w.start_status(lambda: {"lat": 1.0}, period_s=0.01)
    time.sleep(0.05)
    w.stop_status(lambda: 1 / 0)
    assert {
        "link_lost",
        "link_back",
        "pilot_takeover",
        "reboot",
        "fence_refused",
        "boat_dropped",
        "leg_start",
        "leg_end",
    } <= set(KINDS)


def test_a_waypoint_outside_the_geofence_is_an_alert(tmp_path):
    """The controller's geofence check refuses a leg before upload: the view gets a fence_refused alert."""
    from types import SimpleNamespace

    from passt_mav.errors import PlannerError
    from passt_mav.vehicle.controller import MissionController

    ctl = object.__new__(MissionController)  # only what _checked_mission reads
    ctl.grid, ctl.record = GRID, RecordWriter(tmp_path)
    # a fence 20 km inside the region (no mission file allows that: the check is what is tested)
    ctl.config = SimpleNamespace(geofence_margin_m=-20000.0, vehicle=SimpleNamespace(speed_mps=2.0, wp_radius_m=5.0))
    planned = SimpleNamespace(plan=SimpleNamespace(path=np.array([[0, 0], [1, 1], [2, 2]])))
    with pytest.raises(PlannerError, match="outside the geofence"):
        ctl._checked_mission(0, planned.plan.path)
    (ev,) = read_events(tmp_path)[0]
    assert ev["kind"] == "fence_refused" and ev["level"] == "alert" and "not uploaded" in ev["text"]


def test_status_thread_writes_about_once_a_second_and_a_last_one_at_stop(tmp_path):
    w = RecordWriter(tmp_path)
    n = {"k": 0}

    def status():
        n["k"] += 1
        return {"k": n["k"]}

    w.start_status(status, period_s=0.05)
    time.sleep(0.3)
    w.stop_status(lambda: {"k": -1})
    assert n["k"] >= 3 and read_statuses(tmp_path)[0]["k"] == -1


# -- the reader --------------------------------------------------------------------------------------
def test_snapshot_has_what_the_page_draws(tmp_path):
    from passt_mav.view.state import RunState

    rd = make_live_run(tmp_path / "run")
    s = RunState(rd.root).snapshot()
    json.dumps(s, allow_nan=False)  # what the server sends
    assert s["status"] == "running" and s["meta"]["skill_warning"] and "land" not in s["meta"]
    b = s["boats"][0]
    assert b["status"]["leg_k"] == 2 and b["legs_done"] == 1
    assert len(b["samples"]) == 4  # the flying leg's (1) samples only
    assert len(b["track"]) == 9 + 1 + 1  # every sample (+ the newest again) and the status position
    assert [lg["status"] for lg in s["legs"]] == ["complete", "flying"]
    lat, lon = GRID.cell_to_latlon(2, 2)
    assert s["legs"][0]["path"][1] == pytest.approx([float(lat), float(lon)], abs=1e-6)
    e = s["estimate"]
    assert e["kind"] == "estimate" and e["leg"] == 0 and e["std"] and e["reward_leg"] == 1
    assert len(e["arrows"]) == GRID.rows * GRID.cols - 6 and e["arrows"][0][2:] == pytest.approx([0.3, -0.1])
    assert s["rmse"] == {"t": [100.0], "passt": [0.02], "model": [0.05], "leg": [0]}
    r = s["region"]
    assert r["has_land"] and r["bounds"][0][0] < 40.0 and 40.45 < r["bounds"][1][0]
    fence = np.array(r["fence"])
    assert fence[:, 0].min() < r["bounds"][0][0]  # the 500 m margin lies outside the region
    assert [x["kind"] for x in s["events"]] == ["leg_start", "link_lost", "link_back"]


def test_rasters_are_pngs_north_up(tmp_path):
    import io

    from matplotlib.image import imread

    from passt_mav.view.state import RunState

    st = RunState(make_live_run(tmp_path / "run").root)
    for what, leg in (("speed", 0), ("std", 0), ("reward", 1), ("land", None)):
        png = st.raster(what, leg)
        assert png[:8] == b"\x89PNG\r\n\x1a\n", what
    land = imread(io.BytesIO(st.raster("land", None)))
    assert land.shape[:2] == GRID.shape
    assert land[0, -1, 3] > 0 and land[-1, -1, 3] == 0  # the land (north-east rows) at the top of the image
    assert st.raster("std", 1) is None and st.raster("nonsense", 0) is None


# -- the server ----------------------------------------------------------------------------------------
def _get(url: str, timeout: float = 30.0):
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, r.headers.get("Content-Type", ""), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, "", b""
    except (urllib.error.URLError, TimeoutError) as exc:  # not listening yet, or busy (a loaded machine)
        return None, str(exc), b""


def test_server_serves_page_state_stream_and_rasters_on_loopback(tmp_path):
    from passt_mav.view import start_view

    rd = make_live_run(tmp_path / "run")
    vp = start_view(rd.root, log_file=tmp_path / "view.log")
    try:
        assert vp.url.startswith("http://127.0.0.1:") and vp.url == f"{vp.base}?token={vp.token}"
        code, ctype, body = _get(vp.url)
        assert (
            code == 200
            and b"static/vendor/leaflet/leaflet.js" in body
            and b"http" not in body.lower().replace(b"http-equiv", b"")
        )  # nothing from outside
        assert _get(vp.base + "static/vendor/leaflet/leaflet.js")[0] == 200
        assert _get(vp.base + "static/vendor/leaflet/LICENSE")[0] == 200
        code, ctype, body = _get(vp.base + "api/state")
        assert code == 200 and json.loads(body)["boats"][0]["status"]["mode"] == "AUTO"
        code, ctype, body = _get(vp.base + "api/raster/speed.png?leg=0")
        assert code == 200 and ctype == "image/png"
        assert _get(vp.base + "api/raster/speed.png?leg=x")[0] == 400
        # server-sent events: the first snapshot at once, a new one when a file changes
        with urllib.request.urlopen(vp.base + "api/stream", timeout=30) as r:
            assert r.headers["Content-Type"].startswith("text/event-stream")
            first = json.loads(r.readline().decode().removeprefix("data: "))
            RecordWriter(rd.root).event("reboot", "leg 1: vehicle rebooted")
            r.readline()
            t0 = time.monotonic()
            second = json.loads(r.readline().decode().removeprefix("data: "))
            behind = time.monotonic() - t0
            # <= 2 s behind the files (polled every 0.4 s; ~0.4 s measured), with room for a loaded machine
            assert behind < 5.0
            print(f"the page's stream was {behind:.2f} s behind events.jsonl")
        assert first["n_events"] == 3 and second["events"][-1]["kind"] == "reboot"
    finally:
        vp.stop()
    assert vp.proc.poll() is not None


def test_a_non_loopback_host_needs_the_token(tmp_path):
    from passt_mav.view import start_view

    rd = make_live_run(tmp_path / "run")
    vp = start_view(rd.root, host="0.0.0.0", log_file=tmp_path / "view.log")
    try:
        assert "?token=" in vp.url
        token = vp.url.split("?token=")[1]
        base = f"http://127.0.0.1:{vp.port}/"
        assert _get(base + "api/state")[0] == 403 and _get(base + "api/raster/speed.png?leg=0")[0] == 403
        # the page's shell holds no run data: it loads, then reads with the token it keeps (sessionStorage)
        assert _get(base)[0] == 200 and _get(base + "static/view.js")[0] == 200
        assert _get(base + "api/state?token=wrong")[0] == 403
        assert _get(base + f"?token={token}")[0] == 200 and _get(base + f"api/state?token={token}")[0] == 200
    finally:
        vp.stop()


def test_a_view_that_cannot_start_is_one_line_and_the_mission_goes_on(tmp_path):
    import socket

    from passt_mav.commands.view import start_live_view

    rd = make_live_run(tmp_path / "run")
    lines: list[str] = []
    with socket.socket() as s:  # the port is taken: the view's subprocess exits at once
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        assert start_live_view(rd, s.getsockname()[1], "127.0.0.1", echo=lines.append) is None
    assert len(lines) == 1 and "not started" in lines[0] and "goes on without it" in lines[0]


def test_the_view_never_outlives_the_mission_process(tmp_path):
    """A mission process that dies without stopping its view (killed, crashed) takes the view with it."""
    from pathlib import Path

    rd = make_live_run(tmp_path / "run")
    code = (
        "import os, sys; from passt_mav.view import start_view; "
        "print(start_view(sys.argv[1]).proc.pid, flush=True); os._exit(0)"
    )
    pid = int(
        subprocess.run(
            [sys.executable, "-c", code, str(rd.root)], capture_output=True, text=True, timeout=60, check=True
        ).stdout
    )

    def alive() -> bool:
        try:
            return "\tZ" not in Path(f"/proc/{pid}/status").read_text().split("State:")[1][:4]
        except (FileNotFoundError, IndexError):
            return False

    end = time.monotonic() + 15
    while alive() and time.monotonic() < end:
        time.sleep(0.1)
    assert not alive()


# -- the command -------------------------------------------------------------------------------------------
def test_run_view_option_serves_the_run_dir(tmp_path):
    """``passt-mav run ... --view [PORT]``: parsed as a port (none: a free one), served from a subprocess."""
    from passt_mav.cli import build_parser
    from passt_mav.commands.run import _live_view

    args = build_parser().parse_args(["run", "m.yaml", "--view"])
    assert args.view == 0 and args.view_host == "127.0.0.1"
    assert build_parser().parse_args(["run", "m.yaml"]).view is None
    rd = make_live_run(tmp_path / "run")
    vp = _live_view(args, rd)
    try:
        code, _, body = _get(vp.base + "api/state")
        assert code == 200 and json.loads(body)["status"] == "running"
    finally:
        vp.stop()


def test_view_of_a_bad_run_dir_is_one_line_and_exit_2(tmp_path):
    p = subprocess.run(
        [sys.executable, "-m", "passt_mav.cli", "view", str(tmp_path / "nope")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "not a run directory" in p.stderr, p.stderr


def test_view_command_reopens_a_finished_run(tmp_path):
    rd = make_live_run(tmp_path / "run")
    rd.write_summary({"mission": "t", "status": "complete", "finished_utc": "2026-01-01T00:00:00Z"})
    p = subprocess.Popen(
        [sys.executable, "-m", "passt_mav.cli", "view", str(rd.root)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        line = p.stdout.readline()
        assert "http://127.0.0.1:" in line, line
        url = next(w for w in line.split() if w.startswith("http://")).split("?token=")[0]
        end = time.monotonic() + 60
        while time.monotonic() < end:
            code, _, body = _get(url + "api/state", timeout=20.0)  # the first snapshot imports xarray
            if code == 200:
                break
            time.sleep(0.2)
        s = json.loads(body)
        assert s["status"] == "complete" and s["finished"]
    finally:
        p.terminate()
        p.wait(10)


def test_help_imports_no_web_server():
    code = (
        "import sys; from passt_mav.cli import build_parser; build_parser(); "
        "print([m for m in ('starlette', 'uvicorn', 'torch', 'matplotlib') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stdout
    assert out.strip() == "[]"


def test_guard_banner_follows_the_latest_scored_leg():
    """The live view's banner (state ``guard_warning``): the guard's alarm of the latest leg it scored
    (by field time), nothing for a fallback without an alarm, and nothing once a later leg is fine."""
    from passt_mav.view.state import _guard_warning

    alarm = {"alarm": True, "message": "sampling is not helping: at leg 2's samples ..."}
    quiet = {"alarm": False, "message": "at leg 3's samples ... falls back"}
    legs = [{"t_end": 10.0, "guard": {"alarm": False, "message": None}}, {"t_end": 20.0, "guard": alarm}]
    assert _guard_warning(legs) == alarm["message"]
    assert _guard_warning(legs + [{"t_end": 30.0, "guard": quiet}]) is None
    assert _guard_warning(legs + [{"t_end": 5.0, "guard": quiet}, {"t_end": 40.0}]) == alarm["message"]
    assert _guard_warning([]) is None
