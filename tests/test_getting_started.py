"""The manual's tutorial (docs/getting-started.md) runs as written.

The page's ``bash`` blocks and its ``mine.yaml`` block are read from the page itself and run in a
temporary folder, in order, on a synthetic forecast file laid out like HYCOM/RTOFS
(``water_u``/``water_v``, m/s, hourly, a land patch): every ``passt-mav`` line through
``passt_mav.cli.main`` (the command a user types, in-process), ``passt-mav view`` as its own process
(it serves until stopped), and the ``vehicle-sim`` line parsed by the simulator's own argument
parser and built in-process, served in lockstep (``vehicle-sim --lockstep``; the one seam, as in
tests/test_run_missions.py: ``LinkConfig.open`` hands the controller the simulator's endpoint, and the
``run`` line gets ``--lockstep``, so simulated time advances only while the controller waits for the
vehicle), so the flight does not depend on the machine's load.

Known answers: the forecast is linear in latitude, longitude and time, so bilinear regridding is
exact and the imported field equals it at the cell centres (1e-5 m/s); the plan and the flown leg
start at the mission's ``start_cell`` counted from the south-west corner; every sample lies in the
region; the live view's state, the report and the exports describe the same run (the exported
estimate equals the leg's estimate to 1e-6 m/s, the CSV has one row per stored sample).
"""

from __future__ import annotations

import csv
import json
import re
import shlex
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from mavlink_helpers import open_in_lockstep

from passt_mav.cli import main

PAGE = Path(__file__).resolve().parent.parent / "docs" / "getting-started.md"
STEP_S = "1"  # vehicle seconds per lockstep step (run --lockstep, added to the page's run line)


def page_blocks() -> tuple[list[str], str]:
    """(the command lines of the page's bash blocks in order, the text of its mine.yaml block)."""
    text = PAGE.read_text()
    blocks = re.findall(r"^```(\w+)([^\n]*)\n(.*?)^```", text, re.DOTALL | re.MULTILINE)
    commands = [
        line.strip()
        for lang, _, body in blocks
        if lang == "bash"
        for line in body.splitlines()
        if line.strip() and not line.strip().startswith("#")
    ]
    yaml_blocks = [body for lang, info, body in blocks if lang == "yaml" and 'title="mine.yaml"' in info]
    assert len(yaml_blocks) == 1, 'the page must hold one ```yaml title="mine.yaml"``` block'
    return commands, yaml_blocks[0]


# the synthetic forecast: u = U0 + DU_DLAT (lat - 47) + DU_DT t_h, v = V0 + DV_DLON (lon + 126), m/s
U0, DU_DLAT, DU_DT, V0, DV_DLON = 0.1, 0.8, 0.004, -0.05, 0.6
LAND = (47.40, -125.55)  # source nodes north-east of this are land (NaN)


def write_forecast(path: Path) -> None:
    import pandas as pd
    import xarray as xr

    times = pd.date_range("2024-10-28T00:00", periods=24, freq="h")
    lat = np.round(np.arange(47.0, 48.0001, 0.04), 4)
    lon = np.round(np.arange(-126.0, -125.0 + 1e-4, 0.04), 4)
    th, la, lo = np.meshgrid(np.arange(24.0), lat, lon, indexing="ij")
    u = U0 + DU_DLAT * (la - 47.0) + DU_DT * th
    v = V0 + DV_DLON * (lo + 126.0) + 0.0 * th
    land = (la > LAND[0]) & (lo > LAND[1])
    u[land] = np.nan
    v[land] = np.nan
    ds = xr.Dataset(
        {
            "water_u": (("time", "lat", "lon"), u.astype("f8"), {"units": "m/s"}),
            "water_v": (("time", "lat", "lon"), v.astype("f8"), {"units": "m/s"}),
        },
        coords={"time": times, "lat": lat, "lon": lon},
    )
    ds.to_netcdf(path)


def lockstep_simulator(argv: list[str], monkeypatch):
    """The page's ``vehicle-sim`` line, parsed by vehicle-sim's parser, as an in-process simulator served in
    lockstep (the caller stops it)."""
    from vehicle_sim import SimConfig, Simulator
    from vehicle_sim import cli as sim_cli

    args = sim_cli.build_parser().parse_args(argv)
    field = sim_cli._load_field(args)
    start = sim_cli._start_time(args.start_time, field)
    sim = Simulator(
        field,
        home=sim_cli._starts(args, field, 1)[0],
        # the compressed boot timeline (vehicle-sim --fast-boot): the same flight, ready sooner
        config=SimConfig.fast(current_rate_hz=args.current_rate, seed=args.seed),
        start_time=start,
        epoch0=sim_cli._utc_at_boot(args.utc_at_boot, field, start, 1.0),
    )
    open_in_lockstep(monkeypatch, sim)
    return sim


def serve_view(argv: list[str]) -> dict:
    """``passt-mav view RUN_DIR`` as a process: its printed address answers /api/state; returns the state."""
    p = subprocess.Popen(
        [sys.executable, "-m", "passt_mav.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        line = p.stdout.readline()
        assert "http://127.0.0.1:" in line, line
        url = next(w for w in line.split() if w.startswith("http://")).split("?token=")[0]  # (reading needs no token)
        end = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(url + "api/state", timeout=20.0) as r:
                    return json.loads(r.read())
            except OSError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.2)
    finally:
        p.terminate()
        p.wait(10)


@pytest.mark.long(
    reason="the tutorial's commands as processes (import, train, plan, a flight, view, report, export): ~45-70 s"
)
def test_the_tutorial_runs_as_written(tmp_path, monkeypatch):
    import xarray as xr

    from passt_mav.fields.field import load_field
    from passt_mav.runs.store import SampleStore

    commands, mission_yaml = page_blocks()
    monkeypatch.chdir(tmp_path)
    write_forecast(tmp_path / "forecast.nc")
    (tmp_path / "mine.yaml").write_text(mission_yaml)
    import yaml

    region = yaml.safe_load(mission_yaml)["region"]
    start_cell = yaml.safe_load(mission_yaml)["start_cell"]
    ran, sims = [], []
    try:
        for line in commands:
            argv = shlex.split(line.removesuffix("&").strip())
            if argv[0] == "vehicle-sim":
                sims.append(lockstep_simulator(argv[1:], monkeypatch))
            elif argv[:2] == ["passt-mav", "view"]:
                state = serve_view(argv[1:])
            else:
                assert argv[0] == "passt-mav", line
                # the simulator is served in lockstep; its steps unpaced (the page's hint paces them for a watcher)
                extra = ["--lockstep", STEP_S, "--speedup-hint", "1000000"] if argv[1] == "run" else []
                assert main(argv[1:] + extra) == 0, line
            ran.append(argv[1] if argv[0] == "passt-mav" else argv[0])
    finally:
        for sim in sims:
            sim.stop()
    assert ran == ["data", "data", "plan", "vehicle-sim", "run", "view", "report", "export", "export"]

    # 1. the import: the region's corner cells and the forecast's values at every water cell centre
    f = load_field(tmp_path / "mine.nc")
    g = f.grid
    assert (g.rows, g.cols) == (region["rows"], region["cols"]) and f.n_times == 24
    assert (g.south, g.west, g.north, g.east) == pytest.approx(
        (region["south"], region["west"], region["north"], region["east"]), abs=1e-9
    )
    lat, lon = g.centres_latlon()
    th = np.asarray(f.times, float)[:, None, None] / 3600.0
    water = ~np.isnan(f.data[0, 0])
    assert 0 < water.sum() < g.rows * g.cols  # the land patch reaches the region's north-east corner
    want_u = U0 + DU_DLAT * (lat - 47.0) + DU_DT * th
    want_v = np.broadcast_to(V0 + DV_DLON * (lon + 126.0), want_u.shape)
    assert np.allclose(f.data[:, 0][:, water], want_u[:, water], atol=1e-5)
    assert np.allclose(f.data[:, 1][:, water], want_v[:, water], atol=1e-5)

    # 2./3. the plan starts at start_cell, row 0 = south: its first waypoint is that cell's centre
    plan = json.loads((tmp_path / "plan1" / "path.json").read_text())
    assert plan["path"][0] == start_cell and len(plan["path"]) == 4 + 1
    r0, c0 = start_cell
    assert plan["waypoints_latlon"][0] == pytest.approx(
        [region["south"] + r0 * (region["north"] - region["south"]) / (region["rows"] - 1),
         region["west"] + c0 * (region["east"] - region["west"]) / (region["cols"] - 1)], abs=1e-9
    )  # fmt: skip

    # 4. one leg flown from the simulator's start cell, sampled inside the region
    run = tmp_path / "runs" / "mine"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "complete" and len(summary["legs"]) == 1
    assert summary["clock"]["source"] == "utc"  # --utc-at-boot field: the vehicle's UTC lies in the forecast
    leg = summary["legs"][0]
    assert np.abs(np.array(leg["path"][0]) - np.array(start_cell)).max() <= 1
    with SampleStore(run / "samples.sqlite", readonly=True) as store:
        samples = store.all()
    assert len(samples) == summary["n_samples"] > 50
    assert g.contains(np.array([s.lat for s in samples]), np.array([s.lon for s in samples]), 0.0).all()
    assert np.isfinite(leg["rmse_passt"]) and np.isfinite(leg["rmse_model"])

    # 5. the view serves this run
    assert state["status"] == "complete" and state["finished"]

    # 6. the report
    assert (run / "report" / "report.html").stat().st_size > 10_000

    # 7. the exports: the leg's estimate, and one CSV row per stored sample
    with (
        xr.open_dataset(run / "export" / "estimate.nc") as ex,
        xr.open_dataset(run / "legs" / "000" / "estimate.nc") as est,
    ):
        assert np.allclose(ex["lat"], est["lat"]) and np.allclose(ex["lon"], est["lon"])
        u_leg, u_exp = np.asarray(est["u"])[-1], np.asarray(ex["u"])[-1]
        assert int(ex["leg"][-1]) == 1  # leg 1 (numbered from 1) is legs/000
    assert np.isfinite(u_leg).sum() == water.sum()  # the land patch stays NaN in the estimate
    assert np.allclose(u_exp, u_leg, atol=1e-6, equal_nan=True)
    with open(run / "export" / "samples.csv", newline="") as fh:
        assert sum(1 for _ in csv.DictReader(fh)) == len(samples)
