"""A prior that knows when it is wrong (issue 27, item 6): PasstLoop(prior_blend="bma").

Known answers on a translating pattern whose true drift is known: a model with the true drift
must keep its weight (nothing lost against the model-only loop); a model that drifts the
wrong way, worse than persistence, must lose it, and PASST must then come close to PASST
with persistence as its prior (and far below the model-only loop). Measured (3 seeds, final
20 steps): right model 1.86e-6 with and without the blend; wrong model 0.791 model-only, 0.583
blended, 0.583 with persistence as the prior.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_passt import ShiftPredictor, make_field

from passt_mav.errors import ReconstructionError
from passt_mav.loop.engine import run_offline
from passt_mav.loop.passt import PasstLoop

TRUE_VEL = (0.05, 0.12)


class Persistence:
    def fit(self, field):
        return self

    def predict(self, state, steps):
        return np.repeat(np.asarray(state, np.float32)[None], steps, axis=0)


def _final(field, predictor, blend, seeds=range(3), **loop_kw):
    """Mean over ``seeds`` of the final 20 steps' RMSE of a random-walk loop (``loop_kw``: more options)."""
    out = []
    for s in seeds:
        r = run_offline(
            field,
            predictor,
            start_cell=(15, 15),
            n_steps=60,
            planner="random",
            path_length=25,
            steps_per_leg=5,
            noise_std=0.02,
            seed=s,
            prior_blend=blend,
            background=0,
            **loop_kw,
        )
        d = r.estimate[-20:].astype(np.float64) - field.data[41:61]
        out.append(np.sqrt(np.mean(d**2)))
    return float(np.mean(out))


def _legs(field, predictor, blend: str, n: int = 3, *, seed: int = 0, **kw) -> tuple[PasstLoop, object]:
    """(loop, last leg's samples): a loop with ``prior_blend=blend`` (``kw``: more PasstLoop options)
    after ``n`` random-walk legs of 5 snapshots from (10, 10); leg k's sensor seed is k + 10 * seed."""
    from passt_mav.loop.passt import FieldSampler

    loop = PasstLoop(
        predictor, field.grid, planner="random", path_length=25, steps_per_leg=5, prior_blend=blend, seed=seed, **kw
    )
    state, samples = field.data[0], None
    for k in range(n):
        leg = loop.plan_leg(state, (10, 10), float(5 * k), 1.0, steps=5)
        sampler = FieldSampler(field, noise_std=0.02, steps_per_leg=5, seed=k + 10 * seed)
        samples = sampler.sample_path(leg.path, leg.t_start)
        state = loop.update(leg, samples)
    return loop, samples


@pytest.fixture(scope="module")
def field():
    return make_field(T=61, R=20, C=20, vel=TRUE_VEL)


def test_a_right_model_keeps_its_weight(field):
    good = ShiftPredictor(TRUE_VEL)
    off, bma = _final(field, good, "off"), _final(field, good, "bma")
    assert bma <= 1.01 * off
    loop, _ = _legs(field, good, "bma")
    assert loop.weights()[0] > 0.99  # the model (exact here) against persistence
    assert len(loop.blend_history_) == 3 and set(loop.blend_history_[0]["weights"]) == {"model", "persistence", "none"}


def test_a_model_worse_than_persistence_is_outweighed(field):
    wrong = ShiftPredictor((-3 * TRUE_VEL[0], -3 * TRUE_VEL[1]))  # drifts the wrong way, fast
    off, bma = _final(field, wrong, "off"), _final(field, wrong, "bma")
    pers = _final(field, Persistence(), "off")
    assert off > 1.3 * pers  # the test's premise: this model is worse than persistence
    assert bma <= 1.05 * pers and bma < 0.8 * off


def test_bad_settings_are_refused(field):
    with pytest.raises(ReconstructionError, match="prior blend"):
        PasstLoop(Persistence(), field.grid, prior_blend="mix")
    with pytest.raises(ReconstructionError, match="forgetting"):
        PasstLoop(Persistence(), field.grid, prior_blend="bma", forgetting=1.5)


@pytest.mark.parametrize("share", [0.0, 0.05])
def test_select_takes_the_more_probable_prior_alone(field, share):
    """prior_blend="select": the right model is never mixed with persistence (the estimate is the
    model-only loop's to the bit while the model stays the more probable), and a model worse than
    persistence is switched off (PASST within 5 % of persistence-prior PASST). The weights recorded
    are the ones the prior used (one-hot), beside the posterior. Also with the missions' default
    share (0.05): the share's floor weights never reach the prior (``bma`` with it mixed 3.6 %
    persistence into the right model on the North Atlantic demo)."""
    good = ShiftPredictor(TRUE_VEL)
    assert _final(field, good, "select", share=share) == _final(field, good, "off")
    wrong = ShiftPredictor((-3 * TRUE_VEL[0], -3 * TRUE_VEL[1]))
    sel, off = _final(field, wrong, "select", share=share), _final(field, wrong, "off")
    pers = _final(field, Persistence(), "off")
    assert sel <= 1.05 * pers and sel < 0.8 * off, (sel, off, pers)
    loop, _ = _legs(field, wrong, "select", share=share)
    last = loop.blend_history_[-1]
    assert last["weights"] == {"model": 0.0, "persistence": 1.0, "none": 0.0}
    assert last["posterior"]["persistence"] > 0.5 and np.array_equal(loop.mixing_weights(), [0.0, 1.0, 0.0])


def _tidal_field():
    """The test pattern standing still and reversing every 5 snapshots (u, v times cos(pi t / 5)): a
    leg of 5 snapshots ends on the negative of its start, so persistence's error is twice the
    field's own size and no forecast (a zero prior mean: the samples' GP alone) is the better prior."""
    from passt_mav.fields.field import FlowField

    base = make_field(T=1, R=20, C=20, vel=(0.0, 0.0))
    t = np.arange(61, dtype=float)
    data = (base.data[0][None] * np.cos(np.pi * t / 5.0)[:, None, None, None]).astype(np.float32)
    return FlowField(data, base.grid, t, None, "m s-1")


def test_select_drops_a_forecast_worse_than_none():
    """On a reversing (tidal) current, persistence as the prior makes samples fight a stale snapshot;
    "select" moves the prior to none (the third candidate) and PASST ends well below the
    persistence-prior loop and no worse than a loop whose GP has no prior mean (prior="none", whose
    estimate is still held through each leg). Measured (3 seeds, final 20 steps): select 0.243,
    off 0.697, prior "none" 0.372; the field's own RMS 0.247."""
    tide = _tidal_field()
    pers = Persistence()
    sel, off = _final(tide, pers, "select"), _final(tide, pers, "off")
    alone = _final(tide, pers, "off", prior="none")
    assert sel < 0.8 * off and sel <= 1.05 * alone, (sel, off, alone)
    loop, _ = _legs(tide, pers, "select", 6)
    assert loop.blend_history_[-1]["weights"]["none"] == 1.0


def test_background_modes_do_not_score_persistence_up(field):
    """The candidates are scored under the stationary kernels and the sensor noise alone, not the
    background modes: those are the flow's own variability, i.e. the error persistence makes, and
    under them a larger persistence residual scored nearly as well as a model's smaller one. A
    model with half the true drift (far better than persistence over the field) with background
    modes on: its score beats persistence's by > 10 nats on every leg (measured 17-63 on 3 seeds x
    6 legs; scored with the modes, 0.5-6.3, and on the oscillating wake's demo legs persistence
    won with a residual of 0.21 against the KNODE's 0.14 (wake units) and PASST ended at 0.34 against 0.12)."""
    half = ShiftPredictor((0.5 * TRUE_VEL[0], 0.5 * TRUE_VEL[1]))
    for s in range(3):
        loop, samples = _legs(field, half, "select", 6, seed=s, background=40)
        assert loop.gp.background is not None
        margins = [h["log_likelihood"]["model"] - h["log_likelihood"]["persistence"] for h in loop.blend_history_]
        assert min(margins) > 10.0, margins
        # modes=False is the covariance without the background and offset modes
        xy, r = samples.xy(field.grid), samples.uv - 0.1
        no_modes = loop.gp.innovation_loglik(xy, r, modes=False)
        bg, loop.gp.background = loop.gp.background, None
        assert no_modes == pytest.approx(loop.gp.innovation_loglik(xy, r), rel=1e-12)
        loop.gp.background = bg


@pytest.mark.parametrize("share, back", [(0.0, False), (0.05, True)])
def test_fixed_share_wins_a_good_model_back_after_one_bad_leg(field, monkeypatch, share, back):
    """share (fixed share, Herbster & Warmuth 1998): one leg where the model misses by 100 nats
    then one where it is 10 nats better than persistence. Without the share the first leg's loss
    (x 0.8 forgetting) still rules and "select" keeps persistence; with share 0.05 no candidate
    fell below 0.05 / 3 before the second leg (ln = -4.1), so the model is selected again."""
    from passt_mav.reconstruction.gp import GPReconstructor

    scores = iter([-100.0, 0.0, -100.0, 0.0, -10.0, -100.0])  # (model, persistence, none) per leg
    monkeypatch.setattr(GPReconstructor, "innovation_loglik", lambda self, *a, **k: next(scores))
    loop, _ = _legs(field, ShiftPredictor(TRUE_VEL), "select", 2, share=share)
    first, second = (h["weights"] for h in loop.blend_history_)
    assert first == {"model": 0.0, "persistence": 1.0, "none": 0.0}
    assert second["model"] == (1.0 if back else 0.0), second
    with pytest.raises(ReconstructionError, match="share"):
        PasstLoop(Persistence(), field.grid, prior_blend="bma", share=1.5)


def test_with_a_share_the_model_starts_alone_and_the_share_is_the_only_doubt(field, monkeypatch):
    """With a fixed share the blend starts on the model alone: a first leg whose samples cannot tell
    the candidates apart (equal scores) leaves bma's weights at the share's floor, 1 - share + share/3
    against share/3 each (0.9667 / 0.0167 / 0.0167 for 0.05), not at the start weights 0.9 / 0.1 / 0.1
    of a loop without a share (the North Atlantic demo's first short leg mixed 16 % persistence into
    the right model that way). Forgetting 1 here: the factor tempers the weights (w ** 0.8), which
    would move both rows towards the uniform."""
    from passt_mav.reconstruction.gp import GPReconstructor

    monkeypatch.setattr(GPReconstructor, "innovation_loglik", lambda self, *a, **k: 0.0)
    for share, want in [(0.05, [1 - 0.05 + 0.05 / 3, 0.05 / 3, 0.05 / 3]), (0.0, [0.9 / 1.1, 0.1 / 1.1, 0.1 / 1.1])]:
        loop, _ = _legs(field, ShiftPredictor(TRUE_VEL), "bma", 1, share=share, forgetting=1.0)
        got = loop.blend_history_[0]["weights"]
        assert [got[k] for k in ("model", "persistence", "none")] == pytest.approx(want, abs=1e-12), share


def test_forgetting_returns_to_the_start_weights_not_to_the_uniform(field, monkeypatch):
    """The forgetting factor discounts old evidence towards the start weights (0.9 / 0.1 / 0.1: a
    margin of ln 9 = 2.20 nats for the model), not towards the uniform. Three legs whose samples
    cannot tell the model from persistence, then one leg 1.5 nats in persistence's favour (the size
    of the swing that flipped a North Atlantic demo walk to persistence, 5x the model's RMSE):
    "select" keeps the model (2.20 - 1.5 = 0.70; forgetting towards the uniform had left
    2.20 x 0.8^3 = 1.12 and switched). Evidence that persists still rules: 1 nat a leg for
    persistence switches on the third leg (margins 1.20, 0.40, -0.24)."""
    from passt_mav.reconstruction.gp import GPReconstructor

    def run(scores, n):
        it = iter(scores)
        monkeypatch.setattr(GPReconstructor, "innovation_loglik", lambda self, *a, **k: next(it))
        loop, _ = _legs(field, ShiftPredictor(TRUE_VEL), "select", n)
        return loop

    quiet = [-5.0, -5.0, -400.0] * 3 + [-6.5, -5.0, -400.0]
    loop = run(quiet, 4)
    assert [h["weights"]["model"] for h in loop.blend_history_] == [1.0] * 4
    post = loop.blend_history_[-1]["posterior"]
    assert np.log(post["model"] / post["persistence"]) == pytest.approx(np.log(9.0) - 1.5, abs=1e-9)
    steady = [-6.0, -5.0, -400.0] * 4
    loop = run(steady, 4)
    assert [h["weights"]["model"] for h in loop.blend_history_] == [1.0, 1.0, 0.0, 0.0]
