"""The KNODE with DMD's linear operator as knowledge (``knowledge="dmd"``, models/knowledge.py):
the linear term alone reproduces DMD (exactly with the exact propagator, within the stated Euler
error in continuous time), the untrained model's known answer, checkpoints and bad options."""

from __future__ import annotations

import json

import numpy as np
import pytest

import geo
from passt_mav.fields.field import FlowField
from passt_mav.models.base import load_predictor, make_predictor

torch = pytest.importorskip("torch")

from test_models import SMALL, _one_thread  # noqa: E402, F401 - _one_thread: the same autouse fixture here


def two_tone_field(T=60, R=16, C=16):
    """Two travelling waves (periods 12 and 8 snapshots) on a mean flow: a fluctuation of rank 4 whose
    DMD fitted on 24 snapshots (whole periods of both, so the time mean is exact) is exact, eigenvalues
    exp(+-2 pi i / 12) and exp(+-2 pi i / 8)."""
    rr, cc = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
    t = np.arange(T)[:, None, None]
    u = 0.5 + 0.3 * np.sin(2 * np.pi * (cc / C - t / 12)) + 0.2 * np.cos(2 * np.pi * (rr / R - t / 8))
    v = 0.3 * np.cos(2 * np.pi * (rr / R + cc / C - t / 12)) + 0.2 * np.sin(2 * np.pi * (cc / C + t / 8))
    data = np.stack([u, v], axis=1).astype(np.float32)
    grid = geo.MetricRegionGrid(0, C - 1.0, 0, R - 1.0, R, C, anchor_lat=40, anchor_lon=-70)
    return FlowField(data, grid, np.arange(T, dtype=float) * 0.4, None, "1")


@pytest.fixture(scope="module")
def field():
    return two_tone_field()


def _untrained(field, complement, **kw):
    """The KNODE with DMD knowledge and its correction at zero (no epoch), fitted on snapshots 0..24."""
    return make_predictor(
        "knode", epochs=0, zero_init=True, knowledge="dmd", knowledge_complement=complement, **SMALL, **kw
    ).fit(field, start=0, stop=24)


def test_continuous_operator_is_the_log_of_the_discrete_one(field):
    from scipy.linalg import expm

    from passt_mav.models.knowledge import continuous_operator

    dmd = make_predictor("dmd").fit(field, start=0, stop=24)
    assert dmd.rank_ == 4
    Ac, info = continuous_operator(dmd.A_)
    np.testing.assert_allclose(expm(Ac), dmd.A_, atol=1e-12)
    assert info["logm_imag"] == 0.0 and info["expm_error"] < 1e-12
    # continuous-time rates +- 2 pi i / 12 and +- 2 pi i / 8 per snapshot interval
    mu = np.linalg.eigvals(Ac)
    np.testing.assert_allclose(np.sort(np.abs(mu.imag)), np.repeat([2 * np.pi / 12, 2 * np.pi / 8], 2), atol=1e-5)
    np.testing.assert_allclose(mu.real, 0.0, atol=1e-5)


def test_linear_term_alone_reproduces_dmd_exactly_with_the_exact_propagator(field):
    """Correction zeroed, ``complement="drop"``: every step is DMD's ``m + U A U^T (x - m)`` to float32
    rounding, from a state off DMD's subspace (a snapshot plus noise) too."""
    m = _untrained(field, "drop")
    dmd = make_predictor("dmd").fit(field, start=0, stop=24)
    rng = np.random.default_rng(1)
    x = field.data[45] + rng.normal(0, 0.05, field.data[45].shape).astype(np.float32)
    got, want = m.predict(x, 5), dmd.predict(x, 5)
    assert np.max(np.abs(got - want)) < 2e-6 * np.max(np.abs(want))
    assert m.knowledge_info_["rank"] == 4


def test_linear_term_in_continuous_time_matches_dmd_within_the_euler_error(field):
    """``dz/dt = L z`` with n explicit Euler steps over one snapshot interval, from a state in DMD's
    subspace: its distance to DMD's one-step prediction (DMD coordinates y = x - m, 2-norm) stays
    below the Euler bound cond(W) max_j (e^|mu_j| - (1 + |mu_j|/n)^n) |y| (W, mu_j: eigenvectors and
    eigenvalues of A_c; the series of e^mu - (1 + mu/n)^n has non-negative coefficients), plus float32
    rounding, and the error is first order (halves when n doubles)."""
    from passt_mav.models.knode import ode_step

    m = _untrained(field, "keep")
    dmd = make_predictor("dmd").fit(field, start=0, stop=24)
    kn = m.net_.knowledge
    x = field.data[30]  # a training snapshot: y lies in DMD's subspace
    z = torch.from_numpy(((x - m.mean_) / m.std_)[None].astype(np.float32))
    want = dmd.predict(x, 1)[0]
    y = np.linalg.norm(x - dmd.mean_.reshape(x.shape))
    mu, W = np.linalg.eig(kn.Ac.double().numpy())
    errs = []
    for n in (16, 32, 64):
        with torch.no_grad():
            zn = ode_step(kn.rhs, z, 1.0, n, "euler")[0].numpy()
        err = np.linalg.norm(zn * m.std_ + m.mean_ - want)
        bound = np.linalg.cond(W) * np.max(np.exp(np.abs(mu)) - (1 + np.abs(mu) / n) ** n) * y
        assert err <= bound + 1e-5 * y, (n, err, bound)
        errs.append(err)
    assert 1.7 < errs[0] / errs[1] < 2.3 and 1.7 < errs[1] / errs[2] < 2.3, errs
    assert errs[-1] < 5e-3 * y  # 64 Euler steps: within 0.5 % of DMD


@pytest.mark.parametrize("complement,kappa", [("keep", 0.0), (0.3, 0.3), ("0.3", 0.3)])
def test_untrained_model_is_dmd_inside_the_subspace_and_decays_outside(field, complement, kappa):
    """Correction zeroed: y = x - m -> U A U^T y + exp(-kappa) (y - U U^T y); ``"keep"`` is kappa 0
    (persistence outside the subspace); a rate given as text (the command line's) is the same rate."""
    m = _untrained(field, complement)
    assert m.knowledge_complement in ("keep", 0.3)
    dmd = make_predictor("dmd").fit(field, start=0, stop=24)
    rng = np.random.default_rng(2)
    x = field.data[50] + rng.normal(0, 0.05, field.data[50].shape).astype(np.float32)
    mean = dmd.mean_.reshape(x.shape).ravel()
    y = x.ravel().astype(np.float64) - mean
    a = dmd.modes_.T @ y
    want = mean + dmd.modes_ @ (dmd.A_ @ a) + np.exp(-kappa) * (y - dmd.modes_ @ a)
    np.testing.assert_allclose(m.predict(x, 1)[0].ravel(), want, atol=2e-6 * np.max(np.abs(want)))


def test_the_linear_term_never_sees_the_validation_part(field):
    """With a validation split the knowledge is DMD of the training part alone (snapshots 0..31 of
    0..47 here), so the best epoch and the skill report score the linear term out of sample: the
    untrained model forecasts as that DMD, not as DMD of the whole window."""
    m = _untrained(field, "drop", val_frac=1 / 3).fit(field, start=0, stop=48)
    assert m.val_window_ == [32, 48] and m.n_train_ == 32
    part = make_predictor("dmd").fit(field, start=0, stop=32)
    whole = make_predictor("dmd").fit(field, start=0, stop=48)
    x = field.data[50]
    got = m.predict(x, 1)[0]
    np.testing.assert_allclose(got, part.predict(x, 1)[0], atol=2e-5 * np.max(np.abs(got)))
    assert m.knowledge_info_["n_snapshots"] == 32
    # the two DMDs differ by more than the tolerance, so the check above can tell them apart
    assert np.max(np.abs(part.predict(x, 1)[0] - whole.predict(x, 1)[0])) > 1e-3 * np.max(np.abs(got))


def test_dmd_knowledge_checkpoint_round_trip_and_fine_tuning_keeps_the_operator(field, tmp_path):
    m = make_predictor("knode", epochs=2, seed=0, knowledge="dmd", **SMALL).fit(field, start=0, stop=24)
    m.save(tmp_path / "k")
    meta = json.loads((tmp_path / "k.json").read_text())
    assert meta["params"]["knowledge"] == "dmd" and meta["knowledge_info"]["rank"] == 4
    back = load_predictor(tmp_path / "k.pt")
    np.testing.assert_array_equal(back.predict(field.data[45], 3), m.predict(field.data[45], 3))
    # fine-tuning on another window starts from the checkpoint's operator, not a new fit
    ft = make_predictor("knode", epochs=1, seed=0, knowledge="dmd", init=str(tmp_path / "k.pt"), **SMALL)
    ft.fit(field, start=20, stop=60)
    for k in ("U", "Ac", "scale", "offset"):
        assert torch.equal(getattr(ft.net_.knowledge, k), getattr(m.net_.knowledge, k)), k


def test_plain_knode_is_unchanged_by_the_option(field):
    """The default (``knowledge="none"``) builds no linear term: the same weights give the same forecast."""
    a = make_predictor("knode", epochs=1, seed=0, **SMALL).fit(field, start=0, stop=24)
    b = make_predictor("knode", epochs=1, seed=0, knowledge="none", **SMALL).fit(field, start=0, stop=24)
    assert getattr(a.net_, "knowledge", None) is None
    np.testing.assert_array_equal(a.predict(field.data[45], 2), b.predict(field.data[45], 2))


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--knowledge", "dmd", "--method", "rk4"], "method 'rk4' is not available"),
        (["--knowledge", "dmd", "--knowledge-energy", "1.5"], "energy must be in (0, 1]"),
        (["--knowledge", "dmd", "--knowledge-complement", "fast"], "must be keep, drop or a decay rate"),
    ],
)
def test_bad_knowledge_options_are_one_line_errors(field, tmp_path, capsys, args, needle):
    from passt_mav.cli import main

    nc = field.to_netcdf(tmp_path / "f.nc")
    out = tmp_path / "k"
    rc = main(["model", "train", "--data", str(nc), "--epochs", "1", "--no-skill", *args, "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert needle in err[-1] and not list(tmp_path.glob("k.*"))
    assert "Traceback" not in "\n".join(err)


def test_unknown_knowledge_and_complement_name_the_choices(field):
    from passt_mav.errors import ModelError

    with pytest.raises(ModelError, match="unknown knowledge 'koopman'; choose one of none, dmd"):
        make_predictor("knode", knowledge="koopman", **SMALL).fit(field, start=0, stop=24)
    for bad in ("half", -0.1):
        with pytest.raises(ModelError, match="must be keep, drop or a decay rate >= 0 per snapshot interval"):
            make_predictor("knode", knowledge="dmd", knowledge_complement=bad, **SMALL).fit(field, start=0, stop=24)


def test_shipped_alternative_carries_dmd_of_its_window():
    """``builtin:cylinder-dmd``: a KNODE with DMD knowledge whose operator is the DMD of its recorded
    training part (the training window less its validation part; the same rank, exp(A_c) = A to float32 rounding); the command is recorded."""
    from scipy.linalg import expm

    from passt_mav.fields.datasets import load_dataset
    from passt_mav.models import shipped_model

    try:
        path = shipped_model("cylinder-dmd")
    except Exception as exc:  # noqa: BLE001 - a checkout without the asset skips, naming it
        pytest.skip(str(exc))
    m = load_predictor("builtin:cylinder-dmd")
    meta = json.loads(path.with_suffix(".json").read_text())
    f = load_dataset("cylinder")
    assert m.knowledge == "dmd" and meta["command"].startswith("passt-mav model train")
    assert meta["data_hash"] == f.data_hash() and "--knowledge dmd" in meta["command"]
    # fitted on the training part only: the window less its validation part
    a, b = meta["train_window"][0], (meta["val_window"] or meta["train_window"])[0]
    dmd = make_predictor("dmd").fit(f, start=a, stop=b)
    kn = m.net_.knowledge
    assert kn.Ac.shape == (dmd.rank_, dmd.rank_) == (meta["knowledge_info"]["rank"],) * 2
    U = kn.U.double().numpy()[np.broadcast_to(dmd.water_, (2, 30, 30)).ravel()]
    # the same subspace and the same operator in it (modes are unique up to sign)
    A_back = U.T @ dmd.modes_ @ dmd.A_ @ dmd.modes_.T @ U
    np.testing.assert_allclose(expm(kn.Ac.double().numpy()), A_back, atol=1e-4)
