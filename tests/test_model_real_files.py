"""benchmarks/model_real_files.py's smallest configuration on the HF-radar file (read in ../shared/data,
skipped when absent): every predictor is fitted on the file's earlier half only, the lookahead MSE and the
flown loop are scored on the later half, and persistence's figures equal the ones computed by hand."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
HF = ROOT.parent / "shared" / "data" / "RU_MARA_20180301T000000Z-20180301T120000Z_aggregated.nc"

pytestmark = pytest.mark.skipif(not HF.exists(), reason=f"real HF-radar file not found at {HF}")


def _bench():
    spec = importlib.util.spec_from_file_location("model_real_files", ROOT / "benchmarks" / "model_real_files.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    out = tmp_path_factory.mktemp("mrf")
    bench = _bench()
    rc = bench.main(
        ["--files", "hfradar", "--trials", "2", "--epochs", "1", "--out", str(out), "--json", str(out / "r.json")]
    )
    assert rc == 0
    return bench, out, json.loads((out / "r.json").read_text())


@pytest.mark.long(reason="fits DMD and two KNODEs on a real file and flies PASST with each: ~16 s with its fixture")
def test_fitted_on_the_earlier_half_scored_on_the_later(small):
    bench, out, (rec,) = small
    assert rec["file"] == "hfradar" and rec["n_times"] == 13 and rec["n_fit"] == 6
    assert set(rec["models"]) == set(bench.MODELS)
    for name in ("knode", "knode-dmd"):
        meta = json.loads((out / f"hfradar_{name}.json").read_text())
        assert meta["train_window"][1] == rec["n_fit"]  # never trained on the held-out hours
        assert ("--knowledge dmd" in meta["command"]) == (name == "knode-dmd")
    for m in rec["models"].values():
        assert sorted(m["lookahead"]) == ["1", "5"]  # 7 held-out snapshots: h = 10 does not fit
        loop = m["loop"]
        assert len(loop["passt"]) == 2 and loop["steps"] == 6 and loop["steps_per_leg"] == 1
        assert all(np.isfinite(loop["passt"])) and np.isfinite(loop["model"])


@pytest.mark.long(reason="shares the fitted real-file fixture (~16 s) with the test above")
def test_persistence_figures_by_hand(small):
    from passt_mav.fields.field import load_field

    _bench_mod, out, (rec,) = small
    data = load_field(out / "hfradar.nc").data.astype(np.float64)  # the region the bench flew
    a = rec["n_fit"]
    per = rec["models"]["persistence"]
    for h in (1, 5):
        d = data[a + h :] - data[a : len(data) - h]
        assert per["lookahead"][str(h)] == pytest.approx(np.nanmean(d**2), rel=1e-5)
    # the model alone: the first held-out snapshot held, RMSE over the water cells, averaged over the steps
    rmse = [np.sqrt(np.nanmean((data[a] - data[k]) ** 2)) for k in range(a + 1, len(data))]
    assert per["loop"]["model"] == pytest.approx(np.mean(rmse), rel=1e-5)


def test_bad_file_key_is_one_line_and_exit_2(capsys, tmp_path):
    assert _bench().main(["--files", "nope", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nope" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.long(reason="shares the fitted real-file fixture (~16 s) with the tests above")
def test_tables_reprinted_from_the_json(small, capsys):
    bench, out, (rec,) = small
    assert bench.main(["--tables", str(out / "r.json")]) == 0
    text = capsys.readouterr().out
    p = np.asarray(rec["models"]["dmd"]["loop"]["passt"])
    assert f"dmd          {p.mean():.4f} +- {p.std():.4f}" in text
    assert "h=1: 1 h, h=5: 5 h" in text
