"""Cylinder CFD: solver checks against known answers, the shipped data sets, the CLI glue."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import fields as dc_fields
from pathlib import Path

import numpy as np
import pytest

from passt_mav.errors import FieldError
from passt_mav.fields.analysis import pod_energy
from passt_mav.fields.cylinder import (
    CROP,
    CylinderConfig,
    _Lattice,
    generate_cylinder,
    poiseuille_profile_lbm,
    run_cylinder_lbm,
    strouhal_number,
)
from passt_mav.fields.cylinder_cli import DEFAULTS
from passt_mav.fields.cylinder_cli import main as cli_main

REPO = Path(__file__).resolve().parent.parent
ASSETS = REPO / "passt_mav" / "assets"
ST_WINDOW = (0.18, 0.22)  # literature 0.19-0.20 at Re 200 (Williamson 1996; 2-D simulations ~0.195-0.20)


# -- solver on known answers (fast) ------------------------------------------------
@pytest.mark.parametrize("magic", [None, 3 / 16])
def test_poiseuille_profile_matches_analytic(magic):
    # body-force-driven channel between half-way bounce-back walls: parabola u = 4 umax y (H-y) / H^2
    _y, u, ua = poiseuille_profile_lbm(ny=21, tau=0.8, u_max=0.05, steps=4000, magic=magic)
    rel = np.max(np.abs(u - ua)) / ua.max()
    assert rel < 0.01, rel
    # the wall position: the extrapolated profile vanishes half a cell outside the outer fluid rows
    assert abs(u[0] / ua[0] - 1) < 0.02


def test_mass_is_conserved_with_bounce_back_cylinder():
    import torch

    ny, nx = 40, 60
    lat = _Lattice(ny, nx, 0.6, open_x=False)
    yy, xx = np.mgrid[0:ny, 0:nx]
    solid = (xx - 20) ** 2 + (yy - 20) ** 2 <= 6**2
    ux = 0.05 * np.sin(2 * np.pi * yy / ny) * ~solid
    uy = 0.03 * np.cos(2 * np.pi * xx / nx) * ~solid
    lat.init(torch.tensor(ux, dtype=torch.float32), torch.tensor(uy, dtype=torch.float32))
    lat.set_solid(solid)
    fluid = torch.from_numpy(~solid)
    m0 = float(lat.f.sum(0)[fluid].double().sum())
    for _ in range(300):
        lat.step()
    m1 = float(lat.f.sum(0)[fluid].double().sum())
    assert abs(m1 - m0) / m0 < 1e-5


def test_strouhal_number_of_a_known_sine():
    rng = np.random.default_rng(1)
    dt = 0.4
    t = np.arange(500) * dt
    st_true = 0.1973
    x = np.sin(2 * np.pi * st_true / 2.0 * t + 0.3) + 0.2 * rng.standard_normal(t.size) + 0.5
    assert strouhal_number(x, dt) == pytest.approx(st_true, abs=2e-3)
    # a slow imposed oscillation below f_min is ignored
    slow = 3 * np.sin(2 * np.pi * t / (96 * dt))
    assert strouhal_number(x + slow, dt, f_min=2 / (96 * dt)) == pytest.approx(st_true, abs=3e-3)
    with pytest.raises(FieldError):
        strouhal_number([1.0, 2.0], dt)


def test_config_validation_names_the_problem():
    with pytest.raises(FieldError, match="resolution"):
        CylinderConfig(resolution=2).validate()
    with pytest.raises(FieldError, match="dt_out"):
        CylinderConfig(dt_out=0).validate()
    with pytest.raises(FieldError, match="cylinder speed"):
        CylinderConfig(amplitude=2.0, period_snapshots=4).validate()
    with pytest.raises(FieldError, match="dt_out"):
        CylinderConfig(dt_out=0.029, u_lattice=0.2).validate()  # 1 step per snapshot at lattice speed 0.29
    with pytest.raises(FieldError, match="relaxation time"):
        CylinderConfig(resolution=3, u_lattice=0.02).validate()


def test_generation_is_deterministic_and_seeded():
    cfg = CylinderConfig(resolution=4, n_snapshots=6, spin_up=3.0, seed=3)
    a = generate_cylinder(cfg, progress=False)
    # the thread count must not change a bit of the result (element-wise kernels only)
    b = generate_cylinder(CylinderConfig(resolution=4, n_snapshots=6, spin_up=3.0, seed=3, threads=2), progress=False)
    c = generate_cylinder(CylinderConfig(resolution=4, n_snapshots=6, spin_up=3.0, seed=4), progress=False)
    assert a.data_hash() == b.data_hash()
    assert a.data_hash() != c.data_hash()
    assert a.shape == (6, 2, 30, 30) and a.units == "1" and a.time_origin is None
    assert a.dt == pytest.approx(0.4)
    assert np.allclose(a.grid.xs[[0, -1]], CROP[:2]) and np.allclose(a.grid.ys[[0, -1]], CROP[2:4])
    assert a.attrs["seed"] == 3 and a.attrs["config_resolution"] == 4
    # the crop lies in the wake just behind the cylinder: slower than the free stream on average,
    # close to the inflow at the lateral edges
    u = a.data[-1, 0]
    assert np.nanmean(u[12:18, :5]) < 0.8 < np.nanmean(u[[0, -1], :])


def test_oscillating_cylinder_runs_and_moves_the_wall():
    # amplitude 0.5 R, period 16 snapshots = 6.4 time units: peak wall speed ~0.5 U
    cfg = CylinderConfig(resolution=4, n_snapshots=33, spin_up=0.0, amplitude=0.5, period_snapshots=16)
    run = run_cylinder_lbm(cfg, progress=False)
    assert np.all(np.isfinite(run.data))
    # a cylinder moving up and down at 2 pi A / T pushes fluid: the lift follows the motion
    # (added mass ~ pi R^2 A omega^2 ~ 1.5 in C_L units), the dominant signal at the forcing period
    st_forced = strouhal_number(run.lift, run.dt_lift, f_min=0.0)
    f_forced = 1 / (cfg.period_snapshots * cfg.dt_out)
    assert st_forced == pytest.approx(f_forced * 2.0, rel=0.25)


# -- the coarse cylinder still sheds at Re 200 with the right Strouhal number ---------
@pytest.mark.long(reason="a coarse lattice-Boltzmann run long enough to shed a dozen vortices: ~40 s")
def test_coarse_cylinder_sheds_with_literature_strouhal():
    # 4 cells per radius, Re 200 kept: ~3,200 lattice steps on 32k nodes
    cfg = CylinderConfig(resolution=4, n_snapshots=75, spin_up=50.0, seed=0)
    run = run_cylinder_lbm(cfg, progress=False)
    st = strouhal_number(run.lift, run.dt_lift)
    assert ST_WINDOW[0] <= st <= ST_WINDOW[1], st
    # it really sheds: a lift oscillation of order one (literature C_L amplitude ~0.7)
    assert 0.3 < np.std(run.lift) * np.sqrt(2) < 2.0
    st_probe = strouhal_number(run.data[:, 1, 15, 8], cfg.dt_out)
    assert st_probe == pytest.approx(st, rel=0.05)


# -- the shipped data sets ---------------------------------------------------------
def _load(name):
    from passt_mav.fields import load_field

    path = ASSETS / f"{name}.nc"
    assert path.exists(), f"{path} is missing (regenerate: see passt_mav/assets/README.md)"
    return load_field(path)


@pytest.mark.parametrize("name", ["cylinder", "oscillating"])
def test_shipped_file_shape_and_provenance(name):
    f = _load(name)
    assert f.n_times >= 400
    assert f.grid.shape == (30, 30) and f.shape[1] == 2
    assert f.units == "1" and f.time_origin is None
    assert np.all(np.isfinite(f.data))
    assert f.attrs["scenario"] == name
    for key in ("strouhal", "pod4_energy", "command", "seed", "config_resolution", "config_dt_out"):
        assert key in f.attrs
    assert f.dt == pytest.approx(f.attrs["config_dt_out"])
    assert ST_WINDOW[0] <= f.attrs["strouhal"] <= ST_WINDOW[1]


@pytest.mark.parametrize("name", ["cylinder", "oscillating"])
def test_shipped_file_pod_energy_recomputed(name):
    f = _load(name)
    e4 = float(pod_energy(f.data[200:400], 4)[-1])
    assert e4 >= 0.85, e4
    assert e4 == pytest.approx(f.attrs["pod4_energy"], abs=1e-4)


def test_shipped_cylinder_strouhal_from_the_data():
    f = _load("cylinder")
    # v on the wake centre line (x ~ 5 m) of the test window
    st = strouhal_number(f.v[200:400, 15, 8], f.dt)
    assert ST_WINDOW[0] <= st <= ST_WINDOW[1], st
    assert st == pytest.approx(f.attrs["strouhal"], abs=0.01)
    # shedding is fully developed: the fluctuation amplitude in the training and test windows agrees
    a1 = np.std(f.v[200:300, 15, 8])
    a2 = np.std(f.v[300:400, 15, 8])
    assert a1 == pytest.approx(a2, rel=0.05)


def test_shipped_oscillating_period_96_is_visible():
    f = _load("oscillating")
    assert f.attrs["config_period_snapshots"] == 96 and f.attrs["config_amplitude"] > 0
    # the wake swings with the cylinder: the crop-mean v carries the forcing period
    vm = f.v.mean(axis=(1, 2))
    vm = (vm - vm.mean()) * np.hanning(vm.size)
    n = 32 * vm.size
    spec = np.abs(np.fft.rfft(vm, n))
    freq = np.fft.rfftfreq(n)  # cycles per snapshot
    band = (freq > 1 / 400) & (freq < 1 / 40)
    period = 1 / freq[band][np.argmax(spec[band])]
    assert period == pytest.approx(96, rel=0.06), period
    # and shedding is still there at its own frequency
    st = strouhal_number(f.v[:, 15, 8], f.dt, f_min=2 / (96 * f.dt))
    assert ST_WINDOW[0] <= st <= ST_WINDOW[1], st


# -- the CLI glue ------------------------------------------------------------------
def test_cli_defaults_match_the_config():
    cfg = CylinderConfig()
    assert DEFAULTS["resolution"] == cfg.resolution
    assert DEFAULTS["snapshots"] == cfg.n_snapshots
    assert DEFAULTS["dt"] == cfg.dt_out
    assert DEFAULTS["spin_up"] == cfg.spin_up
    assert DEFAULTS["period_snapshots"] == cfg.period_snapshots
    assert DEFAULTS["seed"] == cfg.seed
    assert {f.name for f in dc_fields(cfg)} >= {
        "resolution",
        "n_snapshots",
        "dt_out",
        "spin_up",
        "amplitude",
        "period_snapshots",
        "seed",
    }


def test_cli_bad_input_exits_2(tmp_path, capsys):
    assert cli_main(["cylinder", "--out", str(tmp_path / "x.txt")]) == 2
    assert "--out" in capsys.readouterr().err
    assert cli_main(["cylinder", "--out", str(tmp_path / "x.nc"), "--amplitude", "0.5"]) == 2
    assert cli_main(["oscillating", "--out", str(tmp_path / "x.nc"), "--amplitude", "-1"]) == 2
    assert cli_main(["cylinder", "--out", str(tmp_path / "x.nc"), "--resolution", "2"]) == 2


def test_cli_writes_a_field_and_prints_figures(tmp_path, capsys):
    out = tmp_path / "osc.nc"
    rc = cli_main(
        [
            "oscillating",
            "--out",
            str(out),
            "--resolution",
            "4",
            "--snapshots",
            "8",
            "--spin-up",
            "2",
            "--quiet",
            "--json",
        ]
    )
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["out"] == str(out) and summary["snapshots"] == 8
    from passt_mav.fields import load_field

    f = load_field(out)
    assert f.attrs["config_amplitude"] == 0.5 and f.attrs["scenario"] == "oscillating"
    assert summary["data_hash"] == f.data_hash()


def test_cli_module_imports_no_numpy():
    code = "import sys, passt_mav.fields.cylinder_cli; print('numpy' in sys.modules, 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO).stdout
    assert out.split() == ["False", "False"]


def test_pod_energy_known_answer_and_the_svd():
    """Two orthogonal spatial modes with temporal amplitudes 3 and 1 over whole periods
    carry 0.9 and 0.1 of the fluctuation energy; the Gram-matrix eigenvalues give the
    squared singular values of pod_modes (to 1e-12), NaN (land) cells dropped."""
    from passt_mav.fields.analysis import pod_modes

    t = np.arange(64) * 2 * np.pi / 64
    rr, cc = np.meshgrid(np.arange(6), np.arange(7), indexing="ij")
    phi1 = np.stack([np.sin(np.pi * (rr + 0.5) / 6), np.zeros((6, 7))])
    phi2 = np.stack([np.zeros((6, 7)), np.cos(np.pi * (cc + 0.5) / 7)])
    data = (
        3 * np.sin(t)[:, None, None, None] * phi1 / np.linalg.norm(phi1)
        + np.cos(2 * t)[:, None, None, None] * phi2 / np.linalg.norm(phi2)
        + 5.0
    )
    e = pod_energy(data, 3, cumulative=False)
    np.testing.assert_allclose(e, [0.9, 0.1, 0.0], atol=1e-12)
    land = data.copy()
    land[:, :, 0, 0] = np.nan
    rng = np.random.default_rng(2)
    for d in (
        land + rng.normal(0, 0.1, data.shape),
        rng.normal(size=(5, 2, 8, 9)),
    ):  # more time than features, and fewer
        s, _ = pod_modes(d)
        np.testing.assert_allclose(pod_energy(d, None, cumulative=False), s**2 / np.sum(s**2), atol=1e-12)
