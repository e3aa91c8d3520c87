"""One set of defaults (issue 43): the mission schema, the Python API (``PasstLoop``, ``LoopOptions``),
the offline campaign and ``passt-mav evaluate`` default to :data:`passt_mav.loop.presets.DEFAULT`;
``passt-mav paper`` runs :data:`~passt_mav.loop.presets.PAPER` by name."""

from __future__ import annotations

import argparse
import inspect

import numpy as np
import pytest

from passt_mav.loop.presets import DEFAULT, PAPER, PRESETS, Preset


def _mission():
    from passt_mav.mission.config import MissionConfig

    return MissionConfig.model_validate(
        {
            "name": "t",
            "region": {"south": 40.0, "west": -70.0, "north": 40.2, "east": -69.8, "rows": 6, "cols": 6},
            "field": {"source": "builtin:ocean"},
        }
    )


def test_the_mission_schema_defaults_are_the_default_preset():
    assert _mission().loop_preset() == DEFAULT


def test_the_api_defaults_are_the_default_preset():
    from passt_mav.loop.passt import LoopOptions, PasstLoop

    sig = inspect.signature(PasstLoop.__init__).parameters
    assert {k: sig[k].default for k in DEFAULT.loop_kwargs()} == DEFAULT.loop_kwargs()
    opts = LoopOptions()
    assert {k: getattr(opts, k) for k in DEFAULT.loop_kwargs()} == DEFAULT.loop_kwargs()


def test_a_default_loop_builds_the_default_gp():
    """The GP's own defaults (bias off) are not the loop's: a loop built with no options gets the preset's bias
    and nugget; an explicit ``gp_kw`` wins."""
    import geo
    from passt_mav.loop.passt import PasstLoop

    grid = geo.RegionGrid(40.0, -70.0, 40.2, -69.8, 6, 6)
    gp = PasstLoop(None, grid).gp
    assert (gp.bias, gp.nugget) == (DEFAULT.bias, DEFAULT.nugget) == (True, "state")
    gp = PasstLoop(None, grid, gp_kw=PAPER.gp_kwargs()).gp
    assert (gp.bias, gp.nugget) == (False, "state")


def test_the_campaign_and_evaluate_defaults_are_the_default_preset():
    from passt_mav.commands.evaluate import add_arguments, resolve_preset
    from passt_mav.loop.campaign import CampaignOptions

    o = CampaignOptions()
    assert {k: getattr(o, k) for k in DEFAULT.campaign_kwargs()} == DEFAULT.campaign_kwargs()
    p = argparse.ArgumentParser()
    add_arguments(p)
    for name, preset in PRESETS.items():
        argv = ["--data", "d", "--model", "m", "--out", "o"] + ([] if name == "default" else ["--preset", name])
        args = p.parse_args(argv)
        resolve_preset(args)
        got = {k: getattr(args, k) for k in preset.campaign_kwargs() if k != "guard"}
        assert got == {k: v for k, v in preset.campaign_kwargs().items() if k != "guard"}, name
    args = p.parse_args(["--data", "d", "--model", "m", "--out", "o", "--preset", "paper", "--gp-bias"])
    resolve_preset(args)  # an option given explicitly replaces the preset's
    assert (args.gp_bias, args.prior_blend) == (True, "off")
    args = p.parse_args(["--data", "d", "--model", "m", "--out", "o", "--no-gp-bias"])
    resolve_preset(args)
    assert (args.gp_bias, args.prior_blend) == (False, DEFAULT.prior_blend)


def test_paper_runs_the_paper_preset_by_name():
    from passt_mav.commands.paper import _protocol, add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    proto = _protocol(p.parse_args(["--out", "o", "--quick"]))
    assert proto["preset"] == "paper" and proto["loop"] == PAPER.as_dict()
    assert (PAPER.planner, PAPER.reward, PAPER.prior_blend, PAPER.prior_share, PAPER.bias) == (
        "policy_gradient",
        "speed",
        "off",
        0.0,
        False,
    )
    proto = _protocol(p.parse_args(["--out", "o", "--quick", "--preset", "default", "--prior-blend", "off"]))
    assert proto["loop"] == {**DEFAULT.as_dict(), "prior_blend": "off"}


def test_the_presets_differ_only_where_the_paper_does():
    diff = {k for k, v in DEFAULT.as_dict().items() if PAPER.as_dict()[k] != v}
    assert diff == {"prior_blend", "prior_share", "bias"}


def test_one_background_default():
    from passt_mav.reconstruction.background import DEFAULT_BACKGROUND

    assert DEFAULT.background == DEFAULT_BACKGROUND == 200


@pytest.mark.parametrize("spelling", ["none", "constant"])
def test_one_name_for_the_gp_alone(spelling):
    """The mission's GP prior on the samples alone is ``none``, as the API and ``--baseline-prior`` call it;
    ``constant`` (the mission files' spelling before) still loads, as ``none``."""
    from passt_mav.mission.config import MissionConfig

    base = _mission().model_dump()
    cfg = MissionConfig.model_validate({**base, "gp": {**base["gp"], "prior": spelling}})
    assert cfg.gp.prior == cfg.gp.loop_prior == "none"


def test_a_mission_builds_its_loop_with_its_own_gp_settings():
    """``build_loop`` hands the mission's bias and nugget to the GP explicitly (the API's default would
    otherwise fill what the mission turned off)."""
    import geo
    from passt_mav.loop.legstep import build_loop

    base = _mission().model_dump()
    cfg = type(_mission()).model_validate({**base, "gp": {**base["gp"], "bias": False, "nugget": "noise"}})
    grid = geo.RegionGrid(40.0, -70.0, 40.2, -69.8, 6, 6)
    loop = build_loop(cfg, None, grid)
    assert (loop.gp.bias, loop.gp.nugget) == (False, "noise")
    assert cfg.loop_preset() == Preset(**{**DEFAULT.as_dict(), "bias": False, "nugget": "noise"})
    assert np.isclose(loop.share, cfg.gp.prior_share)
