"""The run report (passt_mav.analysis.report) and `passt-mav report`, on synthetic run directories."""

from __future__ import annotations

import base64
import os
import re
import shutil
import struct
import subprocess
import types
from pathlib import Path

import numpy as np
import pytest

import geo
from passt_mav.analysis.html_page import pyplot
from passt_mav.analysis.report import load_run, recon_rmse, write_report
from passt_mav.cli import main
from passt_mav.errors import UserError
from passt_mav.fields.field import FlowField
from passt_mav.runs.rundir import RunDir

GRID = geo.RegionGrid(40.0, -63.0, 40.45, -62.45, 10, 12)
T0 = "2018-03-01T00:00:00Z"
SECTIONS = ("track_field.png", "legs.png", "reward.png", "samples.png", "reconstruction.png", "rmse.png", "pod.png")


def _truth_field() -> FlowField:
    """8 hourly snapshots of a smooth eddy plus a uniform drift rotating in time (m/s)."""
    lat, lon = GRID.centres_latlon()
    x = (lon - lon.mean()) / (lon.max() - lon.min())
    y = (lat - lat.mean()) / (lat.max() - lat.min())
    times = np.arange(8) * 3600.0
    data = np.empty((8, 2, GRID.rows, GRID.cols), np.float32)
    for k, t in enumerate(times):
        a = 2 * np.pi * t / (12 * 3600)
        data[k, 0] = -0.6 * y * np.exp(-(x**2 + y**2) * 4) + 0.2 * np.cos(a)
        data[k, 1] = 0.6 * x * np.exp(-(x**2 + y**2) * 4) + 0.2 * np.sin(a)
    return FlowField(data, GRID, times, T0)


def _leg(i: int, cells: list[tuple[int, int]], t_start: float, t_end: float) -> dict:
    path = np.array(cells)
    lat, lon = GRID.cell_to_latlon(path[:, 0], path[:, 1])
    return {
        "index": i,
        "start_cell": list(cells[0]),
        "path": path.tolist(),
        "waypoints": np.column_stack([lat, lon]).tolist(),
        "t_start": t_start,
        "t_end": t_end,
        "planning_s": 1.5 + i,
        "upload_s": 0.25 * (i + 1),
        "duration_s": 600.0 + 10 * i,
        "duration_vehicle_s": 1003.0 + i,  # flown, vehicle s
        "planned_duration_vehicle_s": 987.5 + i,  # expected in the forecast current
        "n_samples": len(cells),
        "rmse_passt": 0.05 - 0.01 * i,
        "rmse_model": 0.08,
        "link": {"rtt_ms": 12.5, "loss": 0.01 * i, "messages": 400 + i, "vehicle_bytes_per_s": 333.5 + i},
        "readings": {"received": 8 + i, "used": len(cells), "dropped_gap": 1 + i},
        # the map the leg was planned on: a ramp eastward (what the report draws under the path)
        "reward_map": np.tile(np.linspace(0.0, 1.0, GRID.cols), (GRID.rows, 1)).round(4).tolist(),
    }


LEG_CELLS = [
    [(1, 1), (2, 2), (3, 3), (3, 4), (4, 5), (5, 6), (6, 6)],
    [(6, 6), (6, 7), (7, 8), (8, 9), (8, 10), (7, 11), (6, 11)],
    [(6, 11), (5, 10), (4, 9), (3, 8), (2, 8), (1, 7), (1, 6)],
]


def _samples_for(legs):
    """One sample per planned cell, measured = truth at the cell at the leg's mid time (+ fixed offsets)."""
    fld = _truth_field()
    out, tb = [], 5000
    for leg in legs:
        tm = 0.5 * (leg["t_start"] + leg["t_end"])
        for r, c in leg["path"]:
            u, v = fld.interp(tm, r, c)
            lat, lon = GRID.cell_to_latlon(r, c)
            out.append(
                dict(
                    time_boot_ms=tb,
                    utc=1.5e9 + tb / 1000,
                    lat=float(lat),
                    lon=float(lon),
                    u=float(u),
                    v=float(v),
                    leg=leg["index"],
                    source="test",
                )
            )
            tb += 1000
    return out


def make_run(root: Path, *, estimate=True, summary_extras=True, field_path=None, n_legs=2) -> RunDir:
    rd = RunDir(root).create()
    fld = _truth_field()
    fpath = field_path or (root / "field.nc")
    fld.to_netcdf(fpath)
    legs = [_leg(i, LEG_CELLS[i], 3600.0 * (i + 1), 3600.0 * (i + 2)) for i in range(n_legs)]
    for leg in legs:
        rd.write_leg(leg["index"], leg)
    if estimate:
        # the reconstruction after leg 1: truth at its t_end plus 0.1 m/s eastward everywhere
        truth = fld.interp(10800.0, *np.meshgrid(np.arange(10.0), np.arange(12.0), indexing="ij"))
        est = np.moveaxis(truth, -1, 0)[None].astype(np.float32)
        est[:, 0] += 0.1
        FlowField(est, GRID, np.array([10800.0]), T0).to_netcdf(rd.leg_dir(1) / "estimate.nc")
    summary = {
        "mission": "synthetic-test",
        "status": "complete",
        "started_utc": "2026-01-01T10:00:00Z",
        "finished_utc": "2026-01-01T10:25:00Z",
        "field": str(fpath),
        "model": "knode",
        "planner": "policy_gradient",
        "reward": "speed",
        "seeds": {"planner": 3, "gp": 4},
        "grid": GRID.describe(),
        "field_time_origin": T0,
        "legs": legs,
        "n_samples": 7 * n_legs,
    }
    if summary_extras:
        summary["rmse"] = {"t": [3600.0, 7200.0, 10800.0], "passt": [0.09, 0.05, 0.04], "model": [0.09, None, 0.085]}
        summary["pod"] = {"truth": [0.6, 0.85, 0.95], "passt": [0.55, 0.8, 0.93], "model": [0.5, 0.7, 0.9]}
    rd.write_summary(summary)
    return rd


@pytest.fixture
def fake_store(monkeypatch):
    """Stands in for passt_mav.runs.store (another engineer's module): SampleStore(path).all()."""
    records: dict[str, list] = {}

    class SampleStore:
        def __init__(self, path):
            self.path = str(path)

        def all(self):
            return [types.SimpleNamespace(**r) for r in records.get(self.path, [])]

        def count(self):
            return len(records.get(self.path, []))

        def close(self):
            pass

    import passt_mav.runs.store as real  # (its Sample stays: the log readers import it)

    monkeypatch.setattr(real, "SampleStore", SampleStore)
    return records


def _embedded_pngs(text: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)]


def test_full_report(tmp_path, fake_store):
    rd = make_run(tmp_path / "run")
    rd.samples_db.write_bytes(b"")  # the store's file; the fake store serves the records
    fake_store[str(rd.samples_db)] = _samples_for(rd.read_summary()["legs"])
    path = write_report(rd.root)
    assert path == rd.report_dir / "report.html"
    text = path.read_text()
    pngs = _embedded_pngs(text)
    assert len(pngs) == len(SECTIONS)
    for name, data in zip(SECTIONS, pngs):
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        assert (rd.report_dir / name).read_bytes() == data  # same figure embedded and on disk
    # the page needs nothing from outside
    assert not re.search(r'(src|href)="(https?:|//|file:)', text)
    assert text.count("not recorded") == 1  # only the telemetry log, which this run lacks
    # reconstruction error: +0.1 m/s on u only -> RMSE over pooled components = sqrt(0.1^2 / 2)
    run = load_run(rd.root)
    assert run.samples is not None and len(run.samples["u"]) == 14
    assert "samples.sqlite (14 samples)" in text
    assert "Telemetry log not recorded" in text
    assert f"{np.sqrt(0.005):.4g}" in text
    # summary and timings tables carry the recorded figures
    for s in (
        "synthetic-test",
        "25.0 min",
        "policy_gradient",
        "10 x 12 cells",
        "12.5",
        "1.0 %",
        "401",
        ">0.75<",
        ">1210<",
        ">7 / 8 (88 %)<",
        ">7 / 9 (78 %)<",
        ">334.5<",
        ">1003<",
        ">987.5<",
        ">988.5<",
    ):  # readings used per leg, the vehicle's bytes/s, each leg's flown and planned vehicle seconds
        assert s in text, s


def test_recon_rmse_known_answer():
    truth = np.zeros((2, 3, 4))
    est = truth.copy()
    est[0] += 0.3
    est[1, 0, 0] = np.nan  # a missing cell is left out, not counted as zero error
    assert recon_rmse(est, truth) == pytest.approx(np.sqrt(0.09 / 2))


def test_minimal_and_partial_runs(tmp_path):
    rd = RunDir(tmp_path / "bare").create()
    rd.write_summary({"mission": "m", "status": "aborted"})
    text = write_report(rd.root).read_text()
    assert _embedded_pngs(text) == []
    assert text.count("not recorded") >= 6
    assert "aborted" in text
    assert not list(rd.report_dir.glob("*.png"))

    # legs written, no summary yet (run in progress), field file missing, no samples, no tlog
    rd2 = make_run(tmp_path / "partial", estimate=False, summary_extras=False)
    rd2.summary_file.unlink()
    (rd2.root / "field.nc").unlink()
    text2 = write_report(rd2.root, out=tmp_path / "out").read_text()
    assert "still in progress" in text2
    assert "legs.png" in text2 and (tmp_path / "out" / "legs.png").exists()
    for missing in ("RMSE over time not recorded", "POD energy not recorded", "samples not recorded"):
        assert missing in text2
    assert "Reconstruction vs truth: reconstruction (estimate.nc) not recorded" in text2


def _write_tlog(path: Path, samples: list[dict], legs: list[dict], late_nack=()) -> None:
    """A tlog (8-byte big-endian µs + MAVLink 2 frame): per leg an accepted upload, then positions and samples.

    Legs in ``late_nack``: the vehicle answers a re-sent item with INVALID_SEQUENCE (13) after the
    last item was sent, before its ACCEPTED, as logged in a loaded demo run (/tmp/demo_final,
    mission 2): the tlog reader takes the 13 for the upload's answer and sees no accepted upload.
    """
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    ml = mavutil.mavlink
    veh, gcs = ml.MAVLink(None, srcSystem=1, srcComponent=1), ml.MAVLink(None, srcSystem=255, srcComponent=190)
    out = bytearray()
    t = [1_700_000_000_000_000]

    def put(msg, enc):
        t[0] += 10_000
        out.extend(struct.pack(">Q", t[0]) + bytes(msg.pack(enc)))

    put(veh.heartbeat_encode(11, 3, 129, 10, 4), veh)
    for leg in legs:
        wps = leg["waypoints"]
        put(gcs.mission_count_encode(1, 1, len(wps) + 1), gcs)
        for seq, (la, lo) in enumerate([wps[0]] + wps):
            put(gcs.mission_item_int_encode(1, 1, seq, 6, 16, 0, 1, 0, 2, 0, 0, int(la * 1e7), int(lo * 1e7), 0), gcs)
        if leg["index"] in late_nack:
            put(veh.mission_ack_encode(255, 190, 13), veh)
        put(veh.mission_ack_encode(255, 190, 0), veh)
        put(veh.mission_current_encode(1, len(wps), 3), veh)
        for s in (x for x in samples if x["leg"] == leg["index"]):
            put(
                veh.global_position_int_encode(
                    s["time_boot_ms"], int(s["lat"] * 1e7), int(s["lon"] * 1e7), 0, 0, 0, 0, 0, 0
                ),
                veh,
            )
            put(veh.named_value_float_encode(s["time_boot_ms"], b"CUR_U", s["u"]), veh)
            put(veh.named_value_float_encode(s["time_boot_ms"], b"CUR_V", s["v"]), veh)
        put(veh.mission_current_encode(len(wps), len(wps), 5), veh)
    path.write_bytes(bytes(out))


def test_samples_and_track_from_tlog(tmp_path):
    rd = make_run(tmp_path / "run")
    legs = rd.read_summary()["legs"]
    samples = _samples_for(legs)
    _write_tlog(rd.tlog, samples, legs)
    run = load_run(rd.root)
    assert run.samples_source == "flight.tlog"
    assert len(run.samples["u"]) == 14
    np.testing.assert_allclose(run.samples["u"], [s["u"] for s in samples], atol=1e-6)
    assert list(run.samples["leg"]) == [s["leg"] for s in samples]
    # executed track of each leg = the positions logged during that leg
    for leg in legs:
        np.testing.assert_allclose(run.leg_tracks[leg["index"]], np.array(leg["waypoints"]), atol=1e-6)
    text = write_report(rd.root).read_text()
    assert "flight.tlog GLOBAL_POSITION_INT (14 points)" in text
    assert "2 uploads, 0 bad frames, 0 bytes skipped" in text
    assert text.count("mission complete") == 2 and "mission 1: 8 items, 7 waypoints, accepted" in text


def test_builtin_field(tmp_path):
    """summary['field'] = 'builtin:ocean' resolves through the dataset registry."""
    rd = make_run(tmp_path / "run", estimate=False)
    s = rd.read_summary()
    s["field"] = "builtin:ocean"
    s["grid"] = geo.north_atlantic_grid().describe()
    rd.write_summary(s)
    run = load_run(rd.root)
    assert run.field is not None and run.field.grid.shape == (30, 30)
    assert "field" not in run.notes
    # a field path relative to the run directory
    s["field"], s["grid"] = "field.nc", GRID.describe()
    rd.write_summary(s)
    run = load_run(rd.root)
    assert run.field is not None and run.field.grid == GRID


def test_errors_and_cli(tmp_path, capsys):
    with pytest.raises(UserError):
        write_report(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="not a run directory"):
        load_run(tmp_path / "empty")
    assert main(["report", str(tmp_path / "empty")]) == 2
    assert "not a run directory" in capsys.readouterr().err
    rd = make_run(tmp_path / "run")
    assert main(["report", str(rd.root), "--out", str(tmp_path / "rep")]) == 0
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert Path(printed) == tmp_path / "rep" / "report.html" and Path(printed).exists()
    bad = RunDir(tmp_path / "badjson").create()
    bad.summary_file.write_text("{not json")
    assert main(["report", str(bad.root)]) == 2


def _distinct_colours(png: Path) -> int:
    import matplotlib.image as mpimg

    img = (mpimg.imread(png)[..., :3] * 255).astype(np.uint8).reshape(-1, 3)
    return len(np.unique(img, axis=0))


@pytest.mark.long(reason="renders a report in headless Chromium: ~16-24 s")
@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium not installed")
def test_renders_in_headless_chromium(tmp_path, fake_store):
    rd = make_run(tmp_path / "run")
    rd.samples_db.write_bytes(b"")
    fake_store[str(rd.samples_db)] = _samples_for(rd.read_summary()["legs"])
    html_path = write_report(rd.root)
    shot = tmp_path / "shot.png"
    cmd = [
        shutil.which("chromium"),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        "--hide-scrollbars",
        f"--user-data-dir={tmp_path / 'profile'}",
        f"--screenshot={shot}",
        "--window-size=1200,2600",
        html_path.resolve().as_uri(),
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    assert shot.exists()
    # a blank or broken page has a handful of colours; colour maps and text give thousands
    assert _distinct_colours(shot) > 500


def test_metric_grid_run(tmp_path):
    """A cylinder-like run: metric grid placed on Earth (rotated), non-dimensional time and units; in m/s
    once the run records its mission's velocity scale."""
    grid = geo.MetricRegionGrid(
        0.0, 9.0, -4.0, 4.0, 9, 10, anchor_lat=40.0, anchor_lon=-63.0, rotation_deg=30.0, scale=500.0
    )
    times = np.arange(6) * 0.4
    _ys, xs = np.meshgrid(grid.ys, grid.xs, indexing="ij")
    data = np.stack([np.stack([1.0 + 0 * xs + 0.1 * np.sin(t), 0.2 * np.sin(xs + t)]) for t in times]).astype(
        np.float32
    )
    data[:, :, 4, 2] = np.nan  # the cylinder: no data inside it
    fpath = tmp_path / "cyl.nc"
    FlowField(data, grid, times, None, units="1").to_netcdf(fpath)
    rd = RunDir(tmp_path / "run").create()
    path = [[1, 1], [2, 2], [3, 3], [3, 4]]
    lat, lon = grid.cell_to_latlon(np.array(path)[:, 0], np.array(path)[:, 1])
    leg = {"index": 0, "path": path, "waypoints": np.column_stack([lat, lon]).tolist(), "t_start": 0.4, "t_end": 1.2}
    FlowField(data[3:4] + np.float32(0.05), grid, times[3:4], None, units="1").to_netcdf(rd.leg_dir(0) / "estimate.nc")
    rd.write_summary(
        {
            "mission": "cyl",
            "status": "complete",
            "field": str(fpath),
            "grid": grid.describe(),
            "field_time_origin": None,
            "legs": [leg],
            "rmse": {"t": [0.4, 0.8, 1.2], "passt": [0.1, 0.08, 0.05], "model": [0.1, 0.1, 0.1]},
        }
    )
    text = write_report(rd.root).read_text()
    assert len(_embedded_pngs(text)) == 4  # all but samples and POD (not recorded)
    # no mission recorded: the figures stay in the field's units, and say so (passt_mav.units)
    # +0.05 on both components everywhere the cylinder is not
    assert "reconstruction RMSE vs truth, leg 1</th><td>0.05 field units" in text
    assert "non-dimensional field time" in text
    # the mission it flew gives the velocity scale (m/s per field unit): the same run in m/s
    s = rd.read_summary()
    rd.write_summary({**s, "config": {"field": {"source": str(fpath), "velocity_scale": 0.5}}})
    text = write_report(rd.root).read_text()
    assert "reconstruction RMSE vs truth, leg 1</th><td>0.025 m/s" in text and "field units" not in text


# -- figures, inspected as matplotlib objects ---------------------------------------------------
def _figure(name: str, run, *extra):
    """Draw one report figure (``_fig_legs`` etc.) of ``run`` and return (figure, pyplot) for inspection."""
    from passt_mav.analysis import report

    plt = pyplot()
    return getattr(report, name)(run, plt, *extra), plt


def _executed_lines(fig) -> dict[int, np.ndarray]:
    """Leg index (0-based, as leg.json) -> (n, 2) lon/lat of the line labelled 'leg N executed' in the legs
    figure (N numbered from 1)."""
    out = {}
    for line in fig.axes[0].get_lines():
        m = re.fullmatch(r"leg (\d+) executed", line.get_label())
        if m:
            out[int(m.group(1)) - 1] = line.get_xydata()
    return out


def test_legs_figure_draws_every_leg_when_the_tlog_misses_an_upload(tmp_path, fake_store):
    """Leg numbers come from the controller's records, not from the n-th upload the tlog shows.

    Leg 1's upload is answered INVALID_SEQUENCE before ACCEPTED, so the tlog reader sees two
    accepted uploads for three legs. Splitting the track by the tlog's uploads drew leg 2's
    positions as leg 1 and nothing for leg 2 (the report on main); split by the vehicle time
    of the store's samples, each leg gets exactly the 7 positions logged while it was flown.
    """
    rd = make_run(tmp_path / "run", n_legs=3)
    legs = rd.read_summary()["legs"]
    samples = _samples_for(legs)
    _write_tlog(rd.tlog, samples, legs, late_nack={1})
    rd.samples_db.write_bytes(b"")
    fake_store[str(rd.samples_db)] = samples
    run = load_run(rd.root)
    # the tlog reader no longer takes the late INVALID_SEQUENCE for the upload's answer (it did, as in the
    # demo run); the legs come from the vehicle time of the store's samples either way
    assert [m.accepted for m in run.tlog.missions] == [True, True, True]
    assert sorted(run.leg_tracks) == [0, 1, 2]
    fig, plt = _figure("_fig_legs", run)
    try:
        lines = _executed_lines(fig)
    finally:
        plt.close(fig)
    assert sorted(lines) == [0, 1, 2]
    for leg in legs:
        wp = np.array(leg["waypoints"])  # a sample (and a position) at every planned cell
        np.testing.assert_allclose(lines[leg["index"]], wp[:, ::-1], atol=1e-6)
    assert "split by vehicle time (3 legs as numbered in samples.sqlite)" in write_report(rd.root).read_text()


def test_legs_split_by_clock_readings_without_a_sample_store(tmp_path):
    """No samples.sqlite: legs that recorded the vehicle time they were planned at span from it to
    the next leg's; the last leg to the end of the log."""
    rd = make_run(tmp_path / "run", n_legs=3)
    s = rd.read_summary()
    legs = s["legs"]
    samples = _samples_for(legs)  # time_boot_ms 5000, 6000, ... one per planned cell
    for leg in legs:
        first = next(x["time_boot_ms"] for x in samples if x["leg"] == leg["index"])
        leg["clock_reading"] = {"time_boot_ms": first - 500, "boot": 0}
    rd.write_summary(s)
    _write_tlog(rd.tlog, samples, legs, late_nack={1})
    run = load_run(rd.root)
    assert run.samples_source == "flight.tlog"
    for leg in legs:
        np.testing.assert_allclose(run.leg_tracks[leg["index"]], np.array(leg["waypoints"]), atol=1e-6)
    assert "3 legs from their clock readings" in run.leg_tracks_source


def _many_samples(n: int, legs: int = 3) -> list[dict]:
    """``n`` samples along a boustrophedon over the test grid, u, v a smooth field in m/s."""
    rng = np.random.default_rng(5)
    k = np.arange(n)
    rows = 0.5 + 8.5 * (k / n)
    cols = 0.5 + 10.5 * np.abs(((k / n * 9) % 2) - 1)
    lat, lon = GRID.cell_to_latlon(rows, cols)
    u = 0.3 + 0.2 * np.sin(cols / 3) + 0.01 * rng.standard_normal(n)
    v = 0.1 * np.cos(rows / 2)
    return [
        dict(
            time_boot_ms=10_000 + 200 * int(j),
            utc=1.5e9 + j,
            lat=float(lat[j]),
            lon=float(lon[j]),
            u=float(u[j]),
            v=float(v[j]),
            leg=int(j * legs // n),
            source="test",
        )
        for j in k
    ]


def test_samples_figure_readable_at_ten_thousand_points(tmp_path, fake_store):
    from matplotlib.collections import PathCollection
    from matplotlib.quiver import Quiver

    rd = make_run(tmp_path / "run")
    rd.samples_db.write_bytes(b"")
    fake_store[str(rd.samples_db)] = recs = _many_samples(10_000)
    run = load_run(rd.root)
    fig, plt = _figure("_fig_samples", run)
    try:
        ax, cax = fig.axes[0], fig.axes[1]
        scat = [c for c in ax.collections if isinstance(c, PathCollection)]
        quiv = [c for c in ax.collections if isinstance(c, Quiver)]
        assert len(scat) == 1 and len(quiv) == 1
        # every sample drawn, coloured by its speed
        assert scat[0].get_offsets().shape == (10_000, 2)
        np.testing.assert_allclose(scat[0].get_array(), [np.hypot(r["u"], r["v"]) for r in recs], rtol=1e-12)
        assert cax.get_ylabel() == "measured speed (m/s)"
        assert 20 <= quiv[0].N <= 400  # one arrow per sample (10^4) made a black blob
        assert ax.get_xlabel() == "longitude (deg E)" and ax.get_ylabel() == "latitude (deg N)"
    finally:
        plt.close(fig)


def test_binned_arrows_known_answers():
    from passt_mav.analysis.report import binned_arrows

    rng = np.random.default_rng(1)
    lat, lon = 40.0 + rng.random(10_000), -63.0 + 1.3 * rng.random(10_000)
    u, v = np.full(10_000, 0.4), np.full(10_000, -0.3)
    blat, blon, bu, bv, count = binned_arrows(lat, lon, u, v, max_arrows=300)
    assert 100 <= len(bu) <= 300 and count.sum() == 10_000
    np.testing.assert_allclose(bu, 0.4, atol=1e-12)  # a uniform flow: every bin mean is that flow
    np.testing.assert_allclose(bv, -0.3, atol=1e-12)
    assert blat.min() >= 40.0 and blat.max() <= 41.0 and blon.min() >= -63.0 and blon.max() <= -61.7
    # two clusters far apart, a handful of points each: one arrow per cluster, at its mean
    blat, blon, bu, bv, count = binned_arrows([0, 0, 10, 10.0], [0, 0, 10, 10.0], [1, 3, 5, 7.0], [0, 0, 0, 0.0])
    np.testing.assert_allclose(sorted(bu), [2.0, 6.0])
    assert sorted(count) == [2, 2]
    assert all(len(x) == 0 for x in binned_arrows([], [], [], []))


def _bar_heights(ax) -> dict[str, list[float]]:
    return {c.get_label(): [b.get_height() for b in c.patches] for c in ax.containers}


def test_rmse_figure_with_the_lawnmower_counterfactual(tmp_path):
    """PASST, model alone and the demo's counterfactual (summary ``counterfactual.lawnmower``, one per
    leg, and ``rmse.lawnmower`` over time) each drawn, labelled, in m/s; a log scale when 20x apart."""
    from passt_mav.analysis.report import _per_leg_rmse

    rd = make_run(tmp_path / "run", n_legs=3)
    s = rd.read_summary()
    s["rmse"] = {
        "t": [7200.0, 10800.0, 14400.0],
        "passt": [0.05, 0.04, 0.02],
        "model": [0.08, 0.08, 0.08],
        "lawnmower": [0.48, 0.49, 0.5],
    }
    s["counterfactual"] = {"lawnmower": [0.48, 0.49, 0.5], "how": "offline: lawnmower legs of the same length"}
    s["legs"][2]["rmse_passt"] = 0.02  # per leg: 0.05, 0.04, 0.02 (the leg records)
    rd.write_summary(s)
    run = load_run(rd.root)
    per_leg = _per_leg_rmse(run)
    fig, plt = _figure("_fig_rmse", run, s["rmse"], per_leg)
    try:
        over, legs_ax = fig.axes
        names = [t.get_text() for t in fig.legends[0].get_texts()]  # one legend for both panels
        assert names == ["PASST", "model alone (from the true initial state)", "lawnmower+GP (counterfactual, offline)"]
        np.testing.assert_allclose(over.get_lines()[2].get_ydata(), [0.48, 0.49, 0.5])
        assert over.get_ylabel() == legs_ax.get_ylabel() == "RMSE (m/s)"
        assert over.get_yscale() == legs_ax.get_yscale() == "log"  # 0.02 .. 0.5
        h = _bar_heights(legs_ax)
        assert list(h) == names
        np.testing.assert_allclose(h["PASST"], [0.05, 0.04, 0.02])
        np.testing.assert_allclose(h["model alone (from the true initial state)"], [0.08] * 3)
        np.testing.assert_allclose(h["lawnmower+GP (counterfactual, offline)"], [0.48, 0.49, 0.5])
        assert [t.get_text() for t in legs_ax.get_xticklabels()] == ["leg 1", "leg 2", "leg 3"]
    finally:
        plt.close(fig)
    text = write_report(rd.root).read_text()
    assert "Lawnmower+GP counterfactual: offline: lawnmower legs of the same length." in text

    # a run without the counterfactual: two bars per leg, linear scale, and the page says why
    del s["counterfactual"], s["rmse"]["lawnmower"]
    rd.write_summary(s)
    run = load_run(rd.root)
    fig, plt = _figure("_fig_rmse", run, s["rmse"], _per_leg_rmse(run))
    try:
        assert list(_bar_heights(fig.axes[1])) == ["PASST", "model alone (from the true initial state)"]
        assert fig.axes[1].get_yscale() == "linear"
    finally:
        plt.close(fig)
    assert "No lawnmower+GP counterfactual for this run" in write_report(rd.root).read_text()


def test_prior_per_leg_table(tmp_path):
    """The prior blend per leg (issue 27, item 6): each leg's weights and evidence (summary.json
    legs[i].gp prior_weights / prior_loglik) in a table; a run without a blend gets no section."""
    rd = make_run(tmp_path / "run", n_legs=2)
    s = rd.read_summary()
    assert "Prior per leg" not in write_report(rd.root).read_text()
    s["legs"][0]["gp"] = {
        "prior_weights": {"model": 0.9667, "persistence": 0.0333, "none": 0.0},
        "prior_loglik": {"model": -12.25, "persistence": -12.5, "none": -480.0},
    }
    s["legs"][1]["gp"] = {"prior_weights": {"model": 0.0, "persistence": 0.0, "none": 1.0}}  # older run: no loglik
    rd.write_summary(s)
    text = write_report(rd.root).read_text()
    assert "<h2>Prior per leg</h2>" in text
    table = text.split("<h2>Prior per leg</h2>")[1].split("</table>")[0]
    rows = table.split("<tr>")[2:]
    assert "weight: persistence" in table and "log likelihood: none (nats)" in table
    assert [c.split("<")[0] for c in rows[0].split('class="num">')[1:]] == [
        "0.967",
        "0.033",
        "0.000",
        "-12.2",
        "-12.5",
        "-480.0",
    ]
    assert rows[1].count("&ndash;") == 3 and ">1.000<" in rows[1]


def test_guard_table_and_alarm_note(tmp_path):
    """The guard per leg (summary.json legs[i].guard): each leg's RMSE at its own samples of the restarted
    forecast and of the model alone (m/s) and the background it kept, legs numbered from 1; an alarm's
    one line ("sampling is not helping: ...") heads the report. A run without a guard gets neither."""
    from passt_mav.loop.guard import guard_message

    rd = make_run(tmp_path / "run", n_legs=2)
    s = rd.read_summary()
    assert "Guard:" not in write_report(rd.root).read_text()
    ok = {"rmse_loop": 0.05, "rmse_open_loop": 0.06, "behind": False, "fallback": False, "alarm": False}
    bad = {"rmse_loop": 0.31, "rmse_open_loop": 0.12, "behind": True, "fallback": True, "alarm": True}
    for rec, g in zip(s["legs"], (ok, bad)):
        g.update(rmse_loop_m_s=g["rmse_loop"], rmse_open_loop_m_s=g["rmse_open_loop"])
        g["message"] = guard_message(g, leg_label=f"leg {int(rec.get('index', 0)) + 1}")
        rec["guard"] = g
    rd.write_summary(s)
    text = write_report(rd.root).read_text()
    head = text.split("<h2>")[0]
    assert '<p class="status warn">sampling is not helping: at leg 2&#x27;s samples' in head
    table = text.split("<h2>Guard: the estimate&#x27;s forecast against the model alone</h2>")[1].split("</table>")[0]
    rows = table.split("<tr>")[2:]
    assert [c.split("<")[0] for c in rows[1].split('class="num">')[1:]] == ["0.3100", "0.1200", "model alone", "yes"]
    assert rows[0].startswith("<td>1</td>") and "restarted forecast" in rows[0]


def test_calibration_table_reliability_plot_and_trivial_maps(tmp_path):
    """Where the truth is known (summary.json legs[i].calibration / .baselines): a per-leg table of the 95 %
    interval's coverage, the NLPD (shown for m/s: + ln(velocity scale) of the field-unit figure), the RMS
    standardised error and the RMSE of the map beside the trivial maps' (m/s), the reliability diagram, and a
    warning line for a leg whose map does not beat a trivial map. A run without them gets none of it."""
    from passt_mav.loop.scoring import leg_scores

    rd = make_run(tmp_path / "run", n_legs=2)
    s = rd.read_summary()
    assert "Calibration:" not in write_report(rd.root).read_text()
    rng = np.random.default_rng(0)
    truth = rng.normal(0, 1, (2, 10, 10))
    good = leg_scores(truth + rng.normal(0, 0.1, truth.shape), np.full(truth.shape, 0.1), truth, truth * 0.5)
    bad = leg_scores(truth + 1.0, np.full(truth.shape, 0.1), truth, truth * 0.5)
    for rec, (cal, base) in zip(s["legs"], (good, bad)):
        rec["calibration"], rec["baselines"] = cal, base
    rd.write_summary(s)
    out = write_report(rd.root)
    text = out.read_text()
    scale = load_run(rd.root).unit.per_field_unit
    assert '<p class="status warn">leg 2: the map does not beat zero current, the forecast&#x27;s time mean</p>' in text
    assert "leg 1: the map does not beat" not in text
    table = text.split("<h2>Calibration: does the map know how wrong it is?</h2>")[1].split("</table>")[0]
    rows = table.split("<tr>")[2:]
    cells = [c.split("<")[0] for c in rows[0].split('class="num">')[1:]]
    assert cells[0] == f"{good[0]['coverage95']:.3f}" and cells[-1] == "yes"
    assert cells[1] == f"{good[0]['nlpd'] + np.log(scale):.3f}"
    assert cells[3] == f"{good[1]['map'] * scale:.4f}" and cells[4] == f"{good[1]['zero'] * scale:.4f}"
    assert rows[1].split('class="num">')[-1].startswith("no")
    assert (out.parent / "calibration.png").stat().st_size > 1000
