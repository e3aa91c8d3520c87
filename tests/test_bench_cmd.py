"""`passt-mav bench` on a fake benchmark directory (the real benchmarks are not run here)."""

from __future__ import annotations

import json
import platform
import textwrap

import pytest

from passt_mav.cli import main
from passt_mav.commands import bench

GOOD = """
import argparse, json
ap = argparse.ArgumentParser()
ap.add_argument("--json", action="store_true")
ap.add_argument("--quick", action="store_true")
a = ap.parse_args()
print("warming up")  # text before the JSON must not break the collector
out = {"time_per_snapshot": 0.5, "nested": {"a": 2, "pair": [3, 4.5]}, "long": list(range(20)),
       "quick": a.quick, "label": "ok"}
print(json.dumps(out, indent=1) if a.json else out)
"""

NOQUICK = """
import argparse, json
ap = argparse.ArgumentParser()
ap.add_argument("--json", action="store_true")
a = ap.parse_args()  # an unknown option would exit 2
print(json.dumps({"items_per_s": 48.0}))
"""

FAIL = """
import sys
print("Traceback: something", file=sys.stderr)
print("RuntimeError: boom", file=sys.stderr)
sys.exit(3)
"""

NOJSON = 'print("hello, no json here")\n'

SLOW = "import time\ntime.sleep(30)\n"


@pytest.fixture
def bench_dir(tmp_path):
    d = tmp_path / "benchmarks"
    d.mkdir()
    for name, src in (("good", GOOD), ("noquick", NOQUICK), ("fail", FAIL), ("nojson", NOJSON), ("slow", SLOW)):
        (d / f"bench_{name}.py").write_text(textwrap.dedent(src))
    (d / "helper.py").write_text("raise SystemExit('not a benchmark')\n")
    return d


def test_runs_collects_and_reports_failures(bench_dir, tmp_path, capsys):
    out = tmp_path / "res" / "bench.json"
    rc = main(["bench", "--dir", str(bench_dir), "--quick", "--timeout", "5", "--out", str(out)])
    assert rc == 1  # some benchmarks failed
    table = capsys.readouterr().out
    rep = json.loads(out.read_text())
    b = rep["benchmarks"]
    assert sorted(b) == ["fail", "good", "nojson", "noquick", "slow"]  # helper.py is not a benchmark
    assert b["good"]["status"] == "ok" and b["good"]["args"] == ["--json", "--quick"]
    assert b["good"]["result"]["quick"] is True and b["good"]["result"]["time_per_snapshot"] == 0.5
    assert b["noquick"]["status"] == "ok" and b["noquick"]["args"] == ["--json"]
    assert b["fail"]["status"] == "failed" and b["fail"]["error"] == "exit 3: RuntimeError: boom"
    assert b["nojson"]["status"] == "failed" and "no JSON" in b["nojson"]["error"]
    assert b["slow"]["status"] == "failed" and "timed out after 5 s" in b["slow"]["error"]
    assert 4.5 < b["slow"]["wall_s"] < 15
    # the table: figures flattened, long lists summarised, failures and missing --quick stated
    lines = [ln.split() for ln in table.splitlines()]
    assert ["good", "time_per_snapshot", "0.5"] in lines
    assert ["good", "nested.pair[1]", "4.5"] in lines
    assert any(ln[:2] == ["good", "long"] and "list of 20" in " ".join(ln) for ln in lines)
    assert "no --quick: ran at defaults" in table
    assert "exit 3: RuntimeError: boom" in table
    m = rep["machine"]
    assert m["python"] == platform.python_version() and m["cores"] >= 1 and m["cpu"]
    assert m["memory_gib"] is None or m["memory_gib"] > 0
    from importlib.metadata import version

    assert m["torch"] == version("torch")
    assert f"torch {m['torch']}" in table


def test_all_ok_and_json(bench_dir, capsys):
    assert main(["bench", "--dir", str(bench_dir), "--only", "good", "--only", "noquick", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert sorted(rep["benchmarks"]) == ["good", "noquick"]
    assert rep["benchmarks"]["good"]["result"]["quick"] is False  # no --quick asked


def test_ratios():
    recs = {
        "good": {"status": "ok", "result": {"t": 0.5, "nested": {"a": 2}, "up": [{"x": 3.0}, {"x": 6.0}]}},
        "models": {"status": "ok", "result": {"knode": {"predict_s_per_snapshot": 0.01}}},
        "cfd": {"status": "ok", "result": {"time_per_snapshot": 1.5}},
        "bad": {"status": "failed", "error": "x"},
    }
    r = bench.compute_ratios(
        recs,
        [
            ("t/a", "good.t", "good.nested.a"),
            ("missing", "bad.t", "good.t"),
            ("glob", "cfd.time_per_snapshot", "models.*predict*per_snapshot*"),
            ("index", "good.up[1].x", "good.up[0].x"),
            ("figure", "good.t", ""),
        ],
    )
    assert r[0]["value"] == pytest.approx(0.25)
    assert r[1]["value"] is None and "bad.t missing" in r[1]["note"]
    assert r[2]["value"] == pytest.approx(150.0) and r[2]["denominator"] == "models.knode.predict_s_per_snapshot"
    assert r[3]["value"] == pytest.approx(2.0)  # list indices are keys, not glob classes
    assert r[4]["value"] == pytest.approx(0.5)


def test_bad_input(bench_dir, tmp_path, capsys):
    assert main(["bench", "--dir", str(bench_dir), "--only", "nope"]) == 2
    assert "unknown benchmark 'nope'" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["bench", "--dir", str(tmp_path / "empty")]) == 2
    assert main(["bench", "--dir", str(tmp_path / "missing")]) == 2
    assert main(["bench", "--dir", str(bench_dir), "--list"]) == 0
    listing = capsys.readouterr().out
    assert "good" in listing and "noquick" in listing and "(no --quick)" in listing
