"""Inputs a user gets wrong (issue 42, item 5): currents in the wrong units, a region with little
data, a run's two clocks, a mission's start cell the boat is not at.

* ``passt-mav data import`` refuses speeds no surface current has (median above 2.5 m/s or any above
  10 m/s over the valid cells) in one line with the likely units, exit 2, nothing written;
  ``--allow-fast`` imports them; a region with less than half of its cell-times holding data is
  imported with a one-line warning, one with less than a fifth (a region or window that misses the file) is
  refused unless ``--min-coverage`` lowers the floor; ``--units`` other than the file's own units attribute
  are taken with a one-line warning naming both. ``plan`` and ``vehicle-sim`` warn about a too-fast field file.
* One clock for a run's exports: a mission on a field file with a UTC origin (2024-10-28), flown on a
  simulator started the README's way (``vehicle-sim --field FILE.nc``: the vehicle's UTC is *now*) and
  with ``--utc-at-boot field``, in lockstep (simulated time follows the controller): ``samples.csv``,
  ``samples.nc`` and ``estimate.nc`` carry the field's UTC, the vehicle's UTC kept as ``vehicle_utc``.
  Known answer: the simulator starts at the field's first snapshot, so a sample's field time is its
  ``time_boot_ms / 1000`` s after the field's origin under either clock.
* A mission ``start_cell`` the boat is not at: one line on the console and in events.jsonl naming the
  cell the first leg really starts from.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml
from mavlink_helpers import open_in_lockstep

import geo
from passt_mav.cli import main
from passt_mav.fields.field import FlowField
from passt_mav.fields.importers import (
    MAX_MEDIAN_SPEED,
    MAX_SPEED,
    MIN_IMPORT_COVERAGE,
    coverage_check,
    speed_check,
)

ORIGIN = "2024-10-28T03:00:00Z"
ORIGIN_EPOCH = dt.datetime(2024, 10, 28, 3, tzinfo=dt.UTC).timestamp()


# -- import: units and coverage ------------------------------------------------------------------------
def _radar_file(path: Path, *, units: str = "cm/s", speed_cm_s: float = 30.0, spike: float | None = None, gap=0.0):
    """An HF-radar-like file: u/v (time, lat, lon) in ``units`` on a 0.1 deg grid, 4 hourly snapshots,
    u = ``speed_cm_s`` (in the file's numbers) everywhere, v = 0; ``spike`` puts that u in one node;
    ``gap``: the fraction of the lon nodes (west first) that are NaN at every time."""
    lat = np.round(np.linspace(40.0, 41.0, 11), 6)
    lon = np.round(np.linspace(-70.0, -69.0, 11), 6)
    u = np.full((4, lat.size, lon.size), speed_cm_s)
    if spike is not None:
        u[2, 5, 5] = spike
    u[:, :, : int(round(gap * lon.size))] = np.nan
    v = np.where(np.isfinite(u), 0.0, np.nan)
    times = np.datetime64("2018-03-01T00:00") + np.arange(4) * np.timedelta64(1, "h")
    ds = xr.Dataset(
        {"u": (("time", "lat", "lon"), u, {"units": units}), "v": (("time", "lat", "lon"), v, {"units": units})},
        coords={
            "time": times,
            "lat": ("lat", lat, {"units": "degrees_north"}),
            "lon": ("lon", lon, {"units": "degrees_east"}),
        },
    )
    ds.to_netcdf(path)
    return path


def _import(src: Path, out: Path, *extra: str) -> int:
    return main(["data", "import", str(src), "--region=40,-70,41,-69", "--grid", "11x11", "--out", str(out), *extra])


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


@pytest.mark.parametrize(
    "case, extra, hint",
    [
        # a cm/s file read as m/s: median 30 m/s
        ("cm_as_m", ("--units", "m/s"), "cm/s? use --units cm/s"),
        # a mm/s file read as m/s: 300 m/s
        ("mm_as_m", ("--units", "m/s"), "mm/s? use --units mm/s"),
        # a plausible median but one node at 12 m/s
        ("one_spike", (), "max 12 m/s over the valid cells"),
    ],
)
def test_import_refuses_speeds_no_current_has(tmp_path, capsys, case, extra, hint):
    if case == "cm_as_m":
        src = _radar_file(tmp_path / "r.nc", units="cm/s", speed_cm_s=30.0)
    elif case == "mm_as_m":
        src = _radar_file(tmp_path / "r.nc", units="mm/s", speed_cm_s=300.0)
    else:
        src = _radar_file(tmp_path / "r.nc", units="m/s", speed_cm_s=0.3, spike=12.0)
    out = tmp_path / "out.nc"
    assert _import(src, out, *extra) == 2
    line = _one_error_line(capsys)
    assert "speeds no surface current has" in line and hint in line and "--allow-fast" in line
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["r.nc"]
    # --allow-fast takes them as they are
    assert _import(src, out, *extra, "--allow-fast") == 0
    f = FlowField.from_netcdf(out)
    assert float(np.nanmax(f.speed())) > MAX_SPEED or float(np.nanmedian(f.speed())) > MAX_MEDIAN_SPEED
    assert "--allow-fast" in f.attrs["command"]


def test_import_in_the_right_units_is_quiet_and_exact(tmp_path, capsys):
    src = _radar_file(tmp_path / "r.nc", units="cm/s", speed_cm_s=30.0)
    out = tmp_path / "out.nc"
    assert _import(src, out) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and "wrote" in cap.out
    np.testing.assert_allclose(FlowField.from_netcdf(out).u, 0.30, atol=1e-6)


def test_speed_check_thresholds():
    grid = geo.RegionGrid(40.0, -70.0, 40.1, -69.9, 2, 2)

    def field(speeds, units="m s-1"):
        d = np.zeros((1, 2, 2, 2), np.float32)
        d[0, 0] = np.asarray(speeds, np.float32).reshape(2, 2)
        return FlowField(d, grid, [0.0], ORIGIN, units)

    assert speed_check(field([2.4, 2.5, 2.5, 9.9])) is None  # median 2.5, max 9.9: a fast but real current
    problem, units = speed_check(field([2.6, 2.6, 2.6, 2.6]))
    assert "median 2.6 m/s, max 2.6 m/s" in problem and units == "cm/s"
    # one wild value in a plausible field: bad data, no units to suggest
    problem, units = speed_check(field([0.1, 0.1, 0.1, 10.5]))
    assert "median 0.1 m/s, max 10.5 m/s" in problem and units is None
    assert speed_check(field([40.0, 40.0, 40.0, 40.0]))[1] == "cm/s"
    # NaN cells are not counted; a non-dimensional field (the cylinder) is never judged in m/s
    assert speed_check(field([np.nan, np.nan, 0.2, 0.3])) is None
    assert speed_check(field([40.0, 40.0, 40.0, 40.0], units="1")) is None


def test_low_coverage_warns_in_one_line_and_still_imports(tmp_path, capsys):
    src = _radar_file(tmp_path / "r.nc", gap=0.7)  # 8 of 11 lon nodes empty
    out = tmp_path / "out.nc"
    assert _import(src, out) == 0
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    f = FlowField.from_netcdf(out)
    # the grid is the file's own: the 3 columns east of the gap keep their data
    assert f.coverage == pytest.approx(3 / 11)
    assert len(err) == 1 and err[0].startswith("warning: only 27.3 % of the region's cell-times hold data")
    assert "wrote" in cap.out
    assert _import(src, tmp_path / "o2.nc", "--json") == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["warnings"] == [coverage_check(f)] and cap.err.count("warning:") == 1
    # half or more: no warning
    assert _import(_radar_file(tmp_path / "h.nc", gap=0.3), tmp_path / "o3.nc") == 0
    assert capsys.readouterr().err == ""


def test_an_import_with_little_data_is_refused_unless_asked_for(tmp_path, capsys):
    """Below MIN_IMPORT_COVERAGE of the region's cell-times holding data (a region or window that misses the
    file): one line naming the share and --min-coverage, exit 2, nothing written; --min-coverage PERCENT sets
    the floor (0: any share), and the import then warns as any thin region does."""
    src = _radar_file(tmp_path / "r.nc", gap=0.9)  # 10 of 11 lon nodes empty: 1/11 of the cell-times hold data
    out = tmp_path / "out.nc"
    assert MIN_IMPORT_COVERAGE == 0.2
    assert _import(src, out) == 2
    line = _one_error_line(capsys)
    assert "only 9.1 % of the region's cell-times hold data" in line and "below 20 %" in line, line
    assert "--min-coverage 0" in line and str(src) in line
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["r.nc"]
    assert _import(src, out, "--min-coverage", "10") == 2 and "below 10 %" in _one_error_line(capsys)
    assert _import(src, out, "--min-coverage", "0") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: only 9.1 % of the region's cell-times hold data"), err
    f = FlowField.from_netcdf(out)
    assert f.coverage == pytest.approx(1 / 11) and "--min-coverage 0" in f.attrs["command"]
    for bad in ("-1", "101", "nan"):
        assert _import(src, tmp_path / "o2.nc", "--min-coverage", bad) == 2
        assert "--min-coverage" in _one_error_line(capsys)
    assert not (tmp_path / "o2.nc").exists()


def test_the_real_radar_file_on_a_region_it_barely_covers_is_refused(tmp_path, capsys):
    from conftest import SHARED_DATA

    found = sorted(SHARED_DATA.glob("RU_MARA_*.nc"))
    if not found:
        pytest.skip(f"no RU_MARA_*.nc in {SHARED_DATA} (../shared/data is not beside the checkout)")
    out = tmp_path / "radar.nc"
    # the Gulf of Maine's edge of the radar's footprint: 3.7 % of the cell-times hold data
    args = ["data", "import", str(found[0]), "--region=42,-69,43.5,-67", "--grid", "30x30", "--out", str(out)]
    assert main(args) == 2
    line = _one_error_line(capsys)
    assert "only 3.7 % of the region's cell-times hold data" in line and "--min-coverage 0" in line, line
    assert not out.exists()
    assert main([*args, "--min-coverage", "0"]) == 0 and out.exists()


def test_units_that_contradict_the_files_own_are_said(tmp_path, capsys):
    """--units mm/s on a file whose u/v say m/s: the import goes on (--units is there to override a wrong
    attribute) with one warning line naming both and the factor; --units agreeing with the file, in another
    spelling, says nothing."""
    src = _radar_file(tmp_path / "r.nc", units="m/s", speed_cm_s=0.3)
    out = tmp_path / "out.nc"
    assert _import(src, out, "--units", "mm/s") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: --units mm/s"), err
    assert "'m/s'" in err[0] and "1000 times slower" in err[0], err[0]
    np.testing.assert_allclose(FlowField.from_netcdf(out).u, 0.0003, atol=1e-7)
    assert _import(src, tmp_path / "o2.nc", "--units", "mm/s", "--json") == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["warnings"] == [err[0].removeprefix("warning: ")]
    assert _import(src, tmp_path / "o3.nc", "--units", "m s-1") == 0
    assert capsys.readouterr().err == ""


def test_the_real_cm_s_radar_file_read_as_m_s_is_refused(tmp_path, capsys):
    from conftest import SHARED_DATA

    found = sorted(SHARED_DATA.glob("RU_MARA_*.nc"))
    if not found:
        pytest.skip(f"no RU_MARA_*.nc in {SHARED_DATA} (../shared/data is not beside the checkout)")
    out = tmp_path / "radar.nc"
    args = ["data", "import", str(found[0]), "--region=38,-74,41,-69", "--grid", "30x30", "--out", str(out)]
    assert main([*args, "--units", "m/s"]) == 2
    line = _one_error_line(capsys)
    assert "median 17 m/s, max 136 m/s" in line and "cm/s? use --units cm/s" in line
    assert not out.exists()
    # its own units (cm/s in the file): imported, with the coverage warning (42.4 % of cell-times)
    assert main(args) == 0
    assert capsys.readouterr().err.strip() == (
        "warning: only 42.4 % of the region's cell-times hold data (below 50 %); check --region and --start "
        "against the file"
    )


# -- plan and vehicle-sim on a too-fast field file -------------------------------------------------------
def _fast_field_file(path: Path) -> tuple[Path, geo.RegionGrid]:
    grid = geo.RegionGrid(40.0, -70.0, 40.05, -69.95, 6, 6)
    d = np.zeros((3, 2, 6, 6), np.float32)
    d[:, 0] = 30.0  # a cm/s field written as m/s by another tool
    FlowField(d, grid, [0.0, 3600.0, 7200.0], ORIGIN, "m s-1").to_netcdf(path)
    return path, grid


def test_plan_and_vehicle_sim_warn_about_a_too_fast_field(tmp_path, capsys):
    path, grid = _fast_field_file(tmp_path / "fast.nc")
    mission = {
        "name": "fast",
        "region": grid.describe(),
        "field": {"source": str(path)},
        "model": "persistence",
        "planner": {"name": "greedy", "path_length": 2},
        "start_cell": [2, 2],
    }
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mission))
    rc = main(["plan", str(tmp_path / "m.yaml"), "--out", str(tmp_path / "leg.plan")])
    err = capsys.readouterr().err
    assert rc == 0
    warn = [x for x in err.splitlines() if x.startswith("warning:")]
    assert len(warn) == 1 and "median 30 m/s" in warn[0] and "--units cm/s" in warn[0] and str(path) in warn[0]

    from vehicle_sim.cli import _load_field, build_parser

    _load_field(build_parser().parse_args(["--field", str(path)]))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vehicle-sim: warning: the field") and "cm/s" in err[0]


# -- one clock for a run's exports; the start cell ---------------------------------------------------------
# 8x8 cells of ~40 m off Washington, hourly snapshots from 2024-10-28T03:00Z, a slow uniform current
GRID = geo.RegionGrid(47.0, -125.0, 47.0 + 7 * 0.00036, -125.0 + 7 * 0.00053, 8, 8)


def _clock_mission(tmp_path: Path, start_cell) -> Path:
    d = np.zeros((6, 2, 8, 8), np.float32)
    d[:, 0] = 0.05 + 0.01 * np.arange(6)[:, None, None]
    d[:, 1] = 0.02
    FlowField(d, GRID, 3600.0 * np.arange(6), ORIGIN, "m s-1").to_netcdf(tmp_path / "wa.nc")
    mission = {
        "name": "clock",
        "region": GRID.describe(),
        "field": {"source": "wa.nc"},
        "model": "persistence",
        "planner": {"name": "greedy", "path_length": 2},
        "legs": 1,
        "start_cell": list(start_cell),
        "vehicle": {"speed_mps": 3.0},
        "gp": {"background": 0},
    }
    p = tmp_path / "mission.yaml"
    p.write_text(yaml.safe_dump(mission))
    return p


def _fly(tmp_path: Path, monkeypatch, capsys, *, utc_at_boot: str, sim_cell, start_cell):
    """``vehicle-sim --field wa.nc [--utc-at-boot field]`` (in process, lockstep) then ``passt-mav run
    --lockstep``."""
    from vehicle_sim import SimConfig, Simulator

    mission = _clock_mission(tmp_path, start_cell)
    field = FlowField.from_netcdf(tmp_path / "wa.nc")
    home = tuple(float(x) for x in GRID.cell_to_latlon(*sim_cell))
    # vehicle-sim's --utc-at-boot: default now; 'field': the field's UTC at its start time (the first snapshot)
    epoch0 = None if utc_at_boot == "now" else ORIGIN_EPOCH
    sim = Simulator(field, home=home, config=SimConfig.fast(params=(("WP_SPEED", 3.0),), seed=1), epoch0=epoch0)
    open_in_lockstep(monkeypatch, sim)
    out = tmp_path / "run"
    try:
        rc = main(
            ["run", str(mission), "--out", str(out), "--lockstep", "0.5", "--speedup-hint", "1000000", "--no-report"]
        )
    finally:
        sim.stop()
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    return out, cap


@pytest.fixture(scope="module", params=["now", "field"])
def flown(request, tmp_path_factory):
    """One flight per --utc-at-boot; the "now" one starts the boat 3 cells from the mission's start_cell."""
    tmp = tmp_path_factory.mktemp(f"clock_{request.param}")
    mp = pytest.MonkeyPatch()
    cap = _Capture()
    try:
        sim_cell, start_cell = ((4, 4), (1, 4)) if request.param == "now" else ((3, 3), (3, 3))
        out, c = _fly(tmp, mp, cap, utc_at_boot=request.param, sim_cell=sim_cell, start_cell=start_cell)
    finally:
        mp.undo()
    return request.param, out, c, start_cell


class _Capture:
    """capsys for a module fixture: the command's stdout/stderr."""

    def __init__(self):
        import contextlib
        import io

        self.out, self.err = io.StringIO(), io.StringIO()
        self._ctx = (contextlib.redirect_stdout(self.out), contextlib.redirect_stderr(self.err))
        for c in self._ctx:
            c.__enter__()

    def readouterr(self):
        for c in reversed(self._ctx):
            c.__exit__(None, None, None)
        return type("Cap", (), {"out": self.out.getvalue(), "err": self.err.getvalue()})()


def test_exports_carry_the_fields_utc_whichever_utc_the_vehicle_has(flown, tmp_path):
    clock_option, out, _cap, _ = flown
    summary = json.loads((out / "summary.json").read_text())
    assert summary["clock"]["source"] == ("boot" if clock_option == "now" else "utc")
    for fmt, extra, name in (
        ("csv", (), "samples.csv"),
        ("netcdf", ("--samples",), "samples.nc"),
        ("netcdf", (), "estimate.nc"),
    ):
        assert main(["export", str(out), "--format", fmt, *extra, "--out", str(tmp_path / name)]) == 0
    with open(tmp_path / "samples.csv") as fh:
        rows = list(csv.DictReader(fh))
    from passt_mav.analysis.export_geo import CSV_COLUMNS  # (tests/test_export.py checks the names)

    assert rows and list(rows[0]) == CSV_COLUMNS

    def epoch(iso):
        return dt.datetime.fromisoformat(iso).timestamp()

    t_csv = np.array([epoch(r["time_utc"]) for r in rows])
    tv_csv = np.array([epoch(r["vehicle_utc"]) for r in rows])
    with xr.open_dataset(tmp_path / "samples.nc", decode_times=False) as ds:
        t_nc, tv_nc, tb = ds.time.values, ds.vehicle_utc.values, ds.time_boot_ms.values
        assert "field_time" not in ds  # a field with a UTC origin: time is its UTC
        assert ds.time.attrs["long_name"].startswith("the field's UTC")
    with xr.open_dataset(tmp_path / "estimate.nc", decode_times=False) as ds:
        t_est = ds.time.values
    from test_export import assert_cf_clean

    assert_cf_clean(tmp_path / "samples.nc", tmp_path)  # vehicle_utc beside the CF time: still CF-1.8 clean
    # known answer: the simulator starts at the field's first snapshot (field time 0 at boot)
    np.testing.assert_allclose(t_nc, ORIGIN_EPOCH + tb / 1000.0, atol=1e-3)
    np.testing.assert_allclose(t_csv, t_nc, atol=1e-3)
    np.testing.assert_allclose(tv_csv, tv_nc, atol=1e-3)
    np.testing.assert_allclose([float(r["field_time"]) for r in rows], tb / 1000.0, atol=1e-3)
    # every file on the field's day; the estimate after the leg within a snapshot of its samples
    day = dt.datetime(2024, 10, 28, tzinfo=dt.UTC).timestamp()
    assert (day <= t_nc).all() and (t_nc < day + 86400).all() and (day <= t_est).all() and (t_est < day + 86400).all()
    assert t_est.size == 1 and t_nc.min() - 3600.0 <= t_est[0] <= t_nc.max() + 3600.0
    # the vehicle's UTC is kept: the field's with --utc-at-boot field, the machine's now (2026...) by default
    if clock_option == "field":
        # (readings before the vehicle's first SYSTEM_TIME with UTC carry their time of reception)
        known = np.abs(tv_nc - t_nc) < 86400.0
        assert known.sum() >= 0.8 * known.size
        np.testing.assert_allclose(tv_nc[known], t_nc[known], atol=0.01)
    else:
        assert (tv_nc - t_nc).min() > 365 * 86400.0


def test_a_start_cell_the_boat_is_not_at_is_one_line(flown):
    clock_option, out, cap, start_cell = flown
    events = [json.loads(x) for x in (out / "events.jsonl").read_text().splitlines()]
    said = [e["text"] for e in events if "not honoured" in e["text"]]
    console = [x for x in (cap.out + cap.err).splitlines() if "not honoured" in x]
    leg0 = json.loads((out / "summary.json").read_text())["legs"][0]
    if clock_option == "field":  # the boat starts at the mission's start cell: nothing to say
        assert leg0["start_cell"] == list(start_cell) and said == [] and console == []
        return
    assert leg0["start_cell"] == [4, 4]
    assert len(said) == 1 and len(console) == 1
    assert said[0].startswith("start_cell [1, 4] not honoured: leg 1 starts at cell [4, 4]")
    e = next(e for e in events if "not honoured" in e["text"])
    assert e["kind"] == "warning"
    far = float(said[0].split(" m from ")[0].rsplit(" ", 1)[1])
    assert far == pytest.approx(3 * GRID.cell_size_m[0], rel=0.05)


def test_a_fleets_samples_each_take_their_boats_clock(tmp_path):
    """Three boats, each with its own recorded clock (t_boot0 = 100 b s, boat 2 rebooted: its boot 1 at
    5000 s): every sample's time is the field's UTC of its own boat's clock; without the records the
    vehicle's UTC stays the time axis."""
    from test_export import T0_EPOCH, make_run

    from passt_mav.analysis.export import load_run, sample_table
    from passt_mav.runs.store import Sample, SampleStore

    made = make_run(tmp_path / "run", boats=3, legs=2)
    rd = made["rd"]
    with SampleStore(rd.samples_db) as st:  # boat 2 after a reboot: time_boot_ms from 0 again, boot 1
        st.append_many(
            [Sample(500 * k, T0_EPOCH + 9000.0 + k, 40.1, -63.3, 0.1, 0.0, 1, "mav:3/1", boot=1) for k in range(4)]
        )
    no_clock = sample_table(load_run(rd.root))
    assert str(no_clock["time_is"]) == "vehicle" and np.isnan(no_clock["field_time"]).all()
    np.testing.assert_array_equal(no_clock["utc"], no_clock["vehicle_utc"])
    summary = rd.read_summary()
    summary["boats"] = [
        {"boat": b, "clock": {"t_boot0": 100.0 * b, "time_scale": 1.0, **({"later_boots": [5000.0]} if b == 2 else {})}}
        for b in range(3)
    ]
    rd.write_summary(summary)
    c = sample_table(load_run(rd.root))
    assert str(c["time_is"]) == "field" and int((c["boot"] == 1).sum()) == 4
    anchor = np.where(c["boot"] == 1, 5000.0, 100.0 * c["boat"])
    np.testing.assert_allclose(c["field_time"], anchor + c["time_boot_ms"] / 1000.0, atol=1e-9)
    np.testing.assert_allclose(
        c["utc"], dt.datetime(2018, 3, 1, tzinfo=dt.UTC).timestamp() + c["field_time"], atol=1e-6
    )
    assert sorted(c["vehicle_utc"]) == sorted(no_clock["vehicle_utc"])
