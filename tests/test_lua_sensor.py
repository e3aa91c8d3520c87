"""The ArduPilot Lua current sensor (vehicle_sim/lua/current_sensor.lua) and its grid file.

Off-vehicle: the script's pure functions run under a real Lua 5.3 (``lupa``, the version
ArduPilot embeds) with the vehicle bindings mocked, and must agree with
``FlowField.sample_latlon`` to 1e-5 m/s (same float32 data, bilinear in space, linear in
time). On-vehicle (marker ``sitl``): ArduRover SITL runs the script with an exported grid and
its CUR_U/CUR_V NAMED_VALUE_FLOAT must match the field at the reported GLOBAL_POSITION_INT.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest

import geo
from passt_mav.cli import main
from passt_mav.commands.data import export_lua_grid, lua_script_path, read_lua_grid
from passt_mav.fields.field import FlowField

SCRIPT = Path(__file__).resolve().parent.parent / "vehicle_sim" / "lua" / "current_sensor.lua"


def _lua():
    lupa = pytest.importorskip("lupa", reason="lupa (Lua 5.3 for Python) is not installed: pip install lupa")
    try:
        from lupa import lua53
    except ImportError:
        pytest.skip("this lupa build has no Lua 5.3 runtime (ArduPilot's Lua version)")
    del lupa
    return lua53.LuaRuntime(unpack_returned_tuples=True)


@pytest.fixture
def lua_lib():
    """The script's function table M (the chunk returns it when CURRENT_SENSOR_LIB is set)."""
    L = _lua()
    assert L.eval("_VERSION") == "Lua 5.3"
    L.globals().CURRENT_SENSOR_LIB = True
    return L, L.execute(SCRIPT.read_text())


def _geo_field(seed=0, land=((2, 3), (5, 0))) -> FlowField:
    g = geo.RegionGrid(40.0, -63.0, 40.5, -62.4, 6, 7)
    d = np.random.default_rng(seed).normal(0.0, 0.3, (5, 2, 6, 7)).astype(np.float32)
    for r, c in land:
        d[:, :, r, c] = np.nan
    return FlowField(d, g, 1000.0 + np.arange(5) * 600.0, "2020-01-01T00:00:00Z")


def _lua_sample(M, reader, t, lat, lon):
    out = M.sample(reader.g, reader.get_block, t, lat, lon)
    return (np.nan, np.nan) if out is None or out[0] is None else out


def test_shipped_script_is_package_data():
    assert lua_script_path() == SCRIPT and SCRIPT.exists()
    import tomllib

    pp = tomllib.loads((SCRIPT.parents[2] / "pyproject.toml").read_text())
    assert any(p.startswith("lua/") for p in pp["tool"]["setuptools"]["package-data"]["vehicle_sim"])


def test_grid_file_layout_round_trip(tmp_path):
    f = _geo_field()
    s = export_lua_grid(f, tmp_path / "g.bin", time_at_boot=1300.0)
    assert s["bytes"] == 128 + 5 * 2 * 6 * 7 * 4 == (tmp_path / "g.bin").stat().st_size
    h = read_lua_grid(tmp_path / "g.bin")
    assert (h["rows"], h["cols"], h["snapshots"], h["header"]) == (6, 7, 5, 128)
    assert h["time_at_boot_s"] == 1300.0 and h["t0_s"] == 1000.0 and h["dt_s"] == 600.0
    assert h["data"].tobytes() == f.data.astype("<f4").tobytes()  # NaN land kept bit for bit
    # lat/lon -> cell map is the grid's own (exact for a lat/lon grid)
    assert h["drdlat"] == pytest.approx(1 / f.grid.dlat) and h["dcdlon"] == pytest.approx(1 / f.grid.dlon)
    assert h["drdlon"] == 0.0 and h["dcdlat"] == 0.0


def test_lua_interpolation_matches_flowfield(tmp_path, lua_lib):
    _L, M = lua_lib
    f = _geo_field()
    export_lua_grid(f, tmp_path / "g.bin")
    reader = M.open_grid(str(tmp_path / "g.bin"))
    assert reader.g.rows == 6 and reader.g.ntimes == 5
    rng = np.random.default_rng(1)
    n = 400
    t = rng.uniform(1000.0, 3400.0, n)
    lat = rng.uniform(39.98, 40.52, n)  # a little outside the grid on every side
    lon = rng.uniform(-63.02, -62.38, n)
    ref = f.sample_latlon(t, lat, lon)
    got = np.array([_lua_sample(M, reader, *a) for a in zip(t, lat, lon)])
    assert np.array_equal(np.isnan(got[:, 0]), np.isnan(ref[:, 0]))  # land and outside: nothing
    assert np.isnan(ref[:, 0]).sum() > 20 and np.isfinite(ref[:, 0]).sum() > 200
    ok = np.isfinite(ref[:, 0])
    np.testing.assert_allclose(got[ok], ref[ok], atol=1e-5, rtol=0)
    # exactly on nodes and snapshot times: the stored float32 values
    for k, r, c in ((0, 0, 0), (4, 5, 6), (2, 3, 4)):
        la, lo = (float(x) for x in f.grid.cell_to_latlon(r, c))
        np.testing.assert_allclose(_lua_sample(M, reader, float(f.times[k]), la, lo), f.data[k, :, r, c], atol=1e-6)
    # outside the time span the first/last snapshot is held (like vehicle_sim)
    la, lo = 40.23, -62.71
    np.testing.assert_allclose(_lua_sample(M, reader, 0.0, la, lo), f.sample_latlon(1000.0, la, lo), atol=1e-6)
    np.testing.assert_allclose(_lua_sample(M, reader, 9e9, la, lo), f.sample_latlon(3400.0, la, lo), atol=1e-6)


def test_lua_metric_field_placed_by_anchor(tmp_path, lua_lib):
    """A metric (cylinder-like) field rotated and scaled onto the sea: u/v come out east/north in m/s."""
    _L, M = lua_lib
    n = 9
    mg = geo.MetricRegionGrid(
        2.6, 11.4, -4.7, 4.7, n, n, anchor_lat=40.2, anchor_lon=-63.1, rotation_deg=30.0, scale=100.0
    )
    rng = np.random.default_rng(2)
    d = (1.0 + rng.normal(0, 0.2, (3, 2, n, n))).astype(np.float32)
    f = FlowField(d, mg, np.array([0.0, 0.4, 0.8]), None, "1")
    vs, ts = 0.5, 200.0
    s = export_lua_grid(f, tmp_path / "c.bin", time_at_boot=0.2, velocity_scale=vs, time_scale=ts)
    assert s["max_map_error_cells"] < 1e-3
    reader = M.open_grid(str(tmp_path / "c.bin"))
    m = 200
    r = rng.uniform(0, n - 1, m)
    c = rng.uniform(0, n - 1, m)
    lat, lon = mg.fcell_to_latlon(r, c)
    t_boot_s = rng.uniform(0.0, 100.0, m)  # vehicle seconds since boot
    t_field = 0.2 + t_boot_s / ts
    ref = f.interp(t_field, r, c)
    ue, vn = mg.velocity_to_local(ref[:, 0], ref[:, 1])
    got = np.array([_lua_sample(M, reader, 0.2 * ts + tb, la, lo) for tb, la, lo in zip(t_boot_s, lat, lon)])
    # the map error (< 1e-3 cell) times the gradient bounds the difference
    np.testing.assert_allclose(got[:, 0], ue * vs, atol=2e-4)
    np.testing.assert_allclose(got[:, 1], vn * vs, atol=2e-4)


@pytest.mark.parametrize(
    "line,expected",
    [
        ("$CUR,0.125,-0.5", (0.125, -0.5)),
        ("$CUR,0.125,-0.5\r", (0.125, -0.5)),
        ("$CUR,1e-2,+2.0*" + f"{np.bitwise_xor.reduce(np.frombuffer(b'CUR,1e-2,+2.0', np.uint8)):02X}", (0.01, 2.0)),
        ("$CUR,0.1,0.2*00", None),  # wrong checksum
        ("CUR,0.1,0.2", None),  # no $
        ("$HDG,0.1,0.2", None),  # another sentence
        ("$CUR,0.1", None),
        ("$CUR,abc,0.2", None),
        ("$CUR,nan,0.2", None),
        ("$CUR,45,0.2", None),  # 45 m/s: not a current
        ("", None),
    ],
)
def test_serial_line_parser(lua_lib, line, expected):
    _L, M = lua_lib
    out = M.parse_cur_line(line)
    if expected is None:
        assert out[0] is None and isinstance(out[1], str)
    else:
        assert out == pytest.approx(expected)


def test_serial_line_assembler(lua_lib):
    _L, M = lua_lib
    got = []
    on_line = got.append
    buf = M.feed_lines("", "$CUR,0.1,0.2\n$CU", on_line)
    assert got == ["$CUR,0.1,0.2"] and buf == "$CU"
    buf = M.feed_lines(buf, "R,0.3,0.4\r\n", on_line)
    assert got[-1] == "$CUR,0.3,0.4\r" and buf == ""
    assert M.parse_cur_line(got[-1]) == pytest.approx((0.3, 0.4))
    assert M.feed_lines("", "x" * 500, on_line) == ""  # garbage without newlines is dropped


_MOCKS = """
MOCK = {ms = 0, lat = nil, lon = nil, sent = {}, texts = {}}
local U32 = {}
U32.__index = U32
function U32.tofloat(self) return self.v end
function millis() return setmetatable({v = MOCK.ms}, U32) end
local Loc = {}
Loc.__index = Loc
function Loc.lat(self) return self.la end
function Loc.lng(self) return self.lo end
ahrs = {}
function ahrs.get_location(self)
  if MOCK.lat == nil then return nil end
  return setmetatable({la = math.floor(MOCK.lat * 1e7 + 0.5), lo = math.floor(MOCK.lon * 1e7 + 0.5)}, Loc)
end
gcs = {}
function gcs.send_named_float(self, name, value) MOCK.sent[#MOCK.sent + 1] = {name, value} end
function gcs.send_text(self, sev, text) MOCK.texts[#MOCK.texts + 1] = text end
"""


def test_vehicle_loop_with_mocked_bindings(tmp_path, monkeypatch):
    """The on-vehicle part: finds scripts/current_grid.bin, waits for a position, sends CUR_U/CUR_V, nothing on land."""
    L = _lua()
    L.execute(_MOCKS)
    monkeypatch.chdir(tmp_path)  # SITL runs scripts with its work directory as cwd
    update, delay = L.execute(SCRIPT.read_text())
    assert delay == 1000
    mock = L.globals().MOCK
    fn, delay = update()  # no grid file yet: say so once, retry in 5 s
    assert delay == 5000 and "no grid file" in mock.texts[1]
    f = _geo_field()
    (tmp_path / "scripts").mkdir()
    export_lua_grid(f, tmp_path / "scripts" / "current_grid.bin", time_at_boot=1200.0)
    fn, delay = fn()  # grid found; no position yet -> nothing sent
    assert delay == 250 and len(mock.sent) == 0 and "grid 6x7, 5 snapshots" in mock.texts[2]
    mock.lat, mock.lon, mock.ms = 40.3345678, -62.5123456, 61_250
    fn, _ = fn()
    sent = [tuple(mock.sent[i + 1].values()) for i in range(len(mock.sent))]
    assert [s[0] for s in sent] == ["CUR_U", "CUR_V"]
    exp = f.sample_latlon(1200.0 + 61.25, 40.3345678, -62.5123456)
    np.testing.assert_allclose([sent[0][1], sent[1][1]], exp, atol=1e-5)
    # on a land cell (2, 3): nothing is sent
    la, lo = (float(x) for x in f.grid.cell_to_latlon(2, 3))
    mock.lat, mock.lon = la + 0.01, lo + 0.01
    fn, _ = fn()
    assert len(mock.sent) == 2


def test_export_lua_cli(tmp_path, capsys):
    f = _geo_field()
    src = f.to_netcdf(tmp_path / "f.nc")
    code = main(
        [
            "data",
            "export-lua",
            str(src),
            "--scripts-dir",
            str(tmp_path / "scr"),
            "--snapshots",
            "1:4",
            "--region=40.05,-62.95,40.45,-62.45",
            "--time-at-boot",
            "1700",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0 and "wrote" in out
    assert (tmp_path / "scr" / "current_sensor.lua").read_text() == SCRIPT.read_text()
    h = read_lua_grid(tmp_path / "scr" / "current_grid.bin")
    assert (h["rows"], h["cols"], h["snapshots"]) == (4, 5, 3)
    assert h["t0_s"] == 1600.0 and h["time_at_boot_s"] == 1700.0
    np.testing.assert_array_equal(h["data"], f.data[1:4, :, 1:5, 1:6])
    # the crop's map: cell (0, 0) of the file is cell (1, 1) of the field
    assert h["lat_ref"] == pytest.approx(f.grid.lats[1]) and h["lon_ref"] == pytest.approx(f.grid.lons[1])


@pytest.mark.parametrize(
    "args,msg",
    [
        (["--snapshots", "a:b"], "--snapshots must be"),
        (["--snapshots", "9:12"], "keeps none"),
        (["--region", "1,2,3"], "--region must be"),
        (["--region=50,-10,51,-9"], "fewer than 2x2"),
        (["--anchor", "40,-63"], "--anchor is for metric fields"),
    ],
)
def test_export_lua_bad_input_exit_2(tmp_path, capsys, args, msg):
    src = _geo_field().to_netcdf(tmp_path / "f.nc")
    code = main(["data", "export-lua", str(src), "--out", str(tmp_path / "x.bin"), *args])
    err = capsys.readouterr().err
    assert code == 2 and msg in err and len(err.strip().splitlines()) == 1


def test_export_lua_metric_with_mission(tmp_path, capsys):
    """builtin:cylinder placed by missions/cylinder.yaml (anchor, scale, velocity/time scales, t0)."""
    mission = Path(__file__).resolve().parent.parent / "missions" / "cylinder.yaml"
    code = main(
        [
            "data",
            "export-lua",
            "builtin:cylinder",
            "--mission",
            str(mission),
            "--snapshots",
            "300:302",
            "--out",
            str(tmp_path / "c.bin"),
            "--json",
        ]
    )
    import json

    s = json.loads(capsys.readouterr().out)
    assert code == 0 and s["snapshots"] == 2 and s["max_map_error_cells"] < 1e-3
    h = read_lua_grid(tmp_path / "c.bin")
    # t0 = 300 of the mission: field time at boot = times[300] * 200 s; snapshots 0.4 * 200 = 80 s apart
    assert h["dt_s"] == pytest.approx(80.0) and h["time_at_boot_s"] == pytest.approx(h["t0_s"])
    assert h["lat_ref"] == pytest.approx(40.2, abs=1e-6) and h["lon_ref"] == pytest.approx(-63.1, abs=1e-6)
    # --anchor moves it; the map keeps its shape (cells per degree at 41 N vs 40.2 N)
    assert (
        main(
            [
                "data",
                "export-lua",
                "builtin:cylinder",
                "--mission",
                str(mission),
                "--snapshots",
                "300:302",
                "--anchor",
                "41,-60",
                "--out",
                str(tmp_path / "a.bin"),
            ]
        )
        == 0
    )
    capsys.readouterr()
    a = read_lua_grid(tmp_path / "a.bin")
    assert a["lat_ref"] == pytest.approx(41.0, abs=1e-6) and a["lon_ref"] == pytest.approx(-60.0, abs=1e-6)
    assert a["drdlat"] == pytest.approx(h["drdlat"], rel=1e-3)
    assert a["dcdlon"] == pytest.approx(h["dcdlon"] * np.cos(np.radians(41.0)) / np.cos(np.radians(40.2)), rel=1e-3)
    np.testing.assert_array_equal(a["data"], h["data"])


# -- on the real firmware ----------------------------------------------------------------
HOME = (40.0, -63.0)


@pytest.mark.sitl
def test_lua_sensor_on_ardurover_sitl(tmp_path, sitl_factory):
    """SITL runs current_sensor.lua: CUR_U/CUR_V arrive (after our heartbeats) and equal the field
    at the reported position and at field time = time_at_boot + time_boot_ms / 1000."""
    n, d = 8, 0.0005  # ~55 m cells around home
    g = geo.RegionGrid(HOME[0] - 3.5 * d, HOME[1] - 3.5 * d, HOME[0] + 3.5 * d, HOME[1] + 3.5 * d, n, n)
    lat, lon = g.centres_latlon()
    times = np.arange(40) * 30.0  # 20 min of field, 30 s snapshots
    u = 0.2 + 200.0 * (lat - HOME[0])[None] + 0.004 * times[:, None, None]  # changes 0.12 m/s per 30 s
    v = -0.1 + 300.0 * (lon - HOME[1])[None] - 0.002 * times[:, None, None]
    f = FlowField(np.stack([u, v], axis=1).astype(np.float32), g, times, "2020-01-01T00:00:00Z")
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    shutil.copy(SCRIPT, scripts / SCRIPT.name)
    t_boot = 17.0
    export_lua_grid(f, tmp_path / "current_grid.bin", time_at_boot=t_boot)
    s = sitl_factory(scripts=scripts, speedup=10)
    # start-sitl copies only *.lua; SITL (and the script) do not start before the first client connects
    shutil.copy(tmp_path / "current_grid.bin", s.workdir / "scripts" / "current_grid.bin")
    m = s.mavlink()
    got: list[tuple[int, str, float]] = []
    pos = None
    texts = []
    try:
        end = time.monotonic() + 120.0
        last_hb = 0.0
        while time.monotonic() < end and len(got) < 60:
            if time.monotonic() - last_hb > 0.5:
                m.mav.heartbeat_send(
                    6, 8, 0, 0, 0
                )  # GCS heartbeat: the vehicle sends named floats only to links it heard
                last_hb = time.monotonic()
            msg = m.recv_match(
                type=["NAMED_VALUE_FLOAT", "GLOBAL_POSITION_INT", "STATUSTEXT"], blocking=True, timeout=0.5
            )
            if msg is None:
                continue
            t = msg.get_type()
            if t == "STATUSTEXT":
                texts.append(msg.text)
            elif t == "GLOBAL_POSITION_INT" and msg.lat != 0:
                pos = (msg.lat * 1e-7, msg.lon * 1e-7, msg.time_boot_ms)
            elif t == "NAMED_VALUE_FLOAT" and msg.name in ("CUR_U", "CUR_V") and pos is not None:
                got.append((msg.time_boot_ms, msg.name, msg.value, pos))
    finally:
        m.close()
    assert any("current_sensor: grid 8x8, 40 snapshots" in x for x in texts), texts
    assert len(got) >= 40, f"{len(got)} CUR_U/CUR_V in 120 s; status texts {texts}; {s.log_tail()}"
    errs = []
    for tb, name, value, (la, lo, _) in got:
        exp = f.sample_latlon(t_boot + tb / 1000.0, la, lo)[0 if name == "CUR_U" else 1]
        errs.append(value - exp)
    # the boat sits at home (position exact to 1e-7 deg); measured max 3e-4 m/s: the script reads
    # millis() up to ~80 ms before the queued NAMED_VALUE_FLOAT is stamped (0.004 m/s per s here)
    assert np.max(np.abs(errs)) < 2e-3, np.max(np.abs(errs))
    tus = [tb for tb, name, *_ in got if name == "CUR_U"]
    rate = (len(tus) - 1) / ((tus[-1] - tus[0]) / 1000.0)
    assert 3.0 < rate < 4.5, rate  # PERIOD_MS 250 in vehicle time
    # the field really changes over the samples' span (so the time mapping was tested)
    assert abs(got[-1][2] - got[0][2]) > 0.01 or (tus[-1] - tus[0]) > 3000


# -- vehicle_sim's own sensor: nothing on land either -------------------------------------
def test_vehicle_sim_sensor_silent_on_land():
    """builtin:rtofs: a boat on a land cell gets no CUR_U/CUR_V from vehicle_sim, one at sea does
    (the Lua sensor behaves the same: test_vehicle_loop_with_mocked_bindings)."""
    from passt_mav.fields.datasets import load_dataset
    from vehicle_sim import CurrentModel, SimConfig, Simulator

    f = load_dataset("rtofs")
    cm = CurrentModel(f)
    land_cell, sea_cell = (25, 20), (14, 18)
    assert f.land_mask[land_cell] and not f.land_mask[sea_cell]
    counts = {}
    for cell in (land_cell, sea_cell):
        lat, lon = (float(x) for x in f.grid.cell_to_latlon(*cell))
        if cell == land_cell:
            assert cm.measure(3600.0, lat, lon) is None and cm.at(3600.0, lat, lon) == (0.0, 0.0)
        else:
            np.testing.assert_allclose(cm.measure(3600.0, lat, lon), f.sample_latlon(3600.0, lat, lon), atol=1e-6)
        sim = Simulator(f, home=(lat, lon), config=SimConfig.fast(current_rate_hz=2.0))
        ep = sim.connect_inprocess()
        m = ep.mavlink_connection()
        m.mav.heartbeat_send(6, 8, 0, 0, 0)
        sim.run_until(10.0)
        n = 0
        while (msg := m.recv_match(type="NAMED_VALUE_FLOAT", blocking=False)) is not None:
            n += msg.name == "CUR_U"
        counts[cell] = n
        sim.close()
    assert counts[land_cell] == 0 and counts[sea_cell] >= 15, counts


def test_shipped_grid_is_the_north_atlantic_export(tmp_path):
    """vehicle_sim/lua/current_grid.bin: the embedded ocean (seed 0) for missions/north_atlantic.yaml,
    first 48 h, field time 0 at boot - what the controller's boot clock assumes for that mission."""
    mission = SCRIPT.parents[2] / "missions" / "north_atlantic.yaml"
    out = tmp_path / "g.bin"
    assert (
        main(
            ["data", "export-lua", "builtin:ocean", "--mission", str(mission), "--snapshots", "0:48", "--out", str(out)]
        )
        == 0
    )
    assert out.read_bytes() == (SCRIPT.parent / "current_grid.bin").read_bytes()
    h = read_lua_grid(out)
    assert (h["rows"], h["cols"], h["snapshots"], h["time_at_boot_s"], h["dt_s"]) == (30, 30, 48, 0.0, 3600.0)


@pytest.mark.sitl
def test_lua_serial_sensor_on_ardurover_sitl(tmp_path, sitl_factory):
    """The serial variant on the real firmware: SITL's SERIAL1 is TCP port+2; with
    SERIAL1_PROTOCOL 28 the script reads "$CUR,u,v*hh" lines from it and forwards them."""
    import socket

    scripts = tmp_path / "scripts"
    scripts.mkdir()
    src = SCRIPT.read_text()
    assert src.count('local SOURCE = "grid"') == 1
    (scripts / SCRIPT.name).write_text(
        src.replace('local SOURCE = "grid"', 'local SOURCE = "serial"')
    )  # the edit docs/real-boat.md describes
    parm = tmp_path / "serial.parm"
    parm.write_text("SERIAL1_PROTOCOL 28\n")
    s = sitl_factory(scripts=scripts, params=parm, speedup=10)
    m = s.mavlink()

    def line(u, v, good=True):
        body = f"CUR,{u},{v}"
        cs = 0
        for b in body.encode():
            cs ^= b
        return f"${body}*{(cs if good else cs ^ 1):02X}\r\n".encode()

    got = []
    try:
        sock = socket.create_connection(("127.0.0.1", s.port + 2), timeout=30)
        try:
            end = time.monotonic() + 60.0
            k = 0
            while time.monotonic() < end and len(got) < 20:
                m.mav.heartbeat_send(6, 8, 0, 0, 0)
                # a bad checksum line between two good ones must be dropped
                sock.sendall(line(0.125, -0.5) + line(9.0, 9.0, good=False) + line(-0.25, 0.75))
                k += 1
                stop = time.monotonic() + 0.3
                while time.monotonic() < stop:
                    msg = m.recv_match(type="NAMED_VALUE_FLOAT", blocking=True, timeout=0.1)
                    if msg is not None and msg.name in ("CUR_U", "CUR_V"):
                        got.append((msg.name, msg.value))
        finally:
            sock.close()
    finally:
        m.close()
    assert len(got) >= 20, f"{len(got)} readings; {s.log_tail()}"
    us = {round(v, 6) for n, v in got if n == "CUR_U"}
    vs = {round(v, 6) for n, v in got if n == "CUR_V"}
    assert us <= {0.125, -0.25} and vs <= {-0.5, 0.75} and len(us) == 2, (us, vs)
