"""`passt-mav data ...`: ocean, import, info, show, cylinder wiring, light imports."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import xarray as xr

import geo
from passt_mav.cli import main
from passt_mav.fields.analysis import pod_energy
from passt_mav.fields.field import FlowField, load_field
from passt_mav.fields.ocean import make_ocean_default


def _cli(capsys, *argv):
    code = main(["data", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_data_parser_imports_only_stdlib():
    # building the data parser (cylinder_cli included) must not pull numpy & co.
    code = (
        "import argparse, sys\n"
        "from passt_mav.commands import data\n"
        "data.add_arguments(argparse.ArgumentParser())\n"
        "heavy = [m for m in ('numpy', 'xarray', 'scipy', 'matplotlib', 'torch', 'sklearn', 'pymavlink') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"heavy modules imported while building the data parser: {r.stdout.strip()}"


def test_ocean_command_writes_the_default(tmp_path, capsys):
    out = tmp_path / "o.nc"
    code, text, _ = _cli(capsys, "ocean", "--out", out, "--seed", 1, "--hours", 24)
    assert code == 0 and f"wrote {out}" in text
    f = load_field(out)
    ref = make_ocean_default(seed=1, hours=24)
    assert f.data.tobytes() == ref.data.tobytes()
    assert f.attrs["seed"] == 1 and f.attrs["command"].startswith("passt-mav data ocean")
    assert f.time_origin == "2018-03-01T00:00:00Z"


def test_info_json_figures(tmp_path, capsys):
    f = make_ocean_default(seed=0, hours=48)
    p = f.to_netcdf(tmp_path / "o.nc")
    code, text, _ = _cli(capsys, "info", p, "--json", "--modes", 3)
    assert code == 0
    info = json.loads(text)
    assert info["shape"] == [48, 2, 30, 30]
    assert info["grid"] == geo.north_atlantic_grid().describe()
    assert info["first_time"] == "2018-03-01T00:00:00Z" and info["last_time"] == "2018-03-02T23:00:00Z"
    assert info["dt"] == 3600.0
    assert info["coverage"]["coverage"] == 1.0
    sp = f.speed()
    assert info["speed"]["max"] == pytest.approx(float(sp.max()), rel=1e-6)
    assert info["speed"]["mean"] == pytest.approx(float(sp.mean()), rel=1e-5)
    np.testing.assert_allclose(info["pod_energy"]["modes"], pod_energy(f.data, 3, cumulative=False), rtol=1e-6)
    assert info["pod_energy"]["cells_used"] == 900
    assert info["strouhal"] is None
    assert info["seed"] == 0


def test_info_text_metric_with_gaps_and_strouhal(tmp_path, capsys):
    grid = geo.MetricRegionGrid(0.0, 9.0, -2.0, 2.0, 5, 10, anchor_lat=40.0, anchor_lon=-63.0, scale=100.0)
    rng = np.random.default_rng(0)
    data = rng.normal(size=(8, 2, 5, 10)).astype(np.float32)
    data[:, :, 2, 1] = np.nan  # body
    data[3, :, 0, 9] = np.nan  # one gap
    f = FlowField(data, grid, np.arange(8) * 0.5, None, "1", {"parameters": {"strouhal": 0.198}})
    p = f.to_netcdf(tmp_path / "m.nc")
    code, text, _ = _cli(capsys, "info", p)
    assert code == 0
    assert "strouhal    0.1980" in text
    assert "48 cells valid at every time" in text  # 50 minus the body and the gap cell
    code, text, _ = _cli(capsys, "info", p, "--json")
    info = json.loads(text)
    keep = np.isfinite(data).all(axis=(0, 1))
    np.testing.assert_allclose(
        info["pod_energy"]["modes"], pod_energy(data[:, :, keep][:, :, :, None], 5, cumulative=False), rtol=1e-6
    )
    assert info["coverage"]["cells_all"] == pytest.approx(48 / 50)


def test_show_png_geographic_and_metric(tmp_path, capsys):
    f = make_ocean_default(seed=0, hours=4)
    p = f.to_netcdf(tmp_path / "o.nc")
    png = tmp_path / "fig" / "o.png"
    code, _text, _ = _cli(capsys, "show", p, "--out", png, "--time", -1)
    assert code == 0 and png.exists()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image as mpimg

    img = mpimg.imread(png)
    assert img.shape[0] > 300 and img.shape[1] > 300
    assert img[..., :3].std() > 0.05  # not a blank canvas
    code, _, err = _cli(capsys, "show", p, "--out", png, "--time", 4)
    assert code == 2 and "out of range" in err

    grid = geo.MetricRegionGrid(0.0, 9.0, -2.0, 2.0, 5, 10, anchor_lat=40.0, anchor_lon=-63.0)
    m = FlowField(np.ones((2, 2, 5, 10), np.float32), grid, [0.0, 1.0], None, "1")
    pm = m.to_netcdf(tmp_path / "m.nc")
    code, _, _ = _cli(capsys, "show", pm, "--out", tmp_path / "m.png")
    assert code == 0 and (tmp_path / "m.png").stat().st_size > 1000


def test_import_hf_radar_prints_coverage(tmp_path, capsys, hf_radar_path):
    out = tmp_path / "radar.nc"
    code, text, _ = _cli(
        capsys,
        "import",
        hf_radar_path,
        "--region",
        "38,-74,41,-69",
        "--grid",
        "20x25",
        "--start",
        "2018-03-01T02:00Z",
        "--hours",
        4,
        "--out",
        out,
    )
    assert code == 0, text
    f = load_field(out)
    assert f.shape == (4, 2, 20, 25)
    assert f.time_origin == "2018-03-01T02:00:00Z"
    assert f"coverage {f.coverage:.1%}" in text
    assert 0.2 < f.coverage < 0.8  # the radar covers the shelf, not the land or the open sea
    assert np.nanmax(f.speed()) < 3.0  # m/s, not cm/s
    code, text, _ = _cli(capsys, "import", hf_radar_path, "--region", "38,-74,41,-69", "--out", out, "--json")
    assert code == 0 and json.loads(text)["coverage"] == pytest.approx(load_field(out).coverage)


def test_import_named_region_default(tmp_path, capsys):
    na = geo.north_atlantic_grid()
    lat = np.arange(38.0, 42.5, 0.1)
    lon = np.arange(-66.0, -60.0, 0.1) % 360.0
    t = pd.Timestamp("2018-03-01") + pd.to_timedelta(np.arange(3), unit="h")
    u = np.full((3, 1, lat.size, lon.size), 12.0)
    ds = xr.Dataset(
        {
            "water_u": (("time", "depth", "lat", "lon"), u, {"units": "cm s-1"}),
            "water_v": (("time", "depth", "lat", "lon"), -u, {"units": "cm s-1"}),
        },
        coords={
            "time": t,
            "depth": ("depth", [0.0]),
            "lat": ("lat", lat, {"units": "degrees_north"}),
            "lon": ("lon", lon, {"units": "degrees_east"}),
        },
    )
    src = tmp_path / "hycom.nc"
    ds.to_netcdf(src)
    out = tmp_path / "na.nc"
    code, text, _ = _cli(capsys, "import", src, "--out", out)  # --region north_atlantic --grid 30x30 by default
    assert code == 0
    f = load_field(out)
    assert f.grid == na
    np.testing.assert_allclose(f.u, 0.12, atol=1e-6)
    np.testing.assert_allclose(f.v, -0.12, atol=1e-6)
    assert "coverage 100.0%" in text


@pytest.mark.parametrize(
    "args,msg",
    [
        (["--region", "1,2,3"], "--region must be"),
        (["--region", "atlantis"], "--region must be"),
        (["--grid", "30by30"], "--grid must look like"),
        (["--region", "41,-64,39,-62"], "south < north"),
        (["--variables", "a"], "--variables must be"),
    ],
)
def test_import_bad_options_exit_2(tmp_path, capsys, args, msg):
    src = tmp_path / "x.nc"
    src.write_text("x")
    code, _, err = _cli(capsys, "import", src, "--out", tmp_path / "o.nc", *args)
    assert code == 2 and msg in err and len(err.strip().splitlines()) == 1


def test_no_subcommand_exit_2(capsys):
    code, _, err = _cli(capsys)
    assert code == 2 and "choose a subcommand" in err


def test_cylinder_wiring(capsys):
    have = importlib.util.find_spec("passt_mav.fields.cylinder_cli") is not None
    if have:
        with pytest.raises(SystemExit) as e:
            main(["data", "cylinder", "--help"])
        assert e.value.code == 0
    else:
        code, _, err = _cli(capsys, "cylinder")
        assert code == 2 and "cylinder_cli.py is missing" in err


def test_import_cli_finds_cf_named_variables_and_names_units_flag(tmp_path, capsys):
    """The 504-hour file of issue 13: CF names as variable names, float32 coordinates, units "1"."""
    from test_import import _paper_grid_file

    src, _, _ = _paper_grid_file(tmp_path / "paper.nc")
    out = tmp_path / "o.nc"
    code, _, err = _cli(capsys, "import", src, "--out", out)
    assert code == 2 and "unknown velocity units '1'" in err and "--units" in err and len(err.strip().splitlines()) == 1
    code, text, _ = _cli(capsys, "import", src, "--units", "m/s", "--out", out)
    assert code == 0 and "imported eastward_sea_water_velocity/northward_sea_water_velocity" in text
    assert "coverage 100.0% of cell-times" in text
    assert load_field(out).coverage == 1.0


def test_model_train_log_into_missing_folder(tmp_path, capsys):
    """A recorded training command (knode_*.json) may log into a folder that does not exist yet."""
    from passt_mav.fields.field import FlowField

    g = geo.RegionGrid(40.0, -63.0, 40.5, -62.5, 6, 6)
    t = np.arange(30.0)
    d = np.stack([np.sin(0.3 * t), np.cos(0.3 * t)], axis=1)[:, :, None, None] * np.ones((1, 2, 6, 6))
    nc = FlowField(d.astype(np.float32), g, t * 3600.0, "2020-01-01T00:00:00Z").to_netcdf(tmp_path / "w.nc")
    log = tmp_path / "new" / "logs" / "train.log"
    rc = main(
        [
            "model",
            "train",
            "--data",
            str(nc),
            "--model",
            "dmd",
            "--start",
            "0",
            "--stop",
            "20",
            "--json",
            "--log",
            str(log),
            "--out",
            str(tmp_path / "ck"),
        ]
    )
    capsys.readouterr()
    assert rc == 0 and log.exists()
    (tmp_path / "afile").write_text("x")
    rc = main(
        [
            "model",
            "train",
            "--data",
            str(nc),
            "--model",
            "dmd",
            "--start",
            "0",
            "--stop",
            "20",
            "--log",
            str(tmp_path / "afile" / "train.log"),
            "--out",
            str(tmp_path / "ck2"),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "--log" in err and len(err.strip().splitlines()) == 1


def test_builtin_rtofs_real_currents_with_land(capsys):
    """builtin:rtofs (real NOAA RTOFS, public domain crop): the mission file validates, and an
    offline PASST run never plans onto land nor puts an estimate there."""
    from pathlib import Path

    from passt_mav.fields.datasets import load_dataset
    from passt_mav.loop.engine import run_offline
    from passt_mav.mission.config import load_mission
    from passt_mav.models.base import make_predictor

    code, text, _ = _cli(capsys, "info", "builtin:rtofs", "--json")
    info = json.loads(text)
    assert code == 0 and info["shape"] == [64, 2, 30, 30] and info["time_origin"] == "2024-10-28T03:00:00Z"
    assert info["coverage"]["cells_all"] == pytest.approx(1 - 0.344444, abs=1e-5)  # 310 land cells
    f = load_dataset("rtofs")
    cfg = load_mission(Path(__file__).resolve().parent.parent / "missions" / "rtofs.yaml")
    assert cfg.grid() == f.grid and cfg.model == "persistence" and not f.land_mask[tuple(cfg.start_cell)]
    res = run_offline(
        f,
        make_predictor("persistence").fit(f),
        start_cell=cfg.start_cell,
        n_steps=8,
        path_length=10,
        steps_per_leg=4,
        noise_std=0.02,
        seed=0,
    )
    cells = np.array([c for leg in res.legs for c in leg["path"]])
    assert len(cells) == 22 and not f.land_mask[cells[:, 0], cells[:, 1]].any()
    land = f.land_mask
    assert np.isnan(res.estimate[:, :, land]).all() and np.isfinite(res.estimate[:, :, ~land]).all()
