"""Every field that enters passes one set of checks, whichever door (issue 55, items 1, 2 and 3).

Doors: ``passt-mav data import``, ``vehicle-sim --field``, a mission's ``field.source`` (``run``),
``evaluate --data`` and ``model train --data``. A project field file with a damaged attribute (``passt_grid``
not JSON or missing keys, ``passt_provenance`` not JSON, garbage time units), a field with no data, infinite
values, absurd speeds, or one snapshot where a time series is needed: one line on stderr naming the file,
exit 2, nothing written, no connection made. A grid or time axis too large for memory says its size and the
limit; a mission file nested thousands of levels deep is one line too.

The Hypothesis fuzz of the field loader at the end mutates a valid file (attributes, dtypes, shapes, fill values,
units, times, truncation) and asserts a valid field or a :class:`~passt_mav.errors.UserError`, never another
exception; ``PASST_FUZZ_EXAMPLES=N`` runs N examples (default 200, about 4 s).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
from pathlib import Path

import netCDF4
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import geo
from passt_mav.cli import main
from passt_mav.errors import FieldError, UserError
from passt_mav.fields import checks
from passt_mav.fields.field import FlowField, load_field

ORIGIN = "2024-10-28T03:00:00Z"
GRID = geo.RegionGrid(47.0, -125.0, 47.0 + 7 * 0.00036, -125.0 + 7 * 0.00053, 8, 8)


def _good(path: Path, data: np.ndarray | None = None, n_times: int = 6) -> Path:
    if data is None:
        data = np.zeros((n_times, 2, 8, 8), np.float32)
        data[:, 0], data[:, 1] = 0.05, 0.02
    FlowField(data, GRID, 3600.0 * np.arange(data.shape[0]), ORIGIN, "m s-1").to_netcdf(path)
    return path


def _set_attr(path: Path, var: str | None, name: str, value) -> None:
    with netCDF4.Dataset(path, "a") as ds:
        (ds if var is None else ds[var]).setncattr(name, value)


def _case(tmp_path: Path, case: str) -> Path:
    """A field file of ``case`` in ``tmp_path/fields`` (see :data:`CASES`)."""
    d = tmp_path / "fields"
    d.mkdir(exist_ok=True)
    p = d / f"{case}.nc"
    base = np.zeros((6, 2, 8, 8), np.float32)
    base[:, 0], base[:, 1] = 0.05, 0.02
    if case == "grid-not-json":
        _set_attr(_good(p), None, "passt_grid", "{not json")
    elif case == "grid-missing-keys":
        _set_attr(_good(p), None, "passt_grid", json.dumps({"kind": "geographic"}))
    elif case == "provenance-not-json":
        _set_attr(_good(p), None, "passt_provenance", "{oops")
    elif case == "time-units-garbage":
        _set_attr(_good(p), "time", "units", "seconds since garbage-date")
    elif case == "all-nan":
        _good(p, np.full_like(base, np.nan))
    elif case == "all-inf":
        _good(p, np.full_like(base, np.inf))
    elif case == "some-inf":
        base[2, 0, 3, 3] = np.inf
        _good(p, base)
    elif case == "absurd-speed":
        _good(p, np.full_like(base, 1e30))
    elif case == "single-snapshot":
        _good(p, base[:1])
    else:
        raise AssertionError(case)
    return p


#: case -> what the one line says
CASES = {
    "grid-not-json": "attribute passt_grid is damaged (not JSON",
    "grid-missing-keys": "attribute passt_grid is damaged (missing 6 required positional arguments",
    "provenance-not-json": "attribute passt_provenance is damaged (not JSON",
    "time-units-garbage": "attribute time:units is damaged (time origin 'garbage-date' is not an ISO time)",
    "all-nan": "holds no data: every value is NaN",
    "all-inf": "has 768 infinite value(s) (a missing value is NaN)",
    "some-inf": "has 1 infinite value(s) (a missing value is NaN)",
    "absurd-speed": "has speeds no flow has: median 1.41e+30, max 1.41e+30 m s-1",
    "single-snapshot": "has a single snapshot; a time series (at least 2 snapshots) is needed",
}


def _one_line(capsys, rc: int, prefix: str, needle: str, path: Path) -> str:
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert rc == 2, (out, err)
    assert len(lines) == 1 and lines[0].startswith(prefix), err
    assert needle in lines[0] and str(path) in lines[0], (needle, lines[0])
    assert "Traceback" not in out + err
    return lines[0]


class _Listener:
    """A TCP port that counts the connections made to it (a vehicle nobody should reach)."""

    def __init__(self):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.sock.settimeout(0.05)
        self.port, self.accepted, self.stop = self.sock.getsockname()[1], 0, threading.Event()
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while not self.stop.is_set():
            try:
                c, _ = self.sock.accept()
                self.accepted += 1
                c.close()
            except OSError:
                pass

    def close(self):
        self.stop.set()
        self.sock.close()


def _mission(tmp_path: Path, source: Path) -> Path:
    m = {
        "name": "doors",
        "region": GRID.describe(),
        "field": {"source": str(source)},
        "model": "persistence",
        "planner": {"name": "greedy", "path_length": 2},
        "legs": 1,
        "start_cell": [2, 2],
        "gp": {"background": 0},
    }
    p = tmp_path / "mission.yaml"
    p.write_text(yaml.safe_dump(m))
    return p


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_missions_bad_field_is_one_line_before_the_run_directory_or_a_link(case, tmp_path, capsys, monkeypatch):
    src = _case(tmp_path, case)
    mission = _mission(tmp_path, src)
    monkeypatch.chdir(tmp_path)
    vehicle = _Listener()
    try:
        rc = main(["run", str(mission), "--connect", f"tcp:127.0.0.1:{vehicle.port}", "--no-report", "--quiet"])
        line = _one_line(capsys, rc, "passt-mav: error: ", CASES[case], src)
    finally:
        vehicle.close()
    assert vehicle.accepted == 0, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fields", "mission.yaml"]  # no runs/ left behind
    rc = main(["run", str(mission), "--connect", f"tcp:127.0.0.1:{vehicle.port}", "--out", str(tmp_path / "r1")])
    _one_line(capsys, rc, "passt-mav: error: ", CASES[case], src)
    assert not (tmp_path / "r1").exists()


@pytest.mark.parametrize("case", sorted(CASES))
def test_vehicle_sim_refuses_a_bad_field_before_it_listens(case, tmp_path, capsys):
    from vehicle_sim.cli import main as sim_main

    src = _case(tmp_path, case)
    rc = sim_main(["--field", str(src), "--listen", "tcp:127.0.0.1:0", "--duration", "1", "--fast-boot", "--quiet"])
    _one_line(capsys, rc, "vehicle-sim: error: ", CASES[case], src)


@pytest.mark.parametrize("case", ["grid-missing-keys", "all-nan", "some-inf", "single-snapshot"])
def test_evaluate_and_train_refuse_a_bad_field_and_write_nothing(case, tmp_path, capsys):
    src = _case(tmp_path, case)
    out = tmp_path / "out"
    rc = main(["evaluate", "--data", str(src), "--model", "persistence", "--trials", "1", "--out", str(out)])
    _one_line(capsys, rc, "passt-mav: error: ", CASES[case], src)
    rc = main(["model", "train", "--data", str(src), "--model", "dmd", "--out", str(out / "m")])
    _one_line(capsys, rc, "passt-mav: error: ", CASES[case], src)
    assert not out.exists()


def test_data_info_still_describes_a_field_with_no_data(tmp_path, capsys):
    src = _case(tmp_path, "all-nan")
    assert main(["data", "info", str(src), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["coverage"]["coverage"] == 0.0
    # a damaged attribute is one line there too
    bad = _case(tmp_path, "grid-not-json")
    _one_line(capsys, main(["data", "info", str(bad)]), "passt-mav: error: ", CASES["grid-not-json"], bad)


# -- data import: the same checks, and the size of the grid ---------------------------------------------------
def _radar(path: Path, values: np.ndarray) -> Path:
    import xarray as xr

    lat = np.round(np.linspace(40.0, 41.0, 11), 6)
    lon = np.round(np.linspace(-70.0, -69.0, 11), 6)
    times = np.datetime64("2018-03-01T00:00") + np.arange(values.shape[0]) * np.timedelta64(1, "h")
    ds = xr.Dataset(
        {
            "u": (("time", "lat", "lon"), values, {"units": "m/s"}),
            "v": (("time", "lat", "lon"), values * 0, {"units": "m/s"}),
        },
        coords={
            "time": times,
            "lat": ("lat", lat, {"units": "degrees_north"}),
            "lon": ("lon", lon, {"units": "degrees_east"}),
        },
    )
    ds.to_netcdf(path)
    return path


def _import(src: Path, out: Path, grid: str = "11x11", *extra) -> int:
    return main(["data", "import", str(src), "--region=40,-70,41,-69", "--grid", grid, "--out", str(out), *extra])


def test_import_of_a_grid_too_large_says_the_size_and_the_limit(tmp_path, capsys):
    src = _radar(tmp_path / "r.nc", np.full((3, 11, 11), 0.3))
    out = tmp_path / "out.nc"
    rc = _import(src, out, "100000x100000")
    line = _one_line(
        capsys, rc, "passt-mav: error: ", "grid too large: 100000x100000 = 10,000,000,000 cells", "--grid 100000x100000"
    )
    assert f"over the limit of {checks.MAX_GRID_CELLS:,} cells" in line
    assert not out.exists()


def test_a_time_axis_too_large_for_memory_says_the_size_and_the_limit(tmp_path, capsys):
    src = _radar(tmp_path / "r.nc", np.full((3, 11, 11), 0.3))
    out = tmp_path / "out.nc"
    rc = _import(src, out, "11x11", "--hours", str(10**20))
    line = _one_line(
        capsys, rc, "passt-mav: error: ", "field too large for memory: 100000000000000000000 snapshots", "--hours"
    )
    assert "over the limit of" in line and "half this machine's memory" in line
    rc = main(["data", "ocean", "--hours", "100000000", "--out", str(out)])
    _one_line(capsys, rc, "passt-mav: error: ", "100000000 snapshots of 30x30 cells need 671 GiB", "--hours 100000000")
    assert not out.exists()


def test_import_refuses_a_field_with_no_data_and_the_allow_fast_import_refuses_absurd_speeds(tmp_path, capsys):
    out = tmp_path / "out.nc"
    src = _radar(tmp_path / "nan.nc", np.full((3, 11, 11), np.nan))
    _one_line(capsys, _import(src, out), "passt-mav: error: ", "holds no data: every value is NaN", src)
    src = _radar(tmp_path / "fast.nc", np.full((3, 11, 11), 5000.0))
    rc = _import(src, out, "11x11", "--allow-fast")
    _one_line(capsys, rc, "passt-mav: error: ", "has speeds no flow has: median 5e+03, max 5e+03 m s-1", src)
    assert not out.exists()


def test_a_field_file_too_large_for_memory_says_the_size_and_the_limit(tmp_path, monkeypatch):
    path = _good(tmp_path / "f.nc")
    monkeypatch.setattr(checks, "max_field_bytes", lambda: 1000)
    with pytest.raises(
        FieldError, match=r"field too large for memory: 6 snapshots of 8x8 cells need 3 KiB, over the limit of 1000 B"
    ):
        load_field(path)


# -- a mission file nested too deep -------------------------------------------------------------------------
@pytest.mark.parametrize("shape", ["flow", "block"])
def test_a_mission_nested_thousands_deep_is_one_line(shape, tmp_path, capsys, monkeypatch):
    if shape == "flow":
        text = "name: deep\nregion: " + "[" * 3000 + "]" * 3000 + "\n"
    else:
        text = "name: deep\nfield:\n" + "".join("  " * (i + 1) + f"k{i}:\n" for i in range(3000))
    p = tmp_path / "deep.yaml"
    p.write_text(text)
    monkeypatch.chdir(tmp_path)
    rc = main(["run", str(p), "--connect", "tcp:127.0.0.1:9"])
    _one_line(capsys, rc, "passt-mav: error: ", "nested too deep for a mission file", p)
    rc = main(["demo", "--mission", str(p), "--out", str(tmp_path / "demo")])
    _one_line(capsys, rc, "passt-mav: error: ", "nested too deep for a mission file", p)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["deep.yaml"]


def test_demo_with_a_mission_that_is_not_yaml_or_not_a_mapping_is_one_line(tmp_path, capsys):
    for name, text, needle in (
        ("bad.yaml", "name: [unclosed\n", "invalid YAML at line 2, column 1"),
        ("list.yaml", "- 1\n", "a mission file is a mapping of keys"),
    ):
        p = tmp_path / name
        p.write_text(text)
        rc = main(["demo", "--mission", str(p), "--out", str(tmp_path / "demo")])
        _one_line(capsys, rc, "passt-mav: error: ", needle, p)
    assert not (tmp_path / "demo").exists()


# -- the fuzz of the loader ---------------------------------------------------------------------------------
_ATTRS = {
    "passt_grid": st.one_of(
        st.text(max_size=20),
        st.sampled_from(["{}", "[]", "null", "1", '{"kind": "metric"}', '{"kind": "x"}', "[" * 3000]),
        st.fixed_dictionaries(
            {},
            optional={
                k: st.one_of(st.floats(allow_nan=True), st.integers(-(10**12), 10**12), st.text(max_size=4), st.none())
                for k in ("south", "west", "north", "east", "rows", "cols", "kind", "x0")
            },
        ).map(json.dumps),
    ),
    "passt_provenance": st.one_of(st.text(max_size=20), st.sampled_from(["[]", "3", '{"a": 1}', "{" * 2000])),
}
_TIME_UNITS = st.one_of(
    st.text(max_size=30),
    st.sampled_from(["1", "", "seconds since 2024-13-45", "seconds since 99999-01-01", "hours since 2024-01-01"]),
    st.builds(lambda s: f"seconds since {s}", st.text(max_size=25)),
)
_NUM = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32), st.sampled_from([1e30, -1e30, 1e10, 9.96921e36])
)


@st.composite
def _mutation(draw):
    """One mutation of a valid file: (kind, args)."""
    kind = draw(
        st.sampled_from(
            [
                "attr",
                "attr-number",
                "delete-attr",
                "time-units",
                "u-units",
                "values",
                "fill",
                "times",
                "shape",
                "dtype",
                "truncate",
            ]
        )
    )
    if kind == "attr":
        name = draw(st.sampled_from(sorted(_ATTRS)))
        return kind, (name, draw(_ATTRS[name]))
    if kind == "attr-number":
        return kind, (draw(st.sampled_from(["passt_grid", "passt_provenance"])), draw(st.integers(-5, 5)))
    if kind == "delete-attr":
        return kind, draw(st.sampled_from(["passt_grid", "passt_provenance", "time:units", "u:units"]))
    if kind in ("time-units", "u-units"):
        return kind, draw(_TIME_UNITS) if kind == "time-units" else draw(
            st.one_of(st.text(max_size=8), st.integers(-(2**31), 2**31))
        )
    if kind == "values":
        return kind, (draw(st.sampled_from(["u", "v"])), draw(st.lists(_NUM, min_size=1, max_size=6)))
    if kind == "fill":
        return kind, draw(st.sampled_from([0.0, 0.05, -9999.0, 1e30]))
    if kind == "times":
        return kind, draw(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=1, max_size=6))
    if kind == "shape":
        return kind, (draw(st.integers(1, 4)), draw(st.integers(1, 9)), draw(st.integers(1, 9)), draw(st.booleans()))
    if kind == "dtype":
        return kind, draw(st.sampled_from(["i1", "i2", "i4", "i8", "u1", "f8", "S1", "str"]))
    return kind, draw(st.floats(0.0, 0.99))


def _apply(path: Path, kind: str, args) -> None:
    if kind == "truncate":
        size = path.stat().st_size
        with open(path, "r+b") as f:
            f.truncate(int(size * args))
        return
    if kind in ("shape", "dtype"):
        _rewrite(path, kind, args)
        return
    with netCDF4.Dataset(path, "a") as ds:
        ds.set_auto_mask(False)
        if kind == "attr":
            ds.setncattr(args[0], args[1])
        elif kind == "attr-number":
            ds.setncattr(args[0], np.int32(args[1]))
        elif kind == "delete-attr":
            var, _, name = args.rpartition(":")
            (ds[var] if var else ds).delncattr(name)
        elif kind == "time-units":
            ds["time"].setncattr("units", args)
        elif kind == "u-units":
            ds["u"].setncattr("units", args if isinstance(args, str) else np.int64(args))
        elif kind == "values":
            name, vals = args
            a = ds[name][:]
            with np.errstate(invalid="ignore", over="ignore"):  # (into an integer variable)
                a.flat[: len(vals)] = np.asarray(vals, np.float32)
            ds[name][:] = a
        elif kind == "fill":
            a = ds["u"][:]
            a[0, 0, 0] = args
            ds["u"][:] = a
        elif kind == "times":
            t = ds["time"][:]
            t[: len(args)] = np.asarray(args[: t.size], np.float64)
            ds["time"][:] = t


def _rewrite(path: Path, kind: str, args) -> None:
    """Write the file again with u of another shape or dtype (attributes kept)."""
    with netCDF4.Dataset(path) as src:
        gattrs = {k: src.getncattr(k) for k in src.ncattrs()}
        t = src["time"][:]
        tattrs = {k: src["time"].getncattr(k) for k in src["time"].ncattrs()}
        uv = {n: np.asarray(src[n][:]) for n in ("u", "v")}
    uv = {n: a if a.dtype.kind in "iuf" else np.zeros(a.shape, np.float32) for n, a in uv.items()}
    path.unlink()
    with netCDF4.Dataset(path, "w") as ds:
        ds.setncatts(gattrs)
        if kind == "shape":
            nt, ny, nx, mismatch_v = args
            ds.createDimension("time", nt)
            ds.createDimension("lat", ny)
            ds.createDimension("lon", nx)
            ds.createDimension("lon2", nx + 1)
            tv = ds.createVariable("time", "f8", ("time",))
            tv.setncatts(tattrs)
            tv[:] = np.arange(nt) * 3600.0
            for n in ("u", "v"):
                dims = ("time", "lat", "lon2") if (n == "v" and mismatch_v) else ("time", "lat", "lon")
                var = ds.createVariable(n, "f4", dims)
                var[:] = 0.1
        else:
            if uv["u"].shape != uv["v"].shape or uv["u"].ndim != 3:
                raise RuntimeError("a file of another shape keeps its dtype")  # (the mutations stop here)
            ds.createDimension("time", uv["u"].shape[0])
            ds.createDimension("lat", uv["u"].shape[1])
            ds.createDimension("lon", uv["u"].shape[2])
            tv = ds.createVariable("time", "f8", ("time",))
            tv.setncatts(tattrs)
            tv[:] = t[: uv["u"].shape[0]]
            for n in ("u", "v"):
                if args == "str":
                    var = ds.createVariable(n, str, ("time", "lat", "lon"))
                    var[:] = np.full(uv[n].shape, "x", dtype=object)
                else:
                    var = ds.createVariable(n, args, ("time", "lat", "lon"))
                    if args == "S1":
                        var[:] = np.full(uv[n].shape, b"a")
                    else:
                        var[:] = np.clip(uv[n] * 10, np.iinfo(args).min if args[0] in "iu" else -1e9, 1e9).astype(args)


FUZZ = {"inputs": 0, "valid": 0, "refused": 0, "kinds": {}}


def test_fuzz_the_field_loader_a_valid_field_or_one_line(tmp_path):
    """Mutated field files: :func:`load_field` and the doors' :func:`checks.check_field` give a field or a UserError
    (one line, no newline), never another exception."""
    good = _good(tmp_path / "good.nc")
    n = int(os.environ.get("PASST_FUZZ_EXAMPLES", "200"))

    @settings(max_examples=n, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
    @given(muts=st.lists(_mutation(), min_size=1, max_size=3))
    def one(muts):
        p = tmp_path / "m.nc"
        shutil.copy(good, p)
        for kind, args in muts:
            FUZZ["kinds"][kind] = FUZZ["kinds"].get(kind, 0) + 1
            try:
                _apply(p, kind, args)
            except (OSError, RuntimeError, ValueError, TypeError, OverflowError):
                break  # a mutation that does not apply to this file (truncated, another dtype or shape): stop here
        FUZZ["inputs"] += 1
        try:
            f = load_field(p)
            checks.check_field(f, str(p), series=True)
        except UserError as exc:
            FUZZ["refused"] += 1
            assert str(exc) and "\n" not in str(exc).strip(), str(exc)
            return
        FUZZ["valid"] += 1
        assert f.data.dtype == np.float32 and np.isfinite(f.data).any() and f.n_times >= 2

    one()
    print(
        f"fuzz: {FUZZ['inputs']} files, {FUZZ['valid']} valid, {FUZZ['refused']} refused in one line; {FUZZ['kinds']}"
    )
    assert FUZZ["inputs"] == n and FUZZ["refused"] > 0
