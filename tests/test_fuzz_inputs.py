"""Property-based fuzz of the user's input surfaces: mission YAML, the command line's options, the live view's
command bodies (the field loader's fuzz is in tests/test_field_checks.py).

The property of each: a valid result, or a refusal in one line; never a traceback. On the command line (in
process, :func:`passt_mav.cli.main`): exit 0 with its output complete, or exit 2 (argparse's too) with exactly
one ``error:`` line on stderr (before it at most ``note:`` / ``warning:`` lines, or argparse's usage), no
output left half written, no run folder left behind; ``run`` only ever tries the closed loopback port
``tcp:127.0.0.1:9`` (every connection attempt is recorded). The view: never a 5xx, whatever the body or its
nesting. Each surface runs ``SMALL`` examples in the default run and ``LONG`` under ``-m long``, derandomized
(the same inputs on every run; ``PASST_FUZZ_RANDOM=1`` draws new ones, for a search beyond them); each test prints
its figures (inputs, valid, refused).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import os
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest
import yaml
from asgi_call import call
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_view import make_live_run

import geo
from passt_mav.cli import main
from passt_mav.errors import MissionConfigError
from passt_mav.fields.field import FlowField, load_field
from passt_mav.mission.config import MissionConfig, load_mission
from passt_mav.runs.rundir import RunDir

SMALL, LONG = 40, 500
SIZES = [
    pytest.param(SMALL, id="default"),
    pytest.param(LONG, id="long", marks=pytest.mark.long(reason="a fuzz pass of 500 examples: a minute or more")),
]
#: the closed loopback port every ``run`` of the fuzz is sent to (the discard port: nothing listens there)
NOWHERE = "tcp:127.0.0.1:9"
GRID = geo.RegionGrid(40.0, -70.0, 40.07, -70.0 + 7 * 0.013, 8, 8)
#: the figures of every surface: inputs tried, valid results, one-line refusals
FIGURES: dict[str, dict[str, int]] = {}


def _settings(n: int):
    return settings(
        max_examples=n,
        deadline=None,
        database=None,
        derandomize=not os.environ.get("PASST_FUZZ_RANDOM"),
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    )


def _count(surface: str, outcome: str) -> None:
    fig = FIGURES.setdefault(surface, {"inputs": 0, "valid": 0, "refused": 0})
    fig["inputs"] += 1
    fig[outcome] += 1


def _report(surface: str, n: int) -> None:
    fig = FIGURES.get(surface, {})
    print(f"fuzz {surface}: {fig}")
    assert fig.get("inputs", 0) >= min(n, 10), fig


# -- a small world: a field file, a mission on it, a radar-like source file --------------------------------
def _field(path: Path, *, steady: bool = False) -> Path:
    """An 8x8 geographic field of 6 hourly snapshots: a current that grows eastward and turns with time
    (``steady``: the same at every snapshot)."""
    t = np.arange(6, dtype=np.float32)[:, None, None] * (0.0 if steady else 1.0)
    cols = np.linspace(0.0, 0.2, 8, dtype=np.float32)[None, None, :]
    data = np.zeros((6, 2, 8, 8), np.float32)
    data[:, 0] = 0.3 + cols + 0.02 * t
    data[:, 1] = 0.1 - 0.01 * t
    FlowField(data, GRID, 3600.0 * np.arange(6), "2024-10-28T03:00:00Z", "m s-1").to_netcdf(path)
    return path


BASE_MISSION = {
    "name": "fuzz",
    "region": {"south": 40.0, "west": -70.0, "north": 40.07, "east": -70.0 + 7 * 0.013, "rows": 8, "cols": 8},
    "field": {"source": "f.nc"},
    "model": "persistence",
    "planner": {"name": "greedy", "path_length": 4, "reward": "speed"},
    "legs": 1,
    "start_cell": [3, 3],
    "vehicle": {"connect": NOWHERE, "speed_mps": 2.0, "wp_radius_m": 5.0},
    "sensors": {"u": "CUR_U", "v": "CUR_V", "noise_std": 0.02},
    "gp": {"background": 0, "prior_blend": "off"},
    "seeds": {"planner": 0},
}


def _radar(path: Path) -> Path:
    """A radar-like source file for ``data import``: u/v (time, lat, lon) in cm/s on a 0.1 deg grid."""
    import xarray as xr

    lat, lon = np.round(np.linspace(40.0, 41.0, 11), 6), np.round(np.linspace(-70.0, -69.0, 11), 6)
    u = np.full((4, 11, 11), 30.0)
    times = np.datetime64("2018-03-01T00:00") + np.arange(4) * np.timedelta64(1, "h")
    xr.Dataset(
        {"u": (("time", "lat", "lon"), u, {"units": "cm/s"}), "v": (("time", "lat", "lon"), 0 * u, {"units": "cm/s"})},
        coords={"time": times, "lat": ("lat", lat), "lon": ("lon", lon)},
    ).to_netcdf(path)
    return path


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("fuzz_world")
    _field(d / "f.nc")
    _field(d / "steady.nc", steady=True)
    _radar(d / "radar.nc")
    (d / "m.yaml").write_text(yaml.safe_dump(BASE_MISSION, sort_keys=False))
    (d / "text.nc").write_text("not a netCDF file")
    (d / "empty").mkdir()
    assert load_mission(d / "m.yaml").model == "persistence"
    return d


# -- the command line, in process ---------------------------------------------------------------------------
def _cli(argv: list[str]) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``passt-mav ARGV``; argparse's SystemExit is its exit code."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    return rc, out.getvalue(), err.getvalue()


def _one_line_or_success(surface: str, argv, rc: int, out: str, err: str) -> bool:
    """Assert the command line's property (module docstring); True when it succeeded."""
    assert "Traceback" not in out + err, (argv, err[-2000:])
    assert rc in (0, 2), (argv, rc, err[-2000:])
    if rc == 0:
        _count(surface, "valid")
        return True
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ": error: " in ln]
    assert len(errors) == 1 and errors[0] == lines[-1], (argv, err)
    assert errors[0].split(": error: ", 1)[1].strip(), (argv, err)
    argparse_usage = lines[0].startswith("usage: ")  # argparse's refusal: its usage, then its one error line
    for ln in lines[:-1]:
        ok = ln.startswith(("note: ", "warning: ")) or (argparse_usage and (ln.startswith("usage:") or ln[:1] == " "))
        assert ok, (argv, err)
    _count(surface, "refused")
    return False


@pytest.fixture
def no_connection(monkeypatch):
    """Every TCP connection the link tries, recorded; only the closed loopback port is allowed."""
    from passt_mav.mavlink import link as link_mod

    tried: list = []
    real = socket.create_connection

    def recorded(address, *a, **k):
        tried.append(address)
        assert tuple(address[:2]) == ("127.0.0.1", 9), address
        return real(address, *a, **k)

    monkeypatch.setattr(link_mod.socket, "create_connection", recorded)
    return tried


# -- mission YAML -----------------------------------------------------------------------------------------
def _known_keys() -> list[str]:
    """Every key a mission may hold, at any depth (the pool unknown and misplaced keys are drawn from)."""
    from pydantic import BaseModel

    keys, todo = set(), [MissionConfig]
    while todo:
        cls = todo.pop()
        for name, f in cls.model_fields.items():
            keys.add(name)
            ann = f.annotation
            if isinstance(ann, type) and issubclass(ann, BaseModel):
                todo.append(ann)
    return sorted(keys | {"x0", "x1", "y0", "y1", "anchor_lat", "anchor_lon", "kind", "<<"})


def _scalar():
    return st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-5, 10),
        st.integers(),
        st.sampled_from([2**31, 2**64, -(2**63), 10**30, 1001, 10_001]),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=12),
        st.sampled_from(
            ["", "builtin:ocean", "builtin:nope", "nope.nc", "f.nc", "m.yaml", "x.pt", "knode", "dmd", "constant",
             "metric", "geographic", "on", "off", "yes", "~", "1e400", ".inf", "-.nan", "0x10", "0o7", "1_000",
             "2024-10-28", "tcp:127.0.0.1:9", "../f.nc", "/", "\x00", "é" * 20, "a" * 300]
        ),
    )  # fmt: skip


def _value():
    """Any YAML value: scalars, lists, mappings, and nesting up to a few hundred deep."""
    nested = st.recursive(
        _scalar(), lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=3), max_leaves=6
    )
    deep = st.tuples(_scalar(), st.integers(1, 400), st.booleans()).map(lambda t: _nest(t[0], t[1], as_list=t[2]))
    return st.one_of(_scalar(), _scalar(), nested, deep)


def _nest(v, depth: int, *, as_list: bool):
    for _ in range(depth):
        v = [v] if as_list else {"k": v}
    return v


def _paths(d, prefix=()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(d, dict):
        for k, v in d.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            out += _paths(v, (*prefix, i))
    return out


def _parent(d, path):
    for p in path[:-1]:
        d = d[p]
    return d


KEYS = _known_keys()
#: names the base mission's strings may become (other planners, rewards, models, modes)
TWEAKS = ["lawnmower", "random", "information", "policy_gradient", "vorticity", "variance_reduction", "dmd", "knode",
          "builtin:ocean", "f.nc", "steady.nc", "CUR_X", "CURRENT_U_TOO_LONG", "udpin:127.0.0.1:9", "fuzz2"]  # fmt: skip


def _mutate_dict(draw, data: dict) -> None:
    """One structural mutation of the mission mapping ``data``, in place: drop, replace, add, rename a key."""
    paths = _paths(data)
    path = draw(st.sampled_from(paths))
    parent = _parent(data, path)
    kind = draw(st.sampled_from(["drop", "set", "set", "add", "rename", "retype", "tweak", "tweak"]))
    if kind == "tweak":  # a number to another plausible one, a name to another the mission knows
        v = parent[path[-1]]
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            parent[path[-1]] = draw(st.one_of(st.integers(-1, 12), st.floats(-1.0, 12.0), st.just(v * 1.0001)))
        elif isinstance(v, str):
            parent[path[-1]] = draw(st.sampled_from(TWEAKS))
    elif kind == "drop" and isinstance(parent, dict):
        del parent[path[-1]]
    elif kind == "set":
        parent[path[-1]] = draw(_value())
    elif kind == "retype":  # the same value as another type: a string, a list, a mapping
        v = parent[path[-1]]
        parent[path[-1]] = draw(st.sampled_from([str(v), [v], {"value": v}, -v if isinstance(v, int) else v]))
    elif kind == "add":
        target = parent if isinstance(parent, dict) else data
        target[draw(st.one_of(st.sampled_from(KEYS), st.text(max_size=8)))] = draw(_value())
    elif kind == "rename" and isinstance(parent, dict):
        parent[draw(st.sampled_from(KEYS))] = parent.pop(path[-1])


#: 9**5 * 4 values from a few lines: the "billion laughs" of YAML
_ALIAS_BOMB = (
    "a: &a [x, x, x, x, x, x, x, x, x]\n"
    + "".join(f"{b}: &{b} [{', '.join([f'*{a}'] * 9)}]\n" for a, b in zip("abcd", "bcde"))
    + "f: [*e, *e, *e, *e]\n"
)
ALIAS_TEXTS = [
    "base: &b {speed_mps: 3.0}\nvehicle:\n  <<: *b\n  wp_radius_m: 4.0\n",
    "anchor: &a [1, 2]\nstart_cell: *a\n",
    "start_cell: &c [2, 2]\nplanner: *c\n",
    _ALIAS_BOMB,
    "legs: *undefined\n",
    "vehicle: &v {connect: 'tcp:127.0.0.1:9'}\nvehicles: [*v, *v]\n",
    "region: !!python/object:os.system {}\n",
    "gp: !!binary aGVsbG8=\n",
]


def _mutate_text(draw, text: str) -> bytes:
    """One textual mutation of a mission file: a key given twice, aliases, deep nesting, tabs, junk bytes,
    a cut, or nothing."""
    lines = text.splitlines(keepends=True)
    kind = draw(
        st.sampled_from(
            ["none", "none", "none", "none", "dup", "alias", "deep", "tab", "insert", "cut", "bytes", "doc"]
        )
    )
    if kind == "dup":
        i = draw(st.integers(0, len(lines) - 1))
        lines.insert(draw(st.integers(0, len(lines))), lines[i] if not lines[i].startswith(" ") else lines[i].lstrip())
    elif kind == "alias":
        lines.append(draw(st.sampled_from(ALIAS_TEXTS)))
    elif kind == "deep":
        n = draw(st.sampled_from([10, 500, 5000, 50_000]))
        lines.append(
            f"options: {'[' * n}1{']' * n}\n" if draw(st.booleans()) else "deep: " + "{a: " * n + "1" + "}" * n
        )
    elif kind == "tab":
        lines = [ln.replace("  ", "\t", 1) for ln in lines]
    elif kind == "insert":
        i = draw(st.integers(0, len(text)))
        text = text[:i] + draw(st.text(max_size=5)) + text[i:]
        return text.encode("utf-8", "surrogatepass")
    elif kind == "cut":
        return text[: draw(st.integers(0, len(text)))].encode()
    elif kind == "bytes":
        return text.encode() + draw(st.binary(min_size=1, max_size=8))
    elif kind == "doc":
        lines.append("---\nname: second\n")
    return "".join(lines).encode("utf-8", "surrogatepass")


@st.composite
def mission_files(draw) -> bytes:
    """A mission file: the valid base mission with up to four structural mutations, then a textual one."""
    import copy

    data = copy.deepcopy(BASE_MISSION)
    for _ in range(draw(st.sampled_from([0, 1, 1, 1, 2, 4]))):
        _mutate_dict(draw, data)
    try:
        text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    except RecursionError:
        text = "name: deep\nregion: " + "[" * 2000 + "]" * 2000 + "\n"
    return _mutate_text(draw, text)


def _check_plan(world: Path, p: Path, out: Path, surface: str) -> None:
    """``plan`` on mission file ``p``: one line and nothing written, or the three files, complete."""
    argv = ["plan", p, "--out", out]
    rc, o, e = _cli(argv)
    if _one_line_or_success(surface, argv, rc, o, e):
        assert sorted(f.name for f in out.iterdir()) == ["leg.plan", "leg.waypoints", "path.json"]
        rec = json.loads((out / "path.json").read_text())
        assert len(rec["path"]) == rec["path_length"] + 1
    else:
        assert not out.exists(), (p.read_bytes()[:300], e)


@pytest.mark.parametrize("n", SIZES)
def test_fuzz_mission_files_load_and_plan(world, tmp_path, n):
    """Mutated mission files: :func:`load_mission` gives a config or one :class:`MissionConfigError` line;
    ``passt-mav plan`` on the same file exits 0 with its three files or 2 in one line, writing nothing."""
    counter = iter(range(10**9))

    @_settings(n)
    @given(text=mission_files())
    def one(text):
        i = next(counter)
        p = world / f"fz_{i}.yaml"  # beside the field file: the base mission's relative source resolves
        p.write_bytes(text)
        try:
            try:
                cfg = load_mission(p)
            except MissionConfigError as exc:
                _count("mission (load_mission)", "refused")
                assert str(exc).startswith(str(p)) and "\n" not in str(exc), str(exc)
            else:
                _count("mission (load_mission)", "valid")
                assert isinstance(cfg, MissionConfig)
            _check_plan(world, p, tmp_path / f"o{i}", "mission (plan)")
        finally:
            p.unlink()
            shutil.rmtree(tmp_path / f"o{i}", ignore_errors=True)

    one()
    _report("mission (load_mission)", n)
    _report("mission (plan)", n)


# -- the command line's options -----------------------------------------------------------------------------
JUNK = ["", "-1", "0", "1", "2", "nan", "inf", "-inf", "1e309", "abc", "3,4", "-", "--", "é", "x" * 200, "0x10",
        "1.5", "99999999999999999999", "None", "true", "/", "..", "a=b", "=", "5,5,5", "2x2", "-3,-3"]  # fmt: skip


def _options(options: dict[str, list], flags: list[str], junk: list[str] = JUNK):
    """argv tails: some of ``options`` (each with a value of its list, or junk), some ``flags``, now and then an
    unknown option or a stray word."""
    opt = st.sampled_from(sorted(options)).flatmap(
        lambda o: st.tuples(st.just(o), st.one_of(st.sampled_from(options[o] or junk), st.sampled_from(junk)))
    )
    item = st.one_of(
        opt.map(list),
        opt.map(lambda t: [f"{t[0]}={t[1]}"]),
        st.sampled_from(flags).map(lambda f: [f]) if flags else st.nothing(),
        st.sampled_from(["--bogus", "-x", "stray", "--", "--out"]).map(lambda f: [f]),
    )
    return st.lists(item, max_size=5).map(lambda items: [a for it in items for a in it])


def _fuzz_command(surface: str, n: int, argv_of, check, cwd: Path) -> None:
    """``n`` examples of ``passt-mav`` with the argv ``argv_of(i)`` draws, run in the empty folder ``cwd`` (where a
    relative ``--out`` lands); ``check(i, argv, ok, out, err)`` checks what a success or a refusal left (a success
    may leave files in ``cwd``, which are cleared after it; a refusal leaves none)."""
    counter = iter(range(10**9))
    cwd.mkdir(exist_ok=True)

    @_settings(n)
    @given(data=st.data())
    def one(data):
        i = next(counter)
        argv = data.draw(argv_of(i))
        with contextlib.chdir(cwd):
            rc, o, e = _cli(argv)
        ok = _one_line_or_success(surface, argv, rc, o, e)
        check(i, argv, ok, o, e)
        left = sorted(p.name for p in cwd.iterdir())
        shutil.rmtree(cwd)
        cwd.mkdir()
        assert ok or not left, (argv, e, left)

    one()
    _report(surface, n)


def _untouched(path: Path, before: set[str]) -> None:
    assert {p.name for p in path.iterdir()} == before, sorted(p.name for p in path.iterdir())


@pytest.mark.parametrize("n", SIZES)
def test_fuzz_plan_options(world, tmp_path, n):
    """``plan`` with random options: its three files, or one line and no output folder."""
    opts = {
        "--state": [
            world / "f.nc",
            world / "steady.nc",
            world / "nope.nc",
            world / "text.nc",
            world / "empty",
            world / "radar.nc",
        ],
        "--time": ["0", "5", "6", "-1", "3"],
        "--start": ["3,3", "0,0", "7,7", "8,8", "-1,2", "3", "a,b", "3,3,3"],
        "--length": ["1", "3", "0", "-2", "1001"],
        "--model": ["none", "persistence", "dmd", "builtin:ocean", "builtin:nope", world / "nope.pt", "knode", "", "/"],
        "--planner": ["greedy", "lawnmower", "random", "information", "nope"],
        "--reward": ["speed", "vorticity", "std", "variance_reduction", "nope"],
    }
    mission = st.sampled_from([world / "m.yaml"] * 4 + [world / "f.nc", world / "nope.yaml", world / "empty"])

    def argv_of(i):
        return st.tuples(mission, _options(opts, ["--json", "--help"])).map(
            lambda t: ["plan", t[0], *t[1], "--out", tmp_path / f"o{i}"]
        )

    def check(i, argv, ok, out, err):
        o = tmp_path / f"o{i}"
        if ok and "--help" not in argv:
            assert sorted(f.name for f in o.iterdir()) == ["leg.plan", "leg.waypoints", "path.json"], argv
            json.loads((o / "path.json").read_text())
            if "--json" in argv:
                json.loads(out.strip().splitlines()[-1])
        elif not ok:
            assert not o.exists(), (argv, err)

    _fuzz_command("options (plan)", n, argv_of, check, tmp_path / "cwd")


@pytest.mark.parametrize("n", SIZES)
def test_fuzz_run_options_never_connect_and_leave_nothing(world, tmp_path, no_connection, n):
    """``run`` of the base mission or a mutated one, with random options, to the closed loopback port and a tiny
    ready timeout: one line, exit 2, no run folder left, and no connection tried anywhere else."""
    opts = {
        "--legs": ["1", "0", "-1", "3"],
        "--speedup-hint": ["1", "300", "0", "-5", "nan"],
        "--lockstep": ["0", "0.5", "-1", "nan", "inf"],
        "--field-time-at-boot": ["0", "-1", "nan", "1e300"],
        "--signing-key": ["secret", "", "zz" * 32, "0" * 64],
        "--link-loss-window": ["1", "0", "-1", "nan", "inf"],
        "--pause-timeout": ["1", "0", "nan"],
        "--ready-timeout": ["0.05", "0", "-1", "nan", "inf", "abc"],
        "--source-system": ["1", "0", "255", "256", "-1"],
        "--source-component": ["1", "0", "256"],
        "--set": ["legs=2", "name.x=1", "planner.path_length=3", "region.rows.a=3", "=3", "a.b=[[[", "field=3",
                  "vehicles=[{connect: 'tcp:127.0.0.1:9'}]", "gp=[1]", "x=1", "vehicle.connect=tcp:127.0.0.1:9",
                  "start_cell.0=1", "planner..name=greedy", "seeds.planner=-1"],
        "--connect": [NOWHERE, "tcp:127.0.0.1:99999", "tcp:127.0.0.1:x", "tcp:", "udp:", "/nonexistent/tty9,57600"],
    }  # fmt: skip

    def mission(i, text: bytes | None) -> Path:
        """The base mission, or (``text``) a mutated one beside the field file."""
        if text is None:
            return world / "m.yaml"
        (world / f"fz_run_{i}.yaml").write_bytes(text)
        return world / f"fz_run_{i}.yaml"

    def argv_of(i):
        texts = st.one_of(st.none(), st.none(), mission_files())
        tails = _options(opts, ["--approve", "--quiet", "--resume", "--no-report"])
        return st.tuples(texts, tails).map(
            lambda t: ["run", mission(i, t[0]), "--connect", NOWHERE, "--ready-timeout", "0.05", "--no-report",
                       *t[1], "--out", tmp_path / f"r{i}" / "run"]
        )  # fmt: skip

    def check(i, argv, ok, out, err):
        (world / f"fz_run_{i}.yaml").unlink(missing_ok=True)
        assert not ok or "--help" in argv, (argv, out, err)
        assert not (tmp_path / f"r{i}").exists(), (argv, err)

    _fuzz_command("options (run)", n, argv_of, check, tmp_path / "cwd")  # (where a run without --out makes runs/)
    assert set(no_connection) <= {("127.0.0.1", 9)}


@pytest.mark.parametrize("n", SIZES)
def test_fuzz_data_import_options(world, tmp_path, n):
    """``data import`` with random options: a field file that loads, or one line and no file."""
    opts = {
        "--region": ["40,-70,41,-69", "40.2,-69.8,40.8,-69.2", "41,-69,40,-70", "0,0,1,1", "a,b,c,d", "40,-70,41",
                     "-91,-70,41,-69", "north_atlantic", "nope"],
        "--grid": ["11x11", "4x4", "1x1", "0x3", "100x", "x", "3x-3", "1001x1001", "5X5"],
        "--start": ["2018-03-01T01:00:00Z", "2018-03-01", "2030-01-01T00:00:00Z", "yesterday", "2018-13-01"],
        "--hours": ["1", "2", "0", "-1", "nan", "inf", "1e9"],
        "--variables": ["u,v", "v,u", "u", "a,b", "u,v,w", ","],
        "--units": ["m/s", "cm/s", "knots", "furlongs", ""],
        "--min-coverage": ["0", "50", "100", "101", "-1", "nan"],
        "--out": [],
    }  # fmt: skip
    src = st.sampled_from([world / "radar.nc"] * 4 + [world / "text.nc", world / "nope.nc", world / "empty"])

    def argv_of(i):
        out = tmp_path / f"d{i}.nc"
        opts["--out"] = [out, tmp_path / "no" / "such" / "x.nc", world / "empty", out.with_suffix(".txt")]
        return st.tuples(src, _options(opts, ["--allow-fast", "--json"])).map(
            lambda t: ["data", "import", t[0], "--region=40,-70,41,-69", "--grid", "11x11", "--out", out, *t[1]]
        )

    def check(i, argv, ok, out, err):
        written = [*tmp_path.glob(f"d{i}.*"), *(tmp_path / "no").glob("**/*.nc"), *(tmp_path / "cwd").glob("*")]
        if ok and "--help" not in argv:
            assert written, (argv, out)
            for p in written:
                f = load_field(p)
                assert f.data.dtype == np.float32 and f.n_times >= 1
                p.unlink()
        elif not ok:
            assert not written, (argv, err, written)
        _untouched(world, {"f.nc", "steady.nc", "radar.nc", "m.yaml", "text.nc", "empty"})

    _fuzz_command("options (data import)", n, argv_of, check, tmp_path / "cwd")


@pytest.mark.parametrize("n", SIZES)
def test_fuzz_evaluate_options(world, tmp_path, n):
    """``evaluate`` (a campaign of one or two tiny trials on the 8x8 field) with random options: a summary, or one
    line and no output folder."""
    small = ["1", "2", "0", "-1", "nan", "abc"]
    opts = {
        "--trials": small, "--path-lengths": ["2", "2,3", "0", "-1", "a", "2,,3", "3;4"], "--steps": small + ["4"],
        "--t0": ["0", "1", "5", "6", "-1"], "--steps-per-leg": small, "--noise": ["0", "0.02", "-1", "nan", "inf"],
        "--sampling": ["end", "spread", "nope"], "--hyper": ["every_leg", "first_leg", "state", "nope"],
        "--methods": ["passt", "passt,random", "model", "nope", ""], "--window": small, "--snapshot-step": small,
        "--seed": ["0", "-1", "2**70", "99999999999999999999999"], "--engine": ["lockstep", "serial", "nope"],
        "--batch": small, "--gp-solver": ["cholesky", "sklearn", "nope"], "--background": ["0", "2", "-1"],
        "--prior-blend": ["off", "bma", "select"], "--prior-share": ["0", "0.5", "2", "nan"],
        "--prior-forgetting": ["0", "1", "-1", "nan"], "--memory": ["off", "fitted"], "--gp-fit-points": small,
        "--model": ["persistence", "dmd", "nope", world / "nope.pt"], "--data": [world / "steady.nc", world / "text.nc"],
        "--preset": ["default", "paper", "nope"],
        "--planner": ["greedy", "lawnmower", "nope"], "--reward": ["speed", "std", "nope"],
    }  # fmt: skip
    head = ["--data", world / "f.nc", "--model", "persistence", "--trials", "1", "--path-lengths", "2", "--steps", "2"]

    # (no huge counts: --trials 10**20 is a campaign that runs for ever, not a wrong input)
    junk = [j for j in JUNK if j not in ("99999999999999999999", "1e309", "inf")]

    def argv_of(i):
        return _options(opts, ["--json", "--gp-bias", "--no-gp-bias"], junk).map(
            lambda tail: ["evaluate", *head, *tail, "--out", tmp_path / f"e{i}"]
        )

    def check(i, argv, ok, out, err):
        o = tmp_path / f"e{i}"
        if ok and "--help" not in argv:
            assert json.loads((o / "results.json").read_text())["per_L"], (argv, sorted(o.iterdir()))
            if "--json" in argv:
                json.loads(out[out.index("{") :])
        elif not ok:
            assert not o.exists() or not any(o.iterdir()), (argv, err, sorted(o.iterdir()))
        shutil.rmtree(o, ignore_errors=True)

    _fuzz_command("options (evaluate)", n, argv_of, check, tmp_path / "cwd")


def _not_a_run(d: Path, draw) -> Path:
    """A folder that is no run: empty, or holding junk where a run keeps its records."""
    d.mkdir()
    files = {
        "summary.json": st.one_of(st.binary(max_size=20), _value().map(lambda v: json.dumps(v).encode())),
        "meta.json": _value().map(lambda v: json.dumps(v).encode()),
        "mission.yaml": mission_files(),
        "flight.tlog": st.binary(max_size=200),
        "samples.db": st.binary(max_size=100),
        "samples.csv": st.text(max_size=50).map(str.encode),
    }
    for name in draw(st.lists(st.sampled_from(sorted(files)), max_size=4, unique=True)):
        (d / name).write_bytes(draw(files[name]))
    if draw(st.booleans()):
        (d / "legs" / "0").mkdir(parents=True)
    return d


@pytest.mark.parametrize("n", SIZES)
def test_fuzz_replay_and_report_on_folders_that_hold_no_run(world, tmp_path, n):
    """``replay`` and ``report`` (random options) on a folder holding no run, or junk where a run keeps its
    records: one line, exit 2, nothing written into the folder."""
    opts = {
        "--mission": [world / "m.yaml", world / "nope.yaml", world / "f.nc"],
        "--model": ["persistence", "nope", "builtin:nope"],
        "--planner": ["greedy", "nope"],
        "--reward": ["speed", "nope"],
        "--out": [],
    }
    counter, cwd = iter(range(10**9)), tmp_path / "cwd"

    @_settings(n)
    @given(data=st.data())
    def one(data):
        i = next(counter)
        d = _not_a_run(tmp_path / f"n{i}", data.draw)
        before = {p.relative_to(d) for p in d.rglob("*")}
        opts["--out"] = [tmp_path / f"out{i}", d / "x"]
        cmd = data.draw(st.sampled_from(["replay", "report"]))
        tail = data.draw(_options(opts if cmd == "replay" else {"--out": opts["--out"]}, ["--json"]))
        argv = [cmd, data.draw(st.sampled_from([d, d / "flight.tlog", d / "summary.json"])), *tail]
        cwd.mkdir()
        with contextlib.chdir(cwd):  # where a relative --out lands
            rc, o, e = _cli(argv)
        ok = _one_line_or_success(f"options ({cmd} on no run)", argv, rc, o, e)
        after, made = {p.relative_to(d) for p in d.rglob("*")}, [*cwd.iterdir(), *tmp_path.glob(f"out{i}")]
        shutil.rmtree(cwd)
        if ok and "--help" not in argv:  # junk in a run's file names makes a run folder (RunDir.is_run_dir)
            assert RunDir(d).is_run_dir(), (argv, o)
            assert all(p.parts[0] in ("report", "replay", "x") for p in after - before), (argv, after - before)
            assert any(p.name in ("report.html", "replay.json") for p in after - before) or made, argv
        elif not ok:
            assert after == before and not made, (argv, e, made)

    one()
    _report("options (replay on no run)", n // 4)
    _report("options (report on no run)", n // 4)


# -- the live view's command bodies -------------------------------------------------------------------------
def _json_value():
    """Any JSON value (NaN and the infinities too, which Python's parser reads), small and nested."""
    leaf = st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-3, 3),
        st.integers(),
        st.sampled_from([2**63, -(2**63) - 1, 10**300, "all", "HOLD", "RTL", "pause", "end", "approve", ""]),
        st.floats(),
        st.text(max_size=10),
    )
    return st.recursive(leaf, lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=3))


@st.composite
def command_bodies(draw) -> bytes:
    """A command body: the fields of a command (each valid or any JSON), unknown fields, a value nested up to the
    parser's depth, a key given twice, or bytes that are not JSON."""
    from passt_mav.runs.commands import ACTIONS

    fields = {
        "action": st.sampled_from(ACTIONS),
        "boat": st.sampled_from([0, 0, "all", 1, -1]),
        "end_mode": st.sampled_from(["HOLD", "RTL", "hold"]),
        "leg": st.integers(-1, 5),
    }
    body = {
        k: draw(st.one_of(s, s, s, _json_value()))
        for k, s in fields.items()
        if k == "action" or draw(st.integers(0, 2)) == 0
    }
    if draw(st.integers(0, 4)) == 0:
        body[draw(st.text(max_size=6))] = draw(_json_value())
    kind = draw(st.sampled_from(["plain", "plain", "deep", "dup", "array", "bytes", "big"]))
    deep = None
    if kind == "deep":  # a field's value nested as deep as 4 KiB of brackets goes (the parser's limit is near)
        key, depth, as_list = draw(st.sampled_from(sorted(fields))), draw(st.integers(1, 2040)), draw(st.booleans())
        inner = json.dumps(draw(_json_value()))
        deep = "[" * depth + inner + "]" * depth if as_list else '{"a": ' * (depth // 6) + inner + "}" * (depth // 6)
        body[key] = "@deep@"  # (json.dumps recurses: the nesting is written as text)
    text = json.dumps(body)
    if deep is not None:
        text = text.replace('"@deep@"', deep)
    if kind == "dup":  # the same key twice: the last one wins
        dup = draw(st.sampled_from(sorted(fields)))
        text = "{" + json.dumps(dup) + ": " + json.dumps(draw(_json_value())) + (", " if body else "") + text[1:]
    elif kind == "array":
        text = json.dumps([body] * draw(st.integers(0, 3)))
    elif kind == "bytes":
        return text.encode()[: draw(st.integers(0, len(text)))] + draw(st.binary(max_size=8))
    elif kind == "big":
        text = text[:-1] + ', "pad": "' + "x" * draw(st.sampled_from([4000, 5000, 10**5])) + '"}'
    return text.encode()


@pytest.mark.parametrize("n", SIZES)
def test_fuzz_view_command_bodies_never_a_5xx(tmp_path, n):
    """``POST /api/command`` with the token, from the page's own address, with random JSON bodies and nesting: a
    202 only for a well-formed command (written to the channel as validated), else a 4xx of one line; never a
    5xx."""
    from test_view_security import HOST, ORIGIN, _app, _headers

    from passt_mav.runs.commands import CommandError, read_commands, validate

    root = make_live_run(tmp_path / "run").root
    app, loop = _app(root), asyncio.new_event_loop()
    ctypes = ["application/json", "application/json", "application/json; charset=utf-8", "APPLICATION/JSON"]

    @_settings(3 * n)
    @given(body=command_bodies(), ctype=st.sampled_from(ctypes))
    def one(body, ctype):
        headers = [*_headers(HOST, ORIGIN, "header"), ("content-type", ctype)]
        before = len(read_commands(root)[0])
        r = call(loop, app, "POST", "/api/command", headers=headers, body=body)
        assert r.status < 500, (body[:300], r.status, r.body[:300])
        try:
            expected = validate(json.loads(body), 1) if len(body) <= 4096 else None
        except (ValueError, RecursionError, CommandError):
            expected = None
        cmds = read_commands(root)[0]
        if r.status == 202:
            _count("view (POST /api/command)", "valid")
            assert expected is not None and len(cmds) == before + 1, (body[:300], r.body)
            assert {k: cmds[-1][k] for k in expected} == expected
        else:
            _count("view (POST /api/command)", "refused")
            assert 400 <= r.status < 500 and b"\n" not in r.body.strip(), (body[:300], r.status, r.body[:300])
            assert expected is None and len(cmds) == before, (body[:300], r.status, r.body[:300])

    try:
        one()
    finally:
        loop.close()
    _report("view (POST /api/command)", 3 * n)
    assert FIGURES["view (POST /api/command)"]["valid"] > 0
