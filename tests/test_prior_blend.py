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
from passt_mav.loop.blend import PriorBlend
from passt_mav.loop.engine import run_offline
from passt_mav.loop.passt import PasstLoop
from passt_mav.loop.presets import PAPER

TRUE_VEL = (0.05, 0.12)


class Persistence:
    def fit(self, field):
        return self

    def predict(self, state, steps):
        return np.repeat(np.asarray(state, np.float32)[None], steps, axis=0)


#: _final's results by (field, predictor, blend, options): deterministic, and several tests need the same
#: reference loops (the model-only loop, persistence as the prior)
_FINAL: dict[tuple, float] = {}


def _final(field, predictor, blend, seeds=range(3), **loop_kw):
    """Mean over ``seeds`` of the final 20 steps' RMSE of a random-walk loop (``loop_kw``: more options)."""
    key = (
        id(field),
        getattr(predictor, "vel", type(predictor).__name__),
        blend,
        tuple(seeds),
        tuple(sorted(loop_kw.items())),
    )
    if key not in _FINAL:
        _FINAL[key] = _final_uncached(field, predictor, blend, seeds, **loop_kw)
    return _FINAL[key]


def _final_uncached(field, predictor, blend, seeds, **loop_kw):
    out = []
    for s in seeds:
        r = run_offline(
            field,
            predictor,
            start_cell=(15, 15),
            n_steps=60,
            noise_std=0.02,
            seed=s,
            **PAPER.kwargs(
                planner="random", path_length=25, steps_per_leg=5, prior_blend=blend, background=0, **loop_kw
            ),
        )
        d = r.estimate[-20:].astype(np.float64) - field.data[41:61]
        out.append(np.sqrt(np.mean(d**2)))
    return float(np.mean(out))


def _legs(field, predictor, blend: str, n: int = 3, *, seed: int = 0, **kw) -> tuple[PasstLoop, object]:
    """(loop, last leg's samples): a loop with ``prior_blend=blend`` (``kw``: more PasstLoop options)
    after ``n`` random-walk legs of 5 snapshots from (10, 10); leg k's sensor seed is k + 10 * seed."""
    from passt_mav.loop.passt import FieldSampler

    loop = PasstLoop(
        predictor,
        field.grid,
        **PAPER.kwargs(
            planner="random", path_length=25, steps_per_leg=5, prior_blend=blend, seed=seed, **{"background": 0, **kw}
        ),
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
    # the model (exact here, restarted or alone: the two are the same forecast) against persistence
    assert loop.weights()[0] + loop.weights()[1] > 0.99
    assert len(loop.blend_history_) == 3
    assert set(loop.blend_history_[0]["weights"]) == {"model", "open_loop", "persistence"}


def test_a_model_worse_than_persistence_is_outweighed(field):
    wrong = ShiftPredictor((-3 * TRUE_VEL[0], -3 * TRUE_VEL[1]))  # drifts the wrong way, fast
    off, bma = _final(field, wrong, "off", guard="off"), _final(field, wrong, "bma", guard="off")
    pers = _final(field, Persistence(), "off", guard="off")
    assert off > 1.3 * pers  # the test's premise: this model is worse than persistence
    assert bma <= 1.05 * pers and bma < 0.8 * off
    # the guard alone (no blend) also leaves the restarted forecast when it explains the samples worse
    assert _final(field, wrong, "off") < 0.8 * off


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
    # the model restarted and the model alone are both exact here: either may be selected, nothing is lost
    assert _final(field, good, "select", share=share) == pytest.approx(_final(field, good, "off"), rel=1e-2)
    wrong = ShiftPredictor((-3 * TRUE_VEL[0], -3 * TRUE_VEL[1]))
    sel, off = _final(field, wrong, "select", share=share), _final(field, wrong, "off", guard="off")
    pers = _final(field, Persistence(), "off", guard="off")
    assert sel <= 1.05 * pers and sel < 0.8 * off, (sel, off, pers)
    loop, _ = _legs(field, wrong, "select", share=share)
    last = loop.blend_history_[-1]
    best = max(last["posterior"], key=last["posterior"].get)
    assert best != "model" and last["weights"] == {k: float(k == best) for k in last["weights"]}
    assert np.array_equal(loop.mixing_weights(), [float(k == best) for k in last["weights"]])


def _tidal_field(n: int = 20):
    """The test pattern standing still and reversing every 5 snapshots (u, v times cos(pi t / 5)): a
    leg of 5 snapshots ends on the negative of its start, so persistence's error is twice the
    field's own size and no forecast (a zero prior mean: the samples' GP alone) is the better prior."""
    from passt_mav.fields.field import FlowField

    base = make_field(T=1, R=n, C=n, vel=(0.0, 0.0))
    t = np.arange(61, dtype=float)
    data = (base.data[0][None] * np.cos(np.pi * t / 5.0)[:, None, None, None]).astype(np.float32)
    return FlowField(data, base.grid, t, None, "m s-1")


def test_far_from_the_samples_the_analysis_is_a_forecast_never_zero():
    """On a reversing (tidal) current, persistence's stale snapshot fits a leg's samples worse than
    no forecast at all; a zero mean was once a candidate and "select" took it, so the estimate fell
    to about 0 wherever no sample reached. Every candidate is now a whole-field forecast: on cells
    the samples do not reach (farther than 3 of the kernel's longest length scale, 6 cells), the
    estimate at the leg's end stays within 5 % (RMS) of the background the blend chose, never near 0."""
    tide = _tidal_field(40)
    pers = Persistence()
    loop = PasstLoop(
        pers,
        tide.grid,
        **PAPER.kwargs(planner="random", path_length=6, steps_per_leg=5, prior_blend="select", background=0),
    )
    from passt_mav.loop.passt import PRIOR_CANDIDATES, FieldSampler

    assert "none" not in PRIOR_CANDIDATES
    rr, cc = np.meshgrid(np.arange(40), np.arange(40), indexing="ij")
    state = tide.data[0]
    for k in range(4):
        leg = loop.plan_leg(state, (2, 2), float(5 * k), 1.0, steps=5)
        samples = FieldSampler(tide, noise_std=0.02, steps_per_leg=5, seed=k).sample_path(leg.path, leg.t_start)
        fc = np.asarray(leg.forecast, float)
        cands = PriorBlend.candidates(fc, loop.open_loop_forecast(leg.t_start, leg.dt, fc.shape[0]))
        state = loop.update(leg, samples)
        chosen = cands[int(np.argmax(loop.mixing_weights()))][-1]
        # where no sample reaches: beyond 3 of the kernel's longest length scale (6 cells)
        d = np.min(np.hypot(rr[..., None] - samples.r, cc[..., None] - samples.c), axis=-1)
        far = d > 18
        assert far.sum() > 100, far.sum()
        size = np.sqrt(np.mean(chosen[:, far] ** 2))
        assert np.sqrt(np.mean((state[:, far] - chosen[:, far]) ** 2)) < 0.05 * size, k
        assert np.sqrt(np.mean(state[:, far] ** 2)) > 0.9 * size, k


def test_the_guard_falls_back_when_the_restart_state_is_poor(field):
    """Item 2's guard on a case built to fail: an exact model, but the state it restarts from after
    the first leg is replaced by zeros (a reconstruction gone wrong). The guard scores the loop's
    forecast and the model alone at the next leg's samples (no truth read): the loop's is far worse,
    so that leg falls back to the model alone and says so; the estimate is then close to the truth
    (the exact model alone plus the GP's correction), where without the guard it stays near the
    zero forecast it was restarted from."""
    from passt_mav.loop.guard import guard_message
    from passt_mav.loop.passt import FieldSampler

    good = ShiftPredictor(TRUE_VEL)

    def fly(guard):
        loop = PasstLoop(
            good,
            field.grid,
            **PAPER.kwargs(planner="random", path_length=25, steps_per_leg=5, guard=guard, background=0),
        )
        state = field.data[0]
        for k in range(2):
            leg = loop.plan_leg(state, (10, 10), float(5 * k), 1.0, steps=5)
            samples = FieldSampler(field, noise_std=0.02, steps_per_leg=5, seed=k).sample_path(leg.path, leg.t_start)
            state = loop.update(leg, samples)
            if k == 0:
                state = np.zeros_like(state)  # the restart state gone wrong
        err = float(np.sqrt(np.mean((state.astype(float) - field.data[10]) ** 2)))
        return loop, err

    on, err_on = fly("on")
    off, err_off = fly("off")
    size = float(np.sqrt(np.mean(field.data[10].astype(float) ** 2)))
    rec = on.guard_history_[-1]
    assert not on.guard_history_[0]["behind"]  # the first leg: the two forecasts are one
    assert rec["behind"] and rec["fallback"] and rec["alarm"] and rec["rmse_loop"] > 5 * rec["rmse_open_loop"]
    assert rec["loglik_loop"] < rec["loglik_open_loop"]
    assert off.guard_history_ == [] and err_off > 0.5 * size
    assert err_on < 0.1 * size, (err_on, err_off, size)
    msg = guard_message(rec, leg_label="leg 2")
    assert msg.startswith("sampling is not helping: at leg 2's samples") and "\n" not in msg
    assert on.gp_summary()["guard"]["fallback"] is True


def test_the_guard_falls_back_when_behind_and_alarms_after_two_legs_or_a_margin():
    """guard_record's rule: behind falls back at once; the alarm needs a second leg running or more than
    the margin; ahead resets the count."""
    from passt_mav.loop.guard import GUARD_MARGIN, guard_record

    uv = np.zeros((10, 2))
    hist: list[dict] = []

    def rec(loop_err, open_err):
        r = guard_record(len(hist), uv, np.full((10, 2), loop_err), np.full((10, 2), open_err), lambda r: 0.0, hist)
        hist.append(r)
        return r

    small = 1.0 + GUARD_MARGIN / 2
    first = rec(small, 1.0)
    assert [first[k] for k in ("behind", "fallback", "alarm")] == [True, True, False]
    assert rec(small, 1.0)["alarm"] and hist[-1]["behind_legs"] == 2
    assert not rec(0.5, 1.0)["behind"] and hist[-1]["behind_legs"] == 0 and not hist[-1]["fallback"]
    assert rec(1.0 + 2 * GUARD_MARGIN, 1.0)["alarm"]


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

    scores = iter([-100.0, -100.0, 0.0, 0.0, -100.0, -10.0])  # (model, open_loop, persistence) per leg
    monkeypatch.setattr(GPReconstructor, "innovation_loglik", lambda self, *a, **k: next(scores))
    loop, _ = _legs(field, ShiftPredictor(TRUE_VEL), "select", 2, share=share, guard="off")
    first, second = (h["weights"] for h in loop.blend_history_)
    assert first == {"model": 0.0, "open_loop": 0.0, "persistence": 1.0}
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
        assert [got[k] for k in ("model", "open_loop", "persistence")] == pytest.approx(want, abs=1e-12), share


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
        loop, _ = _legs(field, ShiftPredictor(TRUE_VEL), "select", n, guard="off")
        return loop

    quiet = [-5.0, -400.0, -5.0] * 3 + [-6.5, -400.0, -5.0]  # (model, open_loop, persistence) per leg
    loop = run(quiet, 4)
    assert [h["weights"]["model"] for h in loop.blend_history_] == [1.0] * 4
    post = loop.blend_history_[-1]["posterior"]
    assert np.log(post["model"] / post["persistence"]) == pytest.approx(np.log(9.0) - 1.5, abs=1e-9)
    steady = [-6.0, -400.0, -5.0] * 4
    loop = run(steady, 4)
    assert [h["weights"]["model"] for h in loop.blend_history_] == [1.0, 1.0, 0.0, 0.0]


def test_a_restarted_correction_fades_to_the_model_alone_as_the_gp_s_time_kernel_says():
    """``relax_to_open_loop``: the restarted forecast's departure from the model alone is weighted by the
    GP's Matern-5/2 correlation in time since the reconstruction: 1 at lag 0, (1 + sqrt5 + 5/3)
    exp(-sqrt5) = 0.524 at one time length scale, below 1e-3 at five; u and v by their own kernels;
    a space-only kernel leaves the forecast unchanged."""
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    from passt_mav.loop.guard import relax_to_open_loop

    def kern(lt, ndim=3):
        ls = [1000.0, 1000.0, lt][:ndim]
        return ConstantKernel(0.04) * Matern(length_scale=ls, nu=2.5) + WhiteKernel(1e-4)

    lt_u, lt_v = 3600.0, 7200.0
    times = 1e5 + np.array([0.0, 3600.0, 5 * 3600.0])
    fc = np.ones((3, 2, 4, 5))
    open_fc = np.zeros_like(fc)
    out = relax_to_open_loop(fc, open_fc, times, times[0], [kern(lt_u), kern(lt_v)])
    m52 = (1 + np.sqrt(5) + 5 / 3) * np.exp(-np.sqrt(5))
    assert out[0] == pytest.approx(fc[0])
    assert out[1, 0] == pytest.approx(np.full((4, 5), m52), rel=1e-9)
    assert out[2, 0].max() < 1e-3 and out[2, 1].min() > out[2, 0].max()  # v's longer time scale fades later
    same = relax_to_open_loop(fc, open_fc, times, times[0], [kern(0, 2), kern(0, 2)])
    assert same is fc
