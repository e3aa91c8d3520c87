"""Mission controller faults, continued: an upload DENIED by a vehicle busy with another
GCS's transfer, MAVLink 2 signing, and ``passt-mav run`` killed with SIGKILL mid-leg then
continued with ``--resume``.

The in-process tests use the setting of tests/test_controller.py (8x8 grid of ~40 m cells,
persistence, greedy legs of 3 moves, simulator served in-process at 50x). The kill/resume
test runs both programs as real processes over loopback TCP, as a user would.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mavlink_helpers import inprocess_factory, link_config, served, vehicle
from pymavlink.dialects.v20 import ardupilotmega as M
from simclient import free_port
from test_controller import SPEEDUP, controller, mission, sim_config, wave_field
from test_controller_faults import _modes

from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.errors import LinkTimeout, MissionRejected
from passt_mav.mavlink import Link
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore
from passt_mav.vehicle.controller import MissionController, build_predictor
from vehicle_sim.link import secret_from_key

AUTO = 10  # ArduPilot Rover custom_mode


# -- 1. DENIED: another GCS holds a mission transfer open ------------------------------------
def test_upload_denied_while_another_gcs_holds_a_transfer_open(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    rd = RunDir(tmp_path / "run").create()
    with served(sim_config(), field=field, speedup=SPEEDUP, link_kw={"stream_rates_hz": LEAN_STREAMS}) as (sim, link):
        modes = _modes(link)
        # a second GCS (sysid 254) starts an upload and never sends an item. The vehicle cancels
        # an idle transfer after 8 s of its time (0.16 s wall at 50x), so the GCS restarts it
        # (MISSION_COUNT again: the owner may) every 20 ms wall = 1 s of vehicle time.
        other = Link(
            link_config(source_system=254, stream_rates_hz=()), connection_factory=inprocess_factory(sim)
        ).connect()
        stop = threading.Event()

        def hold_transfer():
            while not stop.is_set():
                other.conn.mav.mission_count_send(1, 1, 5, 0)
                stop.wait(0.02)

        th = threading.Thread(target=hold_transfer, daemon=True)
        th.start()
        try:
            end = time.monotonic() + 5
            while 0 not in sim.autopilot.missions.uploads and time.monotonic() < end:
                time.sleep(0.01)
            assert 0 in sim.autopilot.missions.uploads  # the other GCS's transfer is open
            ctl = controller(cfg, field, link, rd, echo=None)
            with pytest.raises(MissionRejected) as ei:
                ctl.run()
        finally:
            stop.set()
            th.join(2)
            other.close()
        assert ei.value.result == M.MAV_MISSION_DENIED and "DENIED" in str(ei.value)
        time.sleep(0.1)
        assert AUTO not in modes and modes  # heartbeats seen, none in AUTO
        assert not ctl.vehicle.armed and not sim.autopilot.armed
        assert sim.autopilot.store.count(0) <= 1  # our mission never reached the vehicle
    s = rd.read_summary()
    assert s["status"] == "aborted" and "DENIED" in s["events"][-1]
    assert rd.read_leg(0)["status"] == "flying"  # planned, never flown


# -- 2. signing ---------------------------------------------------------------------------------
KEY = "passt signing test key"


def test_signed_vehicle_and_controller_with_the_key_complete_a_leg(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    rd = RunDir(tmp_path / "run").create()
    with served(
        sim_config(signing_key=secret_from_key(KEY)),
        field=field,
        speedup=SPEEDUP,
        link_kw={"stream_rates_hz": LEAN_STREAMS, "signing_key": KEY},
    ) as (sim, link):
        ctl = controller(cfg, field, link, rd, echo=None)
        summary = ctl.run()
        assert sim.autopilot.store.count(0) == len(summary["legs"][0]["waypoints"]) + 2  # home + speed + wps
    assert summary["status"] == "complete" and len(summary["legs"]) == 1
    assert summary["legs"][0]["n_samples"] > 5


def test_controller_without_the_key_is_ignored_and_times_out(tmp_path):
    field = wave_field()
    cfg = mission(tmp_path, field, legs=1)
    rd = RunDir(tmp_path / "run").create()
    with served(
        sim_config(signing_key=secret_from_key(KEY)),
        field=field,
        speedup=SPEEDUP,
        link_kw={"stream_rates_hz": (), "retries": 1},
    ) as (sim, link):
        # (no stream requests: each would go unanswered; the vehicle's default streams still come)
        modes = _modes(link)
        # one resend per step (the default, >= 10, is for lossy radios): an ignored client gives up sooner
        pred, info = build_predictor(cfg.model, field, echo=lambda s: None)
        ctl = MissionController(
            cfg,
            link,
            rd,
            field=field,
            predictor=pred,
            predictor_info=info,
            vehicle=vehicle(link, retries=1),
            speedup_hint=SPEEDUP,
            ready_timeout_s=10.0,
            field_time_at_boot=0.0,
            echo=None,
        )
        t0 = time.monotonic()
        with pytest.raises(LinkTimeout) as ei:
            ctl.run()
        took = time.monotonic() - t0
        time.sleep(0.1)
        assert modes and AUTO not in modes and sim.autopilot.mode != AUTO and not sim.autopilot.armed
        assert sim.autopilot.store.count(0) <= 1
    assert "may require MAVLink 2 signing" in str(ei.value)  # says what timed out and the likely cause
    print(f"keyless controller gave up after {took:.2f} s: {ei.value}")
    s = rd.read_summary()
    assert s["status"] == "aborted" and "LinkTimeout" in s["events"][-1]


# -- 3. passt-mav run killed with SIGKILL mid-leg, then --resume -----------------------------
KILL_SPEEDUP = 20  # a leg of ~30 s vehicle time lasts ~1.5 s of wall time: room to kill it mid-leg


def _wait_port(port: int, proc, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()[1]
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise AssertionError(f"vehicle-sim never listened on {port}")


def _stored(db: Path, leg: int | None = None) -> int:
    if not db.exists():
        return 0
    try:
        with SampleStore(db, readonly=True) as st:
            return st.count(leg)
    except Exception:  # noqa: BLE001 - the store is being created by the other process
        return 0


def _leg_status(rd: RunDir, i: int) -> str | None:
    try:
        return json.loads(rd.leg_file(i).read_text()).get("status")
    except (OSError, ValueError):
        return None


@pytest.mark.slow(reason="two processes importing torch, two legs at 20x: ~17 s on two loaded cores")
def test_run_killed_mid_leg_then_resume_finishes_and_keeps_samples(tmp_path):
    import yaml

    field = wave_field()
    cfg = mission(tmp_path, field, legs=2)  # writes wave.nc; validates the mapping we write below
    mfile = tmp_path / "wave.yaml"
    mfile.write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))
    port = free_port()
    run_dir = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    bindir = Path(sys.executable).parent
    sim = subprocess.Popen(
        [
            str(bindir / "vehicle-sim"),
            "--field",
            str(tmp_path / "wave.nc"),
            "--home",
            "40,-63",
            "--listen",
            f"tcp:127.0.0.1:{port}",
            "--speedup",
            str(KILL_SPEEDUP),
            "--no-wait",
            "--fast-boot",
            "--param",
            "WP_SPEED=5",
            "--current-noise",
            "0.01",
            "--current-rate",
            "1",
            "--seed",
            "3",
            "--quiet",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
    )
    run_cmd = [
        str(bindir / "passt-mav"),
        "run",
        str(mfile),
        "--connect",
        f"tcp:127.0.0.1:{port}",
        "--out",
        str(run_dir),
        "--speedup-hint",
        str(KILL_SPEEDUP),
        "--field-time-at-boot",
        "0",
        "--ready-timeout",
        "20",
        "--no-report",
    ]
    try:
        _wait_port(port, sim)
        t0 = time.monotonic()
        ctl = subprocess.Popen(run_cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True)
        rd = RunDir(run_dir)
        before = 0
        end = time.monotonic() + 60
        while time.monotonic() < end and ctl.poll() is None:
            if _leg_status(rd, 0) == "flying" and (before := _stored(rd.samples_db, 0)) >= 3:
                break
            time.sleep(0.02)
        assert ctl.poll() is None, ctl.communicate()[0]  # still running: leg 0 was in flight
        os.kill(ctl.pid, signal.SIGKILL)
        out1, _ = ctl.communicate(timeout=10)
        t_kill = time.monotonic() - t0
        assert ctl.returncode == -signal.SIGKILL
        assert _leg_status(rd, 0) == "flying" and before >= 3, out1
        kept = {(s.time_boot_ms, s.lat, s.lon) for s in SampleStore(rd.samples_db, readonly=True).all()}
        assert len(kept) >= before

        t1 = time.monotonic()
        res = subprocess.run(run_cmd + ["--resume"], capture_output=True, text=True, env=env, timeout=120)
        t_resume = time.monotonic() - t1
        assert res.returncode == 0, res.stdout + res.stderr
    finally:
        sim.send_signal(signal.SIGINT)
        try:
            sim.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.communicate()
    print(f"killed after {t_kill:.1f} s with {before} samples of leg 0 stored; resume took {t_resume:.1f} s")
    summary = rd.read_summary()
    assert summary["status"] == "complete" and [x["index"] for x in summary["legs"]] == [0, 1]
    for i in (0, 1):
        rec = rd.read_leg(i)
        assert rec["status"] == "complete" and rec["n_samples"] > 3 and rec["rmse_passt"] is not None
        assert rd.estimate_file(i).exists() and rd.waypoints_file(i).exists()
    assert any(e.startswith("resumed before leg 1") for e in summary["events"]) and "resuming" in res.stdout
    assert rd.read_leg(0)["n_samples"] >= before  # the interrupted flight's samples count for the re-flown leg
    with SampleStore(rd.samples_db, readonly=True) as st:
        after = {(s.time_boot_ms, s.lat, s.lon) for s in st.all()}
        assert st.count() == summary["n_samples"]
    assert kept <= after  # every sample stored before the kill is still there
    assert len(after) > len(kept)
