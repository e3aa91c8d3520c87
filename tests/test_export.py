"""`passt-mav export` (issue 29 item 2): CF-1.8 NetCDF checked by the IOOS compliance checker and
re-imported through `passt-mav data import`, GeoJSON validated against the GeoJSON spec models
(geojson-pydantic), KML parsed, CSV read back; errors one line, exit 2, nothing half-written.

The default tests build a small run directory by hand (three boats, four legs, one pair of legs
at the same field time) so that every count is known; the tests marked ``slow`` export the
demo's own runs (one boat and ``--boats 3``).

The CF checker is ``compliance-checker`` (its ``cf-units`` wheel bundles udunits2). Without it the
checker tests skip, unless ``PASST_REQUIRE_CFCHECK=1`` (set by .ci/run): then they fail.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml

import geo
from passt_mav.cli import main
from passt_mav.fields.field import FlowField, load_field, load_std
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import Sample, SampleStore

ORIGIN = "2018-03-01T00:00:00Z"
T0_EPOCH = 1519862400.0  # 2018-03-01T00:00:00Z
KML = "{http://www.opengis.net/kml/2.2}"


def make_run(root: Path, boats: int = 3, legs: int = 4, metric: bool = False) -> dict:
    """A run directory as the fleet controller leaves it; returns what went in (for exact answers).

    Leg i is flown by boat i % boats, ends at field time 3600 * (i + 1) except that legs 1 and 2
    end together (a fleet's two boats finishing at once), carries a 3-cell path and 2 waypoints.
    ``metric``: a cylinder-like field (data-frame metres placed on the sea, non-dimensional time).
    """
    grid = geo.RegionGrid(40.0, -63.5, 40.35, -63.05, 8, 10)
    origin, units = ORIGIN, "m s-1"
    if metric:
        grid = geo.MetricRegionGrid(
            2.6, 11.4, -4.7, 4.7, 8, 10, anchor_lat=40.2, anchor_lon=-63.1, rotation_deg=30.0, scale=100.0
        )
        origin, units = None, "1"
    rng = np.random.default_rng(0)
    rd = RunDir(root).create()
    vehicles = [{"connect": f"tcp:127.0.0.1:{5760 + 10 * b}", "speed_mps": 2.0} for b in range(boats)]
    mission = {
        "name": "synthetic",
        "region": grid.describe(),
        "field": {"source": "builtin:ocean"},
        "model": "persistence",
        "geofence_margin_m": 300.0,
        "legs": legs,
        **({"vehicles": vehicles} if boats > 1 else {"vehicle": vehicles[0]}),
    }
    rd.mission_file.write_text(yaml.safe_dump(mission))
    rd.write_summary(
        {
            "mission": "synthetic",
            "status": "complete",
            "grid": grid.describe(),
            "model": "persistence",
            "planner": "information",
            "reward": "variance_reduction",
            "field_time_origin": ORIGIN,
        }
    )
    t_end = [3600.0 * (i + 1) for i in range(legs)]
    if legs > 2:
        t_end[2] = t_end[1]
    est = {}
    for i in range(legs):
        cells = [[1 + i, 1], [2 + i, 2], [2 + i, 3]]
        lat, lon = grid.cell_to_latlon(np.array([2 + i, 2 + i]), np.array([2, 3]))
        rec = {
            "index": i,
            "boat": i % boats,
            "path": cells,
            "status": "complete",
            "t_state": t_end[i],
            "waypoints": [[float(a), float(b)] for a, b in zip(lat, lon)],
            "waypoint_seqs": [2, 3],
            "fleet_seq": {"plan": i, "absorb": i},
        }
        rd.write_leg(i, rec)
        state = rng.normal(0.0, 0.3, (1, 2, 8, 10)).astype(np.float32)
        state[:, :, 0, 0] = np.nan  # a land cell
        std = rng.uniform(0.001, 0.05, (1, 2, 8, 10)).astype(np.float32)
        std[:, :, 0, 0] = np.nan
        FlowField(state, grid, [t_end[i]], origin, units).to_netcdf(rd.estimate_file(i), std=std)
        est[i] = (state, std)
    per_boat = [40 + 7 * b for b in range(boats)]
    recs = []
    with SampleStore(rd.samples_db) as st:
        for b, n in enumerate(per_boat):
            for k in range(n):
                lat, lon = grid.fcell_to_latlon(1.0 + 0.1 * k, 1.0 + 0.05 * k + b)
                recs.append(
                    Sample(
                        1000 * k,
                        T0_EPOCH + 5.0 * k + 0.25 * b,
                        float(lat),
                        float(lon),
                        float(rng.normal()),
                        float(rng.normal()),
                        -1 if k == 0 else k // 20,  # each boat's first reading outside any leg
                        f"mav:{b + 1}/1",
                    )
                )
        st.append_many(recs)
    return {
        "rd": rd,
        "grid": grid,
        "estimates": est,
        "t_end": t_end,
        "per_boat": per_boat,
        "samples": recs,
        "legs": legs,
        "boats": boats,
        "margin": 300.0,
    }


@pytest.fixture(scope="module")
def run3(tmp_path_factory):
    return make_run(tmp_path_factory.mktemp("export") / "run")


def cf_check(path: Path, tmp: Path) -> dict:
    """The IOOS compliance checker's CF-1.8 result of ``path`` (its JSON report's counts)."""
    try:
        from compliance_checker.runner import CheckSuite, ComplianceChecker
    except ImportError:
        if os.environ.get("PASST_REQUIRE_CFCHECK") == "1":
            pytest.fail("compliance-checker is not installed and PASST_REQUIRE_CFCHECK=1: pip install -e '.[test]'")
        pytest.skip("compliance-checker not installed (pip install -e '.[test]')")
    CheckSuite.load_all_available_checkers()
    report = tmp / f"{path.stem}_cf.json"
    ComplianceChecker.run_checker(str(path), ["cf:1.8"], 0, "normal", output_filename=str(report), output_format="json")
    return json.loads(report.read_text())["cf:1.8"]


def assert_cf_clean(path: Path, tmp: Path) -> None:
    r = cf_check(path, tmp)
    issues = [m for p in ("high_priorities", "medium_priorities", "low_priorities") for m in r.get(p, [])]
    assert (r["high_count"], r["medium_count"], r["low_count"]) == (0, 0, 0), issues
    assert r["scored_points"] == r["possible_points"] > 50


def export(args: list[str], capsys) -> tuple[int, str, str]:
    rc = main(["export", *args])
    out, err = capsys.readouterr()
    return rc, out, err


# -- NetCDF ----------------------------------------------------------------------------------
def test_estimate_netcdf_is_cf_and_round_trips_through_data_import(run3, tmp_path, capsys):
    out = tmp_path / "estimate.nc"
    rc, text, _ = export([str(run3["rd"].root), "--format", "netcdf", "--out", str(out)], capsys)
    assert rc == 0 and str(out) in text
    assert_cf_clean(out, tmp_path)
    g = run3["grid"]
    back = tmp_path / "back.nc"
    assert (
        main(
            [
                "data",
                "import",
                str(out),
                f"--region={g.south},{g.west},{g.north},{g.east}",
                "--grid",
                f"{g.rows}x{g.cols}",
                "--out",
                str(back),
            ]
        )
        == 0
    )
    f = load_field(back)
    kept = [0, 2, 3]  # legs 1 and 2 end together: leg 2 (absorbed later) is kept
    want = np.concatenate([run3["estimates"][i][0] for i in kept])
    assert f.shape == want.shape
    assert np.array_equal(np.isnan(f.data), np.isnan(want))
    np.testing.assert_allclose(f.data, want, atol=1e-6, equal_nan=True)
    epoch = np.array([T0_EPOCH + run3["t_end"][i] for i in kept])
    np.testing.assert_allclose(f.datetimes().astype("datetime64[ms]").astype(float) / 1000.0, epoch, atol=1e-6)
    # the std travels in the export (u_std / v_std, standard_error) with the leg and boat of each time
    import xarray as xr

    with xr.open_dataset(out) as ds:
        np.testing.assert_allclose(
            np.stack([ds.u_std.values, ds.v_std.values], 1),
            np.concatenate([run3["estimates"][i][1] for i in kept]),
            atol=1e-7,
            equal_nan=True,
        )
        assert ds.u_std.attrs["standard_name"] == "eastward_sea_water_velocity standard_error"
        assert ds.u.attrs["units"] == "m s-1" and ds.u.attrs["grid_mapping"] == "crs"
        # legs numbered from 1 (legs/000 is leg 1), as the console and the report count them
        assert list(ds.leg.values) == [i + 1 for i in kept] and list(ds.boat.values) == [0, 2, 0]
        assert ds.attrs["Conventions"] == "CF-1.8, ACDD-1.3" and ds.attrs["passt_mav_version"]
        assert len(ds.attrs["source_commit"]) in (40, len("unknown"))
        assert "leg 2's estimate" in ds.attrs["comment"]


def test_a_metric_field_keeps_its_data_frame_with_lat_lon_and_field_time(tmp_path, capsys):
    """The cylinder placed on the sea: x/y data-frame metres, 2-D lat/lon, non-dimensional field time."""
    r = make_run(tmp_path / "cyl", boats=1, legs=2, metric=True)
    out = tmp_path / "cyl.nc"
    assert export([str(r["rd"].root), "--out", str(out)], capsys)[0] == 0
    assert_cf_clean(out, tmp_path)
    import xarray as xr

    with xr.open_dataset(out, decode_times=False) as ds:
        assert ds.u.dims == ("field_time", "y", "x") and ds.lat.dims == ("y", "x") and "time" not in ds.variables
        np.testing.assert_allclose(ds.field_time.values, r["t_end"][:2])
        np.testing.assert_allclose(ds.lat.values[3, 4], r["grid"].cell_to_latlon(3, 4)[0], atol=1e-12)
        assert "standard_name" not in ds.u.attrs and ds.u.attrs["units"] == "1"
        np.testing.assert_allclose(
            ds.u.values, np.concatenate([r["estimates"][i][0][:, 0] for i in range(2)]), atol=1e-7, equal_nan=True
        )


def test_samples_netcdf_is_a_cf_trajectory_per_boat(run3, tmp_path, capsys):
    out = tmp_path / "samples.nc"
    rc, _, _ = export([str(run3["rd"].root), "--samples", "--out", str(out)], capsys)
    assert rc == 0
    assert_cf_clean(out, tmp_path)
    import xarray as xr

    with xr.open_dataset(out, decode_times=False) as ds:
        assert ds.attrs["featureType"] == "trajectory"
        assert list(ds.trajectory.values) == [0, 1, 2] and list(ds.rowSize.values) == run3["per_boat"]
        assert ds.time.attrs["units"] == "seconds since 1970-01-01T00:00:00Z"
        start = 0
        for b, n in enumerate(run3["per_boat"]):
            mine = sorted((s for s in run3["samples"] if s.source == f"mav:{b + 1}/1"), key=lambda s: s.utc)
            sl = slice(start, start + n)
            np.testing.assert_allclose(ds.time.values[sl], [s.utc for s in mine], atol=1e-6)
            np.testing.assert_allclose(ds.u.values[sl], [s.u for s in mine], atol=1e-12)
            np.testing.assert_allclose(ds.lat.values[sl], [s.lat for s in mine], atol=1e-12)
            # legs from 1; a reading outside any leg (store index -1) is the fill value: missing once decoded
            want = [s.leg + 1 if s.leg >= 0 else np.nan for s in mine]
            np.testing.assert_array_equal(ds.leg.values[sl], want)
            start += n


# -- GeoJSON / KML / CSV ------------------------------------------------------------------------
def test_geojson_validates_with_one_feature_per_track_path_waypoint_and_the_fence(run3, tmp_path, capsys):
    from geojson_pydantic import FeatureCollection

    out = tmp_path / "run.geojson"
    assert export([str(run3["rd"].root), "--format", "geojson", "--out", str(out)], capsys)[0] == 0
    obj = json.loads(out.read_text())
    FeatureCollection.model_validate(obj)  # RFC 7946 models: closed rings, positions, geometry types
    kinds = [f["properties"]["kind"] for f in obj["features"]]
    assert kinds.count("track") == run3["boats"]
    assert kinds.count("planned_path") == run3["legs"]
    assert kinds.count("waypoint") == 2 * run3["legs"]
    assert kinds.count("geofence") == 1
    fence = next(f for f in obj["features"] if f["properties"]["kind"] == "geofence")
    ring = np.array(fence["geometry"]["coordinates"][0])
    assert np.array_equal(ring[0], ring[-1])
    area2 = np.sum(ring[:-1, 0] * ring[1:, 1] - ring[1:, 0] * ring[:-1, 1])
    assert area2 > 0  # RFC 7946: exterior ring counter-clockwise
    g = run3["grid"]
    assert ring[:, 0].min() < g.west and ring[:, 1].max() > g.north  # the margin lies outside the cell centres
    tracks = [f for f in obj["features"] if f["properties"]["kind"] == "track"]
    assert [len(f["geometry"]["coordinates"]) for f in tracks] == run3["per_boat"]
    first = min((s for s in run3["samples"] if s.source == "mav:1/1"), key=lambda s: s.utc)
    np.testing.assert_allclose(tracks[0]["geometry"]["coordinates"][0], [first.lon, first.lat], atol=1e-7)


def test_kml_parses_with_placemarks_per_boat_leg_waypoint_and_fence(run3, tmp_path, capsys):
    out = tmp_path / "run.kml"
    assert export([str(run3["rd"].root), "--format", "kml", "--out", str(out)], capsys)[0] == 0
    root = ET.parse(out).getroot()
    assert root.tag == f"{KML}kml"
    folders = {f.find(f"{KML}name").text: f for f in root.iter(f"{KML}Folder")}
    assert set(folders) == {"Tracks", "Planned paths", "Waypoints", "Geofence"}
    count = {k: len(f.findall(f"{KML}Placemark")) for k, f in folders.items()}
    assert count == {"Tracks": 3, "Planned paths": 4, "Waypoints": 8, "Geofence": 1}
    assert len(folders["Tracks"].findall(f".//{KML}LineString")) == 3
    assert len(folders["Planned paths"].findall(f".//{KML}LineString")) == 4
    assert len(folders["Waypoints"].findall(f".//{KML}Point")) == 8
    ring = folders["Geofence"].find(f".//{KML}Polygon/{KML}outerBoundaryIs/{KML}LinearRing/{KML}coordinates")
    pts = [tuple(map(float, p.split(","))) for p in ring.text.split()]
    assert pts[0] == pts[-1] and len(pts) >= 5
    assert all(-63.6 < lon < -62.9 and 39.9 < lat < 40.5 and z == 0 for lon, lat, z in pts)


def test_csv_has_one_row_per_sample(run3, tmp_path, capsys):
    out = tmp_path / "samples.csv"
    assert export([str(run3["rd"].root), "--format", "csv", "--out", str(out)], capsys)[0] == 0
    rows = list(csv.DictReader(out.open()))
    from passt_mav.analysis.export_geo import CSV_COLUMNS

    assert (
        list(rows[0])
        == CSV_COLUMNS
        == [
            "time_utc",
            "lat_deg",
            "lon_deg",
            "u_m_s",
            "v_m_s",
            "boat",
            "leg",
            "vehicle_utc",
            "field_time",
        ]
    )
    assert len(rows) == len(run3["samples"])
    assert rows[0]["time_utc"] == "2018-03-01T00:00:00.000Z" and rows[0]["boat"] == "0"
    # this run records no clock (summary.json without one): the vehicle's UTC, field time unknown
    assert rows[0]["vehicle_utc"] == rows[0]["time_utc"] and rows[0]["field_time"] == ""
    assert [sum(r["boat"] == str(b) for r in rows) for b in range(3)] == run3["per_boat"]
    # legs numbered from 1 as the console counts them; a reading outside any leg says so
    assert {r["leg"] for r in rows} <= {"outside"} | {str(i + 1) for i in range(run3["legs"])}
    by_time = sorted(run3["samples"], key=lambda x: (x.source, x.utc))
    assert [r["leg"] for r in rows] == [str(x.leg + 1) if x.leg >= 0 else "outside" for x in by_time]
    s = run3["samples"][1]
    assert float(rows[1]["u_m_s"]) == pytest.approx(s.u, abs=1e-6)
    assert float(rows[1]["lat_deg"]) == pytest.approx(s.lat, abs=1e-7)


def test_default_out_is_under_the_run_and_named(run3, capsys):
    rc, text, _ = export([str(run3["rd"].root), "--format", "csv", "--json"], capsys)
    info = json.loads(text)
    assert rc == 0 and info["rows"] == len(run3["samples"])
    assert Path(info["out"]) == run3["rd"].root / "export" / "samples.csv"


def test_a_run_without_std_exports_without_it_and_says_so(tmp_path, capsys):
    r = make_run(tmp_path / "old", boats=1, legs=2)
    for i in range(2):  # an estimate written before the std was recorded
        p = r["rd"].estimate_file(i)
        f = load_field(p)
        f.to_netcdf(p)
        assert load_std(p) is None
    out = tmp_path / "e.nc"
    assert export([str(r["rd"].root), "--out", str(out)], capsys)[0] == 0
    import xarray as xr

    with xr.open_dataset(out) as ds:
        assert "u_std" not in ds and "posterior std not recorded" in ds.attrs["comment"]
        assert "ancillary_variables" not in ds.u.attrs


# -- errors ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "case", ["missing_run", "not_a_run", "bad_format", "missing_folder", "parent_is_file", "samples_with_csv"]
)
def test_errors_are_one_line_exit_2_and_leave_nothing(run3, tmp_path, capsys, case):
    run = str(run3["rd"].root)
    (tmp_path / "empty").mkdir()
    (tmp_path / "afile").write_text("x")
    args = {
        "missing_run": [str(tmp_path / "nope")],
        "not_a_run": [str(tmp_path / "empty")],
        "bad_format": [run, "--format", "shapefile"],
        "missing_folder": [run, "--out", str(tmp_path / "no" / "dir" / "e.nc")],
        "parent_is_file": [run, "--out", str(tmp_path / "afile" / "e.nc")],
        "samples_with_csv": [run, "--format", "csv", "--samples", "--out", str(tmp_path / "s.csv")],
    }[case]
    before = sorted(p.name for p in tmp_path.rglob("*"))
    rc, out, err = export(args, capsys)
    assert rc == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("passt-mav: error: "), err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_a_failure_while_writing_leaves_no_file(run3, tmp_path, monkeypatch):
    from passt_mav.analysis import export as ex

    def boom(ds, path):
        Path(path).write_bytes(b"half")
        raise OSError("disk full")

    monkeypatch.setattr(ex, "_write_netcdf", boom)
    with pytest.raises(OSError, match="disk full"):
        ex.export_run(run3["rd"].root, "netcdf", tmp_path / "e.nc")
    assert list(tmp_path.iterdir()) == []


def test_export_help_imports_nothing_heavy():
    code = (
        "import sys; from passt_mav.cli import build_parser; build_parser().parse_args(['export', 'x']); "
        "print([m for m in ('torch', 'sklearn', 'pymavlink', 'xarray', 'numpy') if m in sys.modules])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "torch" not in r.stdout and "sklearn" not in r.stdout and "pymavlink" not in r.stdout


# -- the demo's runs (slow) ------------------------------------------------------------------------
@pytest.mark.slow(reason="a demo process per fleet size (one boat, three boats) and every export of each: ~2 min")
@pytest.mark.parametrize("boats", [1, 3])
def test_demo_run_exports(tmp_path, boats):
    """`passt-mav demo` (--boats 1 and 3), then every export: CF clean, std present, round trip to 1e-6,
    GeoJSON/KML counts = boats / legs / waypoints."""
    from geojson_pydantic import FeatureCollection

    run = tmp_path / "demo"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "passt_mav.cli",
            "demo",
            "--field",  # a geographic region (the default demo's wake is a metric one): the round trip
            "builtin:ocean",  # through `data import --region S,W,N,E` below needs its bounds
            "--legs",
            "2",
            "--moves",
            "3",
            "--boats",
            str(boats),
            "--no-report",
            "--out",
            str(run),
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=900,
    )
    rd = RunDir(run)
    legs = rd.read_legs()
    for fmt in ("netcdf", "geojson", "kml", "csv"):
        assert main(["export", str(run), "--format", fmt]) == 0
    assert main(["export", str(run), "--samples"]) == 0
    exp = run / "export"
    assert_cf_clean(exp / "estimate.nc", tmp_path)
    assert_cf_clean(exp / "samples.nc", tmp_path)
    g = geo.grid_from_dict(rd.read_summary()["grid"])
    assert (
        main(
            [
                "data",
                "import",
                str(exp / "estimate.nc"),
                f"--region={g.south},{g.west},{g.north},{g.east}",
                "--grid",
                f"{g.rows}x{g.cols}",
                "--out",
                str(tmp_path / "back.nc"),
            ]
        )
        == 0
    )
    back = load_field(tmp_path / "back.nc")
    import xarray as xr

    with xr.open_dataset(exp / "estimate.nc") as ds:
        kept = [int(x) - 1 for x in ds.leg.values]  # leg numbers from 1 -> legs/NNN
        assert "u_std" in ds and np.nanmax(ds.u_std.values) > 0
    want = np.concatenate([load_field(rd.estimate_file(i)).data for i in kept])
    np.testing.assert_allclose(back.data, want, atol=1e-6, equal_nan=True)
    obj = json.loads((exp / "run.geojson").read_text())
    FeatureCollection.model_validate(obj)
    kinds = [f["properties"]["kind"] for f in obj["features"]]
    assert (kinds.count("track"), kinds.count("planned_path"), kinds.count("geofence")) == (boats, len(legs), 1)
    assert kinds.count("waypoint") == sum(len(r["waypoints"]) for r in legs)
    root = ET.parse(exp / "run.kml").getroot()
    assert len(list(root.iter(f"{KML}Placemark"))) == len(obj["features"])
