"""benchmarks/knode_dmd_static_gap.py's table on a small field with known answers: DMD fitted on whole
periods of two travelling waves forecasts them exactly; the untrained DMD-knowledge KNODE with the
complement dropped is that DMD (the same row); a wave DMD never saw is not forecast."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from test_knowledge import two_tone_field  # noqa: E402
from test_models import SMALL, _one_thread  # noqa: E402, F401 - _one_thread: the same autouse fixture here

ROOT = Path(__file__).resolve().parent.parent


def _bench():
    spec = importlib.util.spec_from_file_location(
        "knode_dmd_static_gap", ROOT / "benchmarks" / "knode_dmd_static_gap.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _numbers(row: str) -> list[float]:
    return [float(x) for cell in row.strip("|").split("|")[1:] for x in cell.split("/")]


def test_rows_on_two_travelling_waves():
    bench = _bench()
    field = two_tone_field()
    other = two_tone_field()
    # a third wave (period 5 snapshots) the models never saw
    t = np.arange(other.n_times)[:, None, None, None]
    other.data[:] = other.data + 0.2 * np.sin(2 * np.pi * (np.arange(16)[None, None, None, :] / 16 - t / 5))
    kw = {k: v for k, v in SMALL.items() if k != "progress"}
    preds = bench.models(field, train=(0, 24), shipped=False, **kw)
    assert [label.split(" (")[0] for label, _ in preds] == ["DMD, energy 0.999", "DMD, energy 0.9999"] + [
        f"untrained, {v[0]}" for v in bench.VARIANTS
    ]
    rows = list(bench.table_rows(preds, field, other, test=(24, 60), val=(12, 24)))
    assert len(rows) == len(preds)
    dmd, drop = _numbers(rows[0]), _numbers(rows[2])
    assert len(dmd) == 2 * len(bench.LOOKAHEADS) + 1
    assert max(dmd[:4]) < 1e-8 and dmd[-1] < 1e-8  # the two waves: DMD is exact
    assert min(dmd[4:8]) > 1e-3  # the unseen wave (variance 0.02 per channel) is not forecast
    np.testing.assert_allclose(drop, dmd, rtol=1e-3, atol=1e-9)  # untrained, complement dropped: DMD
