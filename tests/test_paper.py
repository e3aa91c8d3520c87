"""`passt-mav paper`: the claims table's verdicts (known answers), the page's structure, --quick end to end
with the shipped models, its rendering in headless Chromium, --dry-run and bad input."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
from test_passt import WRONG_VEL, ShiftPredictor, make_field

from passt_mav.cli import main
from passt_mav.commands.paper import claims, write_page
from passt_mav.loop.campaign import run_campaign


def _fake_campaign(ratios: dict) -> dict:
    """per_L final RMSE with PASST = 1 and the other methods at 1 / ratio."""
    return {
        "per_L": {
            L: {"final_rmse": {"passt": 1.0, "model": 1.0 / r["model"], "lawnmower_gp": 1.0 / r["lawnmower_gp"]}}
            for L, r in ratios.items()
        }
    }


def test_claims_verdicts_known_answers():
    good = {"50": {"model": 0.4, "lawnmower_gp": 0.9}, "100": {"model": 0.5, "lawnmower_gp": 0.5}}
    res = {
        "campaigns": {
            "cylinder": _fake_campaign(good),
            "oscillating": _fake_campaign(good),
            "ocean": _fake_campaign({"50": {"model": 0.9, "lawnmower_gp": 1.2}}),
        },
        "model_eval": {
            "model_name": "knode",
            "lookahead": {
                "test": {
                    "knode": {"1": {"mse": 1.0}, "20": {"mse": 3.0}, "50": {"mse": 9.0}},
                    "persistence": {"1": {"mse": 2.0}, "20": {"mse": 4.0}, "50": {"mse": 1.0}},
                }
            },
            "pod": {"knode": {"predicted": [0.5, 0.7, 0.8, 0.89], "true": [0.5, 0.7, 0.85, 0.92]}},
        },
    }
    c = {x["claim"].split(":")[0].split(" ")[0] + str(i): x for i, x in enumerate(claims(res))}
    v = [x["held"] for x in c.values()]
    # <= 0.5 x model on the cylinder (0.4, 0.5): held; < model everywhere: held; ocean PASST/lawnmower = 1.2: not held;
    # KNODE/persistence 0.5, 0.75 for h <= 20 (h = 50 ignored): held; POD 0.89 vs 0.92: held
    # the same-loop rows (issue 27) need random_loop / greedy_loop / rmse_mean: not measured here
    assert v == [True, True, False, None, None, True, True]
    assert "ocean: PASST/lawnmower_gp <= 1.20" in list(c.values())[2]["ours"]
    res["campaigns"].pop("ocean")
    assert claims(res)[1]["held"] is None  # a scenario not run: not measured, never "held"


def test_same_loop_claims_known_answers():
    """PASST/random <= 0.8 and PASST < greedy everywhere: held; one cell at 0.85: not held. Mean
    RMSE over time within 2 % of the model alone at every step: held; 3 % above at one step: not."""
    from passt_mav.commands.paper import _same_loop_claims

    def camp(rand, greedy, over):
        return {
            "per_L": {
                "50": {
                    "final_rmse": {"passt": 1.0, "random_loop": rand, "greedy_loop": greedy},
                    "rmse_mean": {"passt": [0.0, 1.0, over], "model": [0.0, 1.0, 1.0]},
                }
            }
        }

    ok = {sc: camp(1.3, 1.05, 1.01) for sc in ("cylinder", "oscillating", "ocean")}
    assert [r["held"] for r in _same_loop_claims(ok)] == [True, True]
    bad = dict(ok, ocean=camp(1.0 / 0.85, 1.05, 1.03))
    rows = _same_loop_claims(bad)
    assert [r["held"] for r in rows] == [False, False]
    assert (
        "ocean: PASST/random <= 0.85" in rows[0]["ours"]
        and "ocean: max over steps of PASST/model 1.03" in rows[1]["ours"]
    )


@pytest.fixture(scope="module")
def small_results():
    f = make_field(T=40)
    camp = run_campaign(
        f,
        ShiftPredictor(WRONG_VEL),
        path_lengths=(12, 24),
        trials=2,
        steps=20,
        snapshot_step=15,
        hyper="state",
        progress=False,
    )
    camp["config"].update(data="synthetic", model="shift")
    res = {
        "protocol": {
            "scenarios": ["cylinder"],
            "path_lengths": [12, 24],
            "trials": 2,
            "steps": 20,
            "hyper": "state",
            "quick": True,
        },
        "campaigns": {"cylinder": camp},
        "timings": {"campaign cylinder (s)": 1.0},
        "trial_legs": camp["trial_legs"],
        "wall_s": 1.0,
    }
    res["claims"] = claims(res)
    return res


def test_page_structure(small_results, tmp_path):
    path = write_page(small_results, tmp_path)
    doc = path.read_text()
    assert doc.startswith("<!DOCTYPE html>") and doc.rstrip().endswith("</html>")
    assert doc.count('src="data:image/png;base64,') == 2  # RMSE over time + snapshots (no model evaluation here)
    assert "model evaluation not run" in doc
    assert doc.count("<tr><td>") == len(small_results["claims"]) == 5  # 3 of the paper + 2 same-loop rows
    assert "not measured" in doc  # oscillating / ocean were not run
    assert "L = 12" in doc and "L = 24" in doc
    assert {p.name for p in tmp_path.glob("*.png")} == {"rmse_cylinder.png", "snapshots_cylinder.png"}
    assert "http://" not in doc and "https://" not in doc  # self-contained


def _shot(html_path, tmp_path):
    shot = tmp_path / "shot.png"
    cmd = [
        shutil.which("chromium"),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        "--hide-scrollbars",
        f"--user-data-dir={tmp_path / 'profile'}",
        f"--screenshot={shot}",
        "--window-size=1200,4200",
        html_path.resolve().as_uri(),
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    import matplotlib.image as mpimg

    img = (mpimg.imread(shot)[..., :3] * 255).astype(np.uint8).reshape(-1, 3)
    return len(np.unique(img, axis=0))


@pytest.fixture(scope="module")
def quick_page(tmp_path_factory):
    pytest.importorskip("passt_mav.models.knode", reason="predictors not available")
    out = tmp_path_factory.mktemp("paper_quick")
    assert main(["paper", "--quick", "--out", str(out)]) == 0
    return out


# --quick takes ~30 s on an idle 2-core machine and 67 s measured beside a training job: slow
@pytest.mark.slow(
    reason="passt-mav paper --quick: the three scenarios with the shipped models and seven methods: minutes"
)
def test_quick_runs_the_protocol(quick_page, capsys):
    """--quick: all three scenarios with the shipped models, the seven methods, the claims table, one page."""
    import json

    res = json.loads((quick_page / "results.json").read_text())
    assert set(res["campaigns"]) == {"cylinder", "oscillating", "ocean"}
    for c in res["campaigns"].values():
        per = c["per_L"]["50"]
        assert set(per["final_rmse"]) == {
            "passt",
            "model",
            "lawnmower_gp",
            "greedy_gp",
            "random_gp",
            "random_loop",
            "greedy_loop",
        }
        assert all(np.isfinite(v) and v > 0 for v in per["final_rmse"].values())
        assert len(per["rmse_mean"]["passt"]) == 31
    assert set(res["model_eval"]["lookahead"]) == {"train", "test", "oscillating"}
    assert len(res["claims"]) == 7 and all(c["held"] in (True, False) for c in res["claims"])
    doc = (quick_page / "paper.html").read_text()
    assert doc.count('src="data:image/png;base64,') == 8  # lookahead, POD, 3 x (RMSE, snapshots)
    assert "Quick version" in doc


@pytest.mark.slow(reason="needs the --quick campaign of the test above (minutes), then renders its page")
@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium not installed")
def test_quick_page_renders_in_headless_chromium(quick_page, tmp_path):
    # a blank or broken page has a handful of colours; colour maps and text give thousands
    assert _shot(quick_page / "paper.html", tmp_path) > 500


@pytest.mark.long(reason="renders the results page in headless Chromium: ~20 s")
@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium not installed")
def test_small_page_renders_in_headless_chromium(small_results, tmp_path):
    path = write_page(small_results, tmp_path / "page")
    assert _shot(path, tmp_path) > 500


@pytest.mark.slow(reason="calibrates on the shipped cylinder KNODE: ~18 s beside a training job")
def test_dry_run_counts_and_estimates(tmp_path, capsys):
    pytest.importorskip("passt_mav.models.knode", reason="predictors not available")
    assert (
        main(
            [
                "paper",
                "--dry-run",
                "--scenarios",
                "cylinder",
                "--trials",
                "3",
                "--steps",
                "40",
                "--path-lengths",
                "25,50",
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "= 96 trial-legs" in out  # 1 scenario x 2 L x 3 trials x 4 loop methods x 4 legs
    assert "estimated campaign wall time" in out and not (tmp_path / "x").exists()


def test_protocol_counts():
    import argparse

    from passt_mav.commands.paper import _protocol, _trial_legs

    a = argparse.Namespace(
        quick=False,
        trials=None,
        steps=None,
        path_lengths=None,
        scenarios="cylinder,oscillating,ocean",
        batch=None,
        workers=1,
        hyper="state",
        gp_solver="cholesky",
        seed=0,
        background=200,
        planner="policy_gradient",
        reward="speed",
        prior_blend="off",
    )
    p = _protocol(a)
    assert (p["trials"], p["steps"], p["path_lengths"], p["background"]) == (30, 300, [25, 50, 75, 100, 150, 200], 200)
    # the paper's protocol: 4 loop methods, and the random walk and greedy in PASST's own loop: 97 200 loop legs
    assert _trial_legs(p) == 3 * 6 * 30 * 6 * 30
    assert p["gp_solver"] == "cholesky"
    a.quick = True
    assert _trial_legs(_protocol(a)) == 3 * 1 * 2 * 6 * 3


def test_bad_input_exit_2(tmp_path, capsys):
    assert main(["paper", "--scenarios", "mars", "--out", str(tmp_path)]) == 2
    assert "scenario" in capsys.readouterr().err
    assert main(["paper", "--path-lengths", "a", "--out", str(tmp_path)]) == 2
    assert main(["paper", "--trials", "0", "--out", str(tmp_path)]) == 2
    assert main(["paper", "--background", "1", "--out", str(tmp_path)]) == 2
    assert "--background" in capsys.readouterr().err
