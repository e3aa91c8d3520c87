"""KNODE training for the loop: GP-residual noise, roll-out loss with curriculum, validation and
best-epoch selection, the skill report and its warning, the compiled fast path."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from passt_mav.models.base import load_predictor, make_predictor

torch = pytest.importorskip("torch")

from test_models import SMALL, _one_thread, wave_field  # noqa: F401 - _one_thread: the same autouse fixture here

LOOP = dict(
    loss="rollout",
    horizon=4,
    curriculum=0.5,
    noise="gp",
    noise_samples=4,
    noise_path_length=20,
    val_frac=0.25,
    zero_init=True,
    train_batch=16,
)


@pytest.fixture(scope="module")
def wave():
    return wave_field(T=40)


@pytest.mark.parametrize("ell", [1.0, 2.0, 4.0])
def test_correlated_noise_has_the_asked_size_and_correlation(ell):
    """Noise drawn with correlation length l (cells) and amplitude a: per-pixel std a within 5 %,
    and correlation_length() measures l back within 15 %."""
    from passt_mav.models.noise import CorrelatedNoise, correlation_length

    amp = np.full((2, 40, 40), 0.3, np.float32)
    gen = torch.Generator().manual_seed(0)
    n = CorrelatedNoise(amp, ell).sample((200, 2, 40, 40), gen).numpy()
    assert n.std() == pytest.approx(0.3, rel=0.05)
    assert correlation_length(n) == pytest.approx(ell, rel=0.15)


def test_white_noise_has_correlation_length_below_one_cell():
    from passt_mav.models.noise import correlation_length

    assert correlation_length(np.random.default_rng(0).normal(size=(50, 2, 30, 30))) <= 0.5


def test_gp_reconstructions_beat_their_stale_prior(wave):
    """A GP state from a 20-move path is closer to the truth than its prior (the truth one step earlier)."""
    from passt_mav.models.noise import reconstruct_states

    ts = np.arange(5, 35, 5)
    rec = reconstruct_states(wave.data, wave.grid, wave.times, ts, path_length=20, lag=1, noise_std=0.01, seed=0)
    err_rec = np.sqrt(np.mean((rec - wave.data[ts]) ** 2))
    err_prior = np.sqrt(np.mean((wave.data[ts - 1] - wave.data[ts]) ** 2))
    assert err_rec < 0.9 * err_prior, (err_rec, err_prior)  # measured 0.84x with 20 of 256 cells sampled
    again = reconstruct_states(wave.data, wave.grid, wave.times, ts, path_length=20, lag=1, noise_std=0.01, seed=0)
    np.testing.assert_array_equal(rec, again)  # seeded


def test_zero_init_untrained_model_is_persistence(wave):
    m = make_predictor("knode", epochs=0, zero_init=True, **SMALL).fit(wave, start=0, stop=20)
    x = wave.data[25]
    np.testing.assert_allclose(m.predict(x, 3), np.repeat(x[None], 3, axis=0), atol=1e-5)


def test_curriculum_grows_the_rollout_to_the_horizon():
    m = make_predictor("knode", loss="rollout", horizon=10, curriculum=0.5, **SMALL)
    hs = [m._horizon_at(ep, 40) for ep in range(40)]
    assert hs[0] == 1 and hs[-1] == 10 and hs[20:] == [10] * 20 and all(a <= b for a, b in itertools.pairwise(hs))
    assert make_predictor("knode", loss="one_step", **SMALL)._horizon_at(30, 40) == 1
    assert make_predictor("knode", loss="rollout", horizon=7, curriculum=0.0, **SMALL)._horizon_at(0, 40) == 7


def test_rollout_training_improves_validation_and_keeps_the_best_epoch(wave, tmp_path):
    """On a travelling wave, 30 epochs of roll-out training end with a validation roll-out loss
    (from true and GP-reconstructed states) well below persistence's (epoch 0 of a zero-init
    model); the kept weights are those of the best validation epoch and survive a save/load."""
    m = make_predictor("knode", epochs=30, lr=3e-3, substeps=2, seed=0, **LOOP, **SMALL).fit(wave, start=0, stop=32)
    assert m.val_window_ == [24, 32] and m.train_window_ == [0, 32]
    assert len(m.val_curve_) == 31  # epoch 0 (persistence) + one per epoch
    assert min(m.val_curve_) < 0.5 * m.val_curve_[0], m.val_curve_
    assert m.val_curve_[m.best_epoch_] == pytest.approx(min(m.val_curve_[16:] + [m.val_curve_[0]]))
    info = m.noise_info_
    assert info["kind"] == "gp" and info["rms"] > 0 and info["corr_cells"] >= 0.5 and info["n"] == 4
    m.save(tmp_path / "k")
    meta = json.loads((tmp_path / "k.json").read_text())
    assert meta["params"]["loss"] == "rollout" and meta["best_epoch"] == m.best_epoch_ and len(meta["val_curve"]) == 31
    np.testing.assert_array_equal(
        load_predictor(tmp_path / "k.pt").predict(wave.data[30], 2), m.predict(wave.data[30], 2)
    )


def test_bad_training_options():
    from passt_mav.errors import ModelError

    for kw in ({"loss": "two_step"}, {"noise": "pink"}, {"horizon": 0}, {"val_frac": 0.95}):
        with pytest.raises(ModelError):
            make_predictor("knode", epochs=1, **SMALL, **kw).fit(wave_field(T=20), start=0, stop=20)


def test_skill_report_and_warning(wave):
    """The report compares with persistence and DMD on the held-out window from true and GP
    starts; a model that loses to persistence (an untrained, randomly initialised net) triggers
    the one-line warning, a trained one on this easy wave does not."""
    from passt_mav.models.evaluate import skill_lines, skill_report, skill_warning

    bad = make_predictor("knode", epochs=0, seed=3, **SMALL).fit(wave, start=0, stop=30)
    rep = skill_report(bad, wave, train=(0, 30), val=(30, 40), horizon=4)
    assert set(rep["true"]) == {"model", "persistence", "dmd"} and rep["lookaheads"] == [1, 2, 5]
    assert not rep["verdict"]["true"]["beats_persistence"]
    w = skill_warning({"skill": rep})
    assert w.startswith("warning: this model is worse than persistence") and "\n" not in w
    good = make_predictor("knode", epochs=30, lr=3e-3, substeps=2, seed=0, **LOOP, **SMALL).fit(wave, start=0, stop=32)
    rep2 = skill_report(good, wave, train=(0, 24), val=(24, 32), horizon=4)
    assert rep2["verdict"]["true"]["beats_persistence"] and rep2["verdict"]["gp"]["beats_persistence"], rep2["verdict"]
    assert skill_warning({"skill": rep2}) is None
    assert len(skill_lines(rep2)) == 2 + 2 * len(rep2["lookaheads"]) + 2


def test_train_cli_prints_skill_and_warns(tmp_path, capsys):
    """`passt-mav model train` (loop recipe) on a short file prints the skill table and stores it."""
    from passt_mav.cli import main

    nc = wave_field(T=40).to_netcdf(tmp_path / "w.nc")
    out = tmp_path / "k"
    rc = main(
        [
            "model",
            "train",
            "--data",
            str(nc),
            "--start",
            "0",
            "--stop",
            "40",
            "--epochs",
            "1",
            "--horizon",
            "3",
            "--substeps",
            "1",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "skill on the held-out window 32:40" in text and "from GP reconstructions" in text
    meta = json.loads((tmp_path / "k.json").read_text())
    assert meta["skill"]["window"] == [32, 40] and meta["recipe"] == "loop" and meta["val_window"] == [32, 40]


def test_compile_falls_back_to_eager_when_the_compiler_fails(monkeypatch):
    from passt_mav.models import fast

    def broken(*a, **k):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(torch, "compile", broken)
    msgs = []
    f = fast.compiled_or_eager(lambda x: 2 * x, warn=msgs.append)
    assert float(f(torch.tensor(3.0))) == 6.0 and float(f(torch.tensor(1.0))) == 2.0
    assert len(msgs) == 1 and "eager" in msgs[0]


@pytest.mark.slow(reason="torch inductor compiles the snapshot step: ~1 min on two cores")
def test_compiled_training_follows_the_eager_training(wave, tmp_path):
    """``compile=True`` (compiled snapshot step): the same training to fp32 rounding -
    loss curves of 3 roll-out epochs within 1e-3 relative, the same predictions to 1e-3 - and
    the kept network is saved and reloaded exactly."""
    kw = dict(epochs=3, lr=3e-3, substeps=2, seed=0, loss="rollout", horizon=3, curriculum=0.0, train_batch=8, **SMALL)
    e = make_predictor("knode", **kw).fit(wave, start=0, stop=24)
    c = make_predictor("knode", compile=True, **kw).fit(wave, start=0, stop=24)
    np.testing.assert_allclose(c.loss_curve_, e.loss_curve_, rtol=1e-3)
    x = wave.data[25]
    np.testing.assert_allclose(c.predict(x, 3), e.predict(x, 3), rtol=1e-3, atol=1e-4)
    assert all(p.is_contiguous() for p in c.net_.parameters())
    c.save(tmp_path / "c")
    np.testing.assert_array_equal(load_predictor(tmp_path / "c.pt").predict(x, 3), c.predict(x, 3))


@pytest.mark.slow(reason="torch inductor compiles the snapshot step: ~1 min on two cores")
def test_compiled_step_equals_eager_to_fp32_tolerance():
    from passt_mav.models import fast
    from passt_mav.models.knode import KnodeNet, ode_step

    torch.manual_seed(0)
    net = KnodeNet(30, 30)
    x = torch.randn(8, 2, 30, 30)
    eager = lambda z: ode_step(net, z, 1.0, 6)
    f = fast.compiled_or_eager(eager, net)
    with torch.no_grad():
        torch.testing.assert_close(f(x), eager(x), rtol=1e-5, atol=1e-5)


def _fast_and_eager(wave):
    """(a small fitted KNODE with ``fast_predict`` on and its compiled step built, a state, the eager roll-out)."""
    m = make_predictor("knode", epochs=2, substeps=2, seed=0, **SMALL).fit(wave, start=0, stop=20)
    x = wave.data[20:23]
    eager = m.predict(x, 4)
    m.fast_predict = True
    fast = m.predict(x, 4)
    assert m._fast_step.is_compiled()
    np.testing.assert_allclose(fast, eager, rtol=1e-5, atol=1e-5)
    return m, x, eager


def test_fast_predict_equals_eager_and_is_not_pickled(wave):
    """``fast_predict``: the compiled (inductor freezing) prediction path gives the eager
    roll-out to fp32 rounding, is really compiled here (gcc is there) and is not pickled to workers."""
    import cloudpickle

    m, x, _ = _fast_and_eager(wave)
    if torch.backends.mkldnn.is_available():  # freezing really on: pre-packed oneDNN convolutions, not aten's
        with torch.profiler.profile() as prof:
            m.predict(x, 1)
        ops = {e.key for e in prof.key_averages()}
        assert "mkldnn::_convolution_pointwise" in ops and "aten::convolution" not in ops, sorted(
            o for o in ops if "conv" in o
        )
    w = cloudpickle.loads(cloudpickle.dumps(m))
    assert w.fast_predict and "_fast_step" not in vars(w)


@pytest.mark.slow(reason="two more inductor compilations (a worker's copy, a refitted network): ~1 min on two cores")
def test_fast_predict_in_a_worker_and_after_a_refit_follows_the_network(wave):
    """An unpickled copy compiles its own step and predicts the eager roll-out; a refitted network gets
    its own compiled step (frozen weights would be stale)."""
    import cloudpickle

    m, x, eager = _fast_and_eager(wave)
    w = cloudpickle.loads(cloudpickle.dumps(m))
    np.testing.assert_allclose(w.predict(x, 4), eager, rtol=1e-5, atol=1e-5)
    m.fit(wave, start=0, stop=20, epochs=3)  # new weights: the old frozen step must not be reused
    m.fast_predict = False
    eager2 = m.predict(x, 4)
    m.fast_predict = True
    np.testing.assert_allclose(m.predict(x, 4), eager2, rtol=1e-5, atol=1e-5)
    assert np.abs(eager2 - eager).max() > 1e-4  # the refit really changed the model


def test_fine_tuning_starts_from_the_checkpoint_and_never_ends_worse(wave, tmp_path):
    """``init``: the start model's weights and scaler are taken (0 epochs = the start model exactly),
    the start model competes as epoch 0 of the best-epoch selection (the kept weights validate no
    worse than it), the checkpoint records where it started, and a wrong grid is refused."""
    from passt_mav.errors import ModelError

    base = make_predictor("knode", epochs=6, lr=3e-3, substeps=2, seed=0, **LOOP, **SMALL).fit(wave, start=0, stop=32)
    base.save(tmp_path / "base")
    x = wave.data[33]
    # 0 epochs from the start model: the same predictions (weights AND scaler carried over), on a
    # different window, whose own scaler would differ
    same = make_predictor("knode", epochs=0, substeps=2, seed=0, init=str(tmp_path / "base.pt"), **LOOP, **SMALL).fit(
        wave, start=4, stop=36
    )
    np.testing.assert_allclose(same.predict(x, 3), base.predict(x, 3), atol=1e-6)
    tuned = make_predictor(
        "knode",
        epochs=6,
        lr=1e-3,
        substeps=2,
        seed=1,
        init=str(tmp_path / "base.pt"),
        **dict(LOOP, horizon=6, curriculum=0.0),
        **SMALL,
    ).fit(wave, start=0, stop=32)
    assert tuned.val_curve_[tuned.best_epoch_] <= tuned.val_curve_[0]
    tuned.save(tmp_path / "tuned")
    assert json.loads((tmp_path / "tuned.json").read_text())["params"]["init"] == str(tmp_path / "base.pt")
    np.testing.assert_allclose(load_predictor(tmp_path / "tuned.pt").predict(x, 2), tuned.predict(x, 2), atol=1e-6)
    small = wave_field(T=40, R=12, C=12)
    with pytest.raises(ModelError, match="do not match"):
        make_predictor("knode", epochs=1, substeps=2, init=str(tmp_path / "base.pt"), **LOOP, **SMALL).fit(
            small, start=0, stop=32
        )


def test_a_window_too_short_for_the_horizon_is_a_one_line_error(tmp_path, capsys):
    """17 snapshots with 20 % validation leave 6 to train on: a 10-snapshot roll-out is refused
    before any epoch (it used to end in a ZeroDivisionError traceback), exit 2, naming the fix."""
    from passt_mav.cli import main

    path = tmp_path / "short.nc"
    wave_field(T=17).to_netcdf(path)
    assert (
        main(["model", "train", "--data", str(path), "--epochs", "2", "--no-skill", "--out", str(tmp_path / "k")]) == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "too few for a roll-out of 10" in err[0] and "--horizon" in err[0]


def band_field(T=40, R=16, C=16, centre=6.0):
    """A travelling wave (period 12 snapshots) confined to a band of rows around ``centre``
    (Gaussian envelope, width 2 rows) on a uniform stream: a toy wake whose position across the
    stream is set by ``centre``."""
    from passt_mav.fields.field import FlowField

    rr, cc = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
    env = np.exp(-0.5 * ((rr - centre) / 2.0) ** 2)
    t = np.arange(T)[:, None, None]
    u = 0.5 + 0.3 * env * np.sin(2 * np.pi * (cc / C - t / 12))
    v = 0.3 * env * np.cos(2 * np.pi * (cc / C - t / 12))
    data = np.stack([u, v], axis=1).astype(np.float32)
    return FlowField(data, wave_field(T=T, R=R, C=C).grid, np.arange(T, dtype=float) * 0.4, None, "1")


def test_shift_field_rows_moves_rows_and_replicates_the_edge():
    from passt_mav.models.knode import shift_field_rows

    a = np.arange(2 * 5 * 3, dtype=np.float32).reshape(2, 5, 3)
    assert shift_field_rows(a, 0) is a
    up = shift_field_rows(a, 2)
    np.testing.assert_array_equal(up[:, 2:], a[:, :3])
    np.testing.assert_array_equal(up[:, :2], a[:, :1].repeat(2, axis=1))
    down = shift_field_rows(a, -1)
    np.testing.assert_array_equal(down[:, :4], a[:, 1:])
    np.testing.assert_array_equal(down[:, 4], a[:, 4])


@pytest.mark.long(reason="trains two KNODEs (with and without the shift) long enough to tell them apart: ~16 s")
def test_row_shift_augmentation_generalises_to_a_displaced_band(tmp_path):
    """A model trained on a band centred on row 6 is rolled out on the same band centred on row 9
    (never in its training data). Trained with ``shift_rows=3`` (the training roll-outs moved by
    up to 3 rows; the scaler taken over the shifted copies) it beats persistence there, while the
    same training without the augmentation blows up (in its per-pixel scaling the displaced band
    is far outside the training data). Measured, 4-step roll-out MSE: shift_rows=3 0.0141,
    persistence 0.0299, unaugmented 1.09 (same seed, 30 epochs)."""
    from passt_mav.models.evaluate import lookahead_errors

    train, test = band_field(centre=6.0), band_field(centre=9.0)
    kw = dict(epochs=30, lr=3e-3, substeps=2, seed=0, **LOOP, **SMALL)
    plain = make_predictor("knode", **kw).fit(train, start=0, stop=32)
    shifted = make_predictor("knode", shift_rows=3, **kw).fit(train, start=0, stop=32)
    e_plain = lookahead_errors(plain, test.data, (0, 40), (4,), ic_stride=2)[4]["mse"]
    e_shift = lookahead_errors(shifted, test.data, (0, 40), (4,), ic_stride=2)[4]["mse"]
    e_pers = lookahead_errors(
        make_predictor("persistence").fit(train, start=0, stop=32), test.data, (0, 40), (4,), ic_stride=2
    )[4]["mse"]
    print("displaced band, h=4 MSE: plain", e_plain, "shift_rows=3", e_shift, "persistence", e_pers)
    assert e_shift < e_pers < e_plain
    shifted.save(tmp_path / "s")
    assert json.loads((tmp_path / "s.json").read_text())["params"]["shift_rows"] == 3
    assert load_predictor(tmp_path / "s.pt").shift_rows == 3


def test_row_shift_augmentation_refuses_land_and_too_large_shifts(tmp_path, capsys):
    from passt_mav.cli import main
    from passt_mav.errors import ModelError

    f = band_field()
    f.data[:, :, 0, 0] = np.nan
    with pytest.raises(ModelError, match="without land"):
        make_predictor("knode", epochs=1, shift_rows=2, **LOOP, **SMALL).fit(f, start=0, stop=32)
    with pytest.raises(ModelError, match="below the grid's 16 rows"):
        make_predictor("knode", epochs=1, shift_rows=16, **LOOP, **SMALL).fit(band_field(), start=0, stop=32)
    nc = band_field().to_netcdf(tmp_path / "b.nc")
    assert (
        main(
            [
                "model",
                "train",
                "--data",
                str(nc),
                "--epochs",
                "1",
                "--shift-rows",
                "-1",
                "--no-skill",
                "--out",
                str(tmp_path / "k"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shift_rows must be a non-negative integer" in err[0]


def test_shift_fraction_draws_that_share_of_shifts_and_weighs_validation_alike():
    from passt_mav.errors import ModelError

    """``shift_fraction`` p: a share p of the initial conditions is shifted (uniform over the
    2n non-zero shifts), the rest unshifted; validation weighs the unshifted window 1 - p and
    each shift p / 2n. Without it, the draw is uniform over all 2n + 1 shifts (as before)."""
    n_draw = 20000
    k = make_predictor("knode", shift_rows=2, shift_fraction=0.25, **SMALL)
    idx = k._draw_shifts(np.random.default_rng(0), 5, n_draw)
    assert abs(np.mean(idx == 0) - 0.75) < 0.015
    counts = np.bincount(idx, minlength=5)[1:] / n_draw
    np.testing.assert_allclose(counts, 0.25 / 4, atol=0.01)
    assert k._shift_weight(0, 5) == pytest.approx(0.75) and k._shift_weight(-2, 5) == pytest.approx(0.0625)
    assert np.all(
        make_predictor("knode", shift_rows=2, shift_fraction=0.0, **SMALL)._draw_shifts(
            np.random.default_rng(1), 5, 100
        )
        == 0
    )
    assert np.all(
        make_predictor("knode", shift_rows=2, shift_fraction=1.0, **SMALL)._draw_shifts(
            np.random.default_rng(1), 5, 100
        )
        > 0
    )
    old = make_predictor("knode", shift_rows=2, **SMALL)
    np.testing.assert_array_equal(
        old._draw_shifts(np.random.default_rng(3), 5, 50), np.random.default_rng(3).integers(5, size=50)
    )
    assert old._shift_weight(0, 5) == old._shift_weight(2, 5) == 1.0
    with pytest.raises(ModelError, match="shift_fraction"):
        make_predictor("knode", shift_rows=0, shift_fraction=0.5, epochs=1, **LOOP, **SMALL).fit(
            band_field(), start=0, stop=32
        )
