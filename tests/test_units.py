"""One unit rule (passt_mav.units): a demo on the cylinder wake (field velocity_scale 0.5 m/s per unit, so
m/s and field units differ by 2x) shows each leg's RMSE in m/s, and the console's leg lines, the final
line, the report, the live view's state and the NetCDF export agree on it.

The leg lines print 4 decimals, so they are compared to their printed precision; the report (6
decimals), the view's state and the export carry the value and are compared to 1e-6.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from passt_mav.units import FIELD_UNITS, MPS, SpeedUnit, run_speed_unit, speed_unit


def test_the_rule_scales_a_mission_field_and_labels_one_without_a_scale():
    assert speed_unit(0.5, "1") == SpeedUnit(0.5, MPS)
    assert speed_unit(None, "m s-1") == SpeedUnit(1.0, MPS)
    assert speed_unit(None, "1") == SpeedUnit(1.0, FIELD_UNITS)
    u = speed_unit(0.5)
    assert u(0.2) == pytest.approx(0.1) and u(None) is None and u.text(0.2) == "0.1000 m/s" and u.text(None) == "n/a"
    # a run: summary.json's mission config first, then the live meta, then the field's own units
    assert run_speed_unit({"config": {"field": {"velocity_scale": 0.25}}}, {"velocity_scale": 9}).per_field_unit == 0.25
    assert run_speed_unit(None, {"velocity_scale": 0.5}) == SpeedUnit(0.5, MPS)
    assert run_speed_unit({}, None, "1").label == FIELD_UNITS


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """``passt-mav demo`` on its default (the oscillating wake), 2 short legs, in process (lockstep: the
    speed-up only paces the wall clock, the figures are the same), and its stdout."""
    import contextlib
    import io

    from passt_mav.cli import main

    out = tmp_path_factory.mktemp("units") / "demo"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["demo", "--legs", "2", "--moves", "8", "--speedup", "1000", "--no-view", "--out", str(out)])
    assert rc == 0, buf.getvalue()[-3000:]
    return out, buf.getvalue()


@pytest.mark.long(reason="a two-leg demo with its report, view and exports: ~25 s")
def test_a_demo_reports_each_legs_rmse_in_m_s_everywhere(demo_run):
    import json

    import xarray as xr

    from passt_mav.view.state import RunState

    out, stdout = demo_run
    s = json.loads((out / "summary.json").read_text())
    vs = s["config"]["field"]["velocity_scale"]
    assert vs == 0.5  # the wake's missions: so m/s and field units differ
    want = {int(r["index"]) + 1: (r["rmse_passt"] * vs, r["rmse_model"] * vs) for r in s["legs"]}
    assert len(want) == 2 and all(p > 0 and m > 0 for p, m in want.values())

    # the console: "leg 1/2: ... RMSE passt 0.0422 m/s model 0.0443 m/s"
    lines = re.findall(r"^leg (\d+)/2: .*RMSE passt ([0-9.]+) m/s model ([0-9.]+) m/s", stdout, re.MULTILINE)
    assert len(lines) == 2, stdout[-3000:]
    for n, p, m in lines:
        assert float(p) == pytest.approx(want[int(n)][0], abs=5.1e-5)
        assert float(m) == pytest.approx(want[int(n)][1], abs=5.1e-5)
    # the final line: the last leg's, in m/s
    fin = re.search(r"final RMSE: PASST ([0-9.]+) m/s, model alone ([0-9.]+) m/s", stdout)
    assert fin, stdout[-2000:]
    assert float(fin.group(1)) == pytest.approx(want[2][0], abs=5.1e-5)
    assert float(fin.group(2)) == pytest.approx(want[2][1], abs=5.1e-5)
    assert "field units" not in stdout

    # the report's per-leg table: "leg 1 | PASST 0.042180 m/s, model alone 0.044310 m/s"
    html = (out / "report" / "report.html").read_text()
    rows = re.findall(r"<th>leg (\d+)</th><td>PASST ([0-9.]+) m/s, model alone ([0-9.]+) m/s</td>", html)
    assert len(rows) == 2
    for n, p, m in rows:
        assert float(p) == pytest.approx(want[int(n)][0], abs=1e-6)
        assert float(m) == pytest.approx(want[int(n)][1], abs=1e-6)
    assert "RMSE (m/s)" in html or "m/s" in html
    assert "non-dimensional)" not in html  # the old label of the measured speeds

    # the live view's state
    snap = RunState(out).snapshot()
    assert snap["units"] == {"label": "m/s", "per_field_unit": 0.5}
    for leg in snap["legs"]:
        n = leg["index"] + 1
        assert leg["rmse_passt"] == pytest.approx(want[n][0], abs=1e-6)
        assert leg["rmse_model"] == pytest.approx(want[n][1], abs=1e-6)
    np.testing.assert_allclose(snap["rmse"]["passt"], [want[1][0], want[2][0]], atol=1e-6)

    # the export: the estimate in m/s (the stored one times the scale) and each leg's RMSE
    from passt_mav.cli import main
    from passt_mav.fields.field import load_field
    from passt_mav.runs.rundir import RunDir

    assert main(["export", str(out), "--format", "netcdf", "--out", str(out / "e.nc")]) == 0
    with xr.open_dataset(out / "e.nc", decode_times=False) as ds:
        assert ds.u.attrs["units"] == "m s-1" and ds.rmse.attrs["units"] == "m s-1"
        legs = [int(x) for x in ds.leg.values]
        np.testing.assert_allclose(ds.rmse.values, [want[n][0] for n in legs], atol=1e-6)
        np.testing.assert_allclose(ds.rmse_model.values, [want[n][1] for n in legs], atol=1e-6)
        stored = load_field(RunDir(out).estimate_file(legs[-1] - 1)).data[0, 0]
        np.testing.assert_allclose(ds.u.values[-1], stored * vs, atol=1e-6, equal_nan=True)
