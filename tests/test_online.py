"""Learning at sea (models/online.py): an update is kept only when it raises the score."""

from __future__ import annotations

import numpy as np
import pytest

from passt_mav.errors import ModelError
from passt_mav.models.base import make_predictor
from passt_mav.models.online import update_online

torch = pytest.importorskip("torch")

from test_models import SMALL, _one_thread, wave_field  # noqa: E402, F401 - _one_thread: the same autouse fixture here


@pytest.fixture(scope="module")
def wave():
    return wave_field(T=40)


@pytest.fixture(scope="module")
def persistence_knode(wave):
    """A KNODE that is persistence (zero last layer, no epoch), scaled on the wave's snapshots 0..24."""
    return make_predictor("knode", epochs=0, zero_init=True, lr=3e-3, **SMALL).fit(wave, start=0, stop=24)


def neg_mse_next(truth_now, truth_next, steps=1):
    """A score: minus the MSE of the forecast ``steps`` snapshots on from ``truth_now`` against
    ``truth_next`` (higher is better)."""
    return lambda p: -float(np.mean((p.predict(truth_now, steps)[-1] - truth_next) ** 2))


def test_an_update_that_explains_the_next_leg_worse_is_discarded(wave, persistence_knode):
    """Legs so far: a travelling wave (the update learns to move it). Next leg: the field has stopped,
    so persistence (the original) is exact and any learned motion scores worse: discarded, and the
    original comes back as the same, untouched object."""
    p = persistence_knode
    before = {k: v.clone() for k, v in p.net_.state_dict().items()}
    still = wave.data[30]
    out, rec = update_online(p, wave.data[20:30], budget_s=1e9, score=neg_mse_next(still, still), lr=3e-3, max_steps=30)
    assert out is p and rec["kept"] is False and rec["steps"] == 30
    assert rec["scores"]["original"] == pytest.approx(0.0, abs=1e-12) and rec["scores"]["updated"] < -1e-6
    assert rec["reason"] == "the update did not raise the score"
    assert rec["loss"][1] < rec["loss"][0]  # it did learn the wave's motion
    assert all(torch.equal(v, p.net_.state_dict()[k]) for k, v in before.items())


def test_an_update_that_explains_the_next_leg_better_is_kept(wave, persistence_knode):
    """Next leg: the wave keeps moving, so the learned motion beats persistence: kept, a new object."""
    out, rec = update_online(
        persistence_knode,
        wave.data[20:30],
        budget_s=1e9,
        score=neg_mse_next(wave.data[30], wave.data[31]),
        lr=3e-3,
        max_steps=30,
    )
    assert out is not persistence_knode and rec["kept"] is True and rec["reason"] is None
    assert rec["scores"]["updated"] > rec["scores"]["original"]
    # the original is untouched: still persistence
    np.testing.assert_allclose(persistence_knode.predict(wave.data[30], 1)[0], wave.data[30], atol=1e-5)


def test_the_budget_bounds_the_steps_and_is_recorded():
    """A clock that advances 1 s per reading: with a 3 s budget, steps start at readings 1, 2 (the
    third reading is at 3 s): 2 steps; the recorded seconds are the clock's. No budget: no step,
    no updated score, not kept."""
    wave = wave_field(T=30)
    p = make_predictor("knode", epochs=0, zero_init=True, **SMALL).fit(wave, start=0, stop=20)
    ticks = iter(range(1000))
    clock = lambda: float(next(ticks))  # noqa: E731
    calls = []
    out, rec = update_online(p, wave.data[20:26], budget_s=3.0, score=lambda q: calls.append(q) or 0.0, clock=clock)
    assert rec["steps"] == 2 and rec["seconds"] == 4.0 and len(calls) == 2 and out is p  # equal scores: not kept
    out, rec = update_online(p, wave.data[20:26], budget_s=0.0, score=lambda q: calls.append(q) or 0.0)
    assert out is p and rec["steps"] == 0 and "updated" not in rec["scores"] and not rec["kept"]
    assert rec["reason"] == "no gradient step fitted in the budget"


def test_states_a_leg_apart_are_compared_after_interval_steps(wave, persistence_knode):
    """One state every 3 snapshots (``interval=3``): the learned motion explains the state 3 snapshots
    on better than persistence: kept."""
    out, rec = update_online(
        persistence_knode,
        wave.data[12:31:3],
        budget_s=1e9,
        score=neg_mse_next(wave.data[30], wave.data[33], steps=3),
        lr=3e-3,
        interval=3,
        max_steps=30,
    )
    assert rec["kept"] and out is not persistence_knode
    assert rec["scores"]["updated"] > rec["scores"]["original"] and rec["loss"][1] < rec["loss"][0]


def test_bad_input_and_untrainable_predictors(wave, persistence_knode):
    with pytest.raises(ModelError, match=r"states must be \(time >= 2, 2, 16, 16\)"):
        update_online(persistence_knode, wave.data[20:21], budget_s=1, score=lambda q: 0.0)
    bad = wave.data[20:24].copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ModelError, match="NaN"):
        update_online(persistence_knode, bad, budget_s=1, score=lambda q: 0.0)
    with pytest.raises(ModelError, match="interval must be a positive integer"):
        update_online(persistence_knode, wave.data[20:24], budget_s=1, score=lambda q: 0.0, interval=0)
    dmd = make_predictor("dmd").fit(wave, start=0, stop=24)
    out, rec = update_online(dmd, wave.data[20:24], budget_s=1, score=lambda q: 0.0)
    assert out is dmd and not rec["kept"] and "no trainable weights" in rec["reason"]
