"""Learning at sea in the loop (loop/online.py): the update between legs is kept only when the next
leg's samples find it more probable; the mission key and the evaluate options are checked."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from passt_mav.errors import MissionConfigError, ModelError
from passt_mav.loop.engine import run_offline
from passt_mav.loop.online import ModelUpdate, OnlineUpdate, model_update_problem
from passt_mav.loop.passt import LoopOptions
from passt_mav.mission.config import validate_mission
from passt_mav.models.base import make_predictor

torch = pytest.importorskip("torch")

from test_models import SMALL, _one_thread, wave_field  # noqa: E402, F401 - _one_thread: the same autouse fixture here

S = 1  # snapshots per leg (3: one pair of states is memorised, not generalised: the update loses on a moving wave)
#: deterministic: a step cap with a budget far above it (the decision does not depend on the machine's speed)
UPDATE = ModelUpdate(online="on", budget_s=1e9, lr=3e-3, max_steps=30)


def _wave(stop_at=None):
    """The travelling wave (test_models.wave_field), frozen from snapshot ``stop_at`` on (None: moving)."""
    f = wave_field(T=40)
    if stop_at is not None:
        f.data[stop_at:] = f.data[stop_at]
    return f


@pytest.fixture(scope="module")
def persistence_knode():
    """A KNODE that is persistence (zero last layer, no epoch), scaled on the moving wave's snapshots 0..24."""
    return make_predictor("knode", epochs=0, zero_init=True, lr=3e-3, **SMALL).fit(_wave(), start=0, stop=24)


def _two_legs(field, predictor, update=UPDATE):
    """Two legs of S snapshots from snapshot 0, samples at each leg's end, lawnmower paths; the legs' records."""
    options = LoopOptions(planner="lawnmower", path_length=60, steps_per_leg=S, hyper="every_leg", model_update=update)
    return run_offline(field, predictor, start_cell=(0, 0), n_steps=2 * S, options=options).legs


def test_an_update_that_the_next_leg_contradicts_is_discarded(persistence_knode):
    """The first leg sees the wave move (the states: the truth at 0, the estimate at S); from S on the
    field stands still, so the model as it is (persistence) explains the second leg's samples and the
    learned motion explains them worse: the update is discarded, the loop keeps its model."""
    legs = _two_legs(_wave(stop_at=S), persistence_knode)
    first, second = legs[0]["model_update"], legs[1]["model_update"]
    assert first["steps"] == 0 and first["reason"] == "fewer than 2 evenly spaced states so far"
    assert second["steps"] == 30 and second["states"] == 2 and second["interval"] == S
    assert second["loss"][1] < second["loss"][0]  # it did learn the first leg's motion
    assert second["scores"]["updated"] < second["scores"]["original"]
    assert second["kept"] is False and second["reason"] == "the update did not raise the score"


def test_an_update_that_explains_the_next_leg_better_is_kept(persistence_knode):
    """The wave keeps moving: the motion learned from the first leg explains the second leg's samples
    better than persistence: kept (the loop's model and the leg's forecast are the update's); the
    model alone is still the one the loop was built with."""
    field = _wave()
    options = LoopOptions(planner="lawnmower", path_length=60, steps_per_leg=S, model_update=UPDATE)
    loop = options.loop(persistence_knode, field.grid, land=field.land_mask)
    legs = _two_legs(field, persistence_knode)
    second = legs[1]["model_update"]
    assert second["kept"] is True and second["reason"] is None and second["steps"] == 30
    assert second["scores"]["updated"] > second["scores"]["original"]
    # the same decision when the loop is driven by hand, and what it changes
    plan, state = _drive(loop, field)
    assert loop.online.kept_ == 1 and loop.predictor is not persistence_knode
    assert loop.initial_predictor is persistence_knode
    # the leg's background is the update's forecast (it moves the wave), not persistence's
    assert np.abs(plan.forecast[1] - plan.forecast[0]).max() > 1e-3
    assert loop.gp_summary()["model_update"]["kept"] is True
    np.testing.assert_allclose(loop.model_alone(field.data[0], 1)[1], field.data[0], atol=1e-5)  # still persistence
    # the estimate is better than the model alone's (persistence) at the end of the second leg
    truth = field.data[2 * S]
    assert np.sqrt(np.mean((state - truth) ** 2)) < np.sqrt(np.mean((field.data[0] - truth) ** 2))


def _drive(loop, field, legs=2):
    """``legs`` legs of the loop by hand on ``field`` (samples at each leg's end), from its snapshot 0."""
    from passt_mav.loop.passt import FieldSampler

    sampler, state = FieldSampler(field, steps_per_leg=S), field.data[0]
    for k in range(legs):
        plan = loop.plan_leg(state, (0, 0), field.times[k * S], field.dt)
        state = loop.update(plan, sampler.sample_path(plan.path, plan.t_start))
    return plan, state


def test_a_replay_takes_the_recorded_steps_whatever_the_budget(persistence_knode):
    """A budget no step fits in, but the replay's recorded 7 steps for leg 1: 7 steps are taken."""
    field = _wave()
    mu = ModelUpdate(online="on", budget_s=1e-9, lr=3e-3)
    loop = LoopOptions(planner="lawnmower", path_length=60, steps_per_leg=S, model_update=mu).loop(
        persistence_knode, field.grid
    )
    loop.online.replay_steps[1] = 7
    _drive(loop, field)
    assert [r["steps"] for r in loop.online.history_] == [0, 7] and not loop.online.replay_steps


def test_off_by_default_and_untrainable_models_are_left_alone():
    """No ``model_update`` (or ``online="off"``): no updater, no record; DMD has no weights: every
    leg's record says so and the loop keeps it."""
    field = _wave()
    assert LoopOptions().model_update is None
    assert LoopOptions(model_update=ModelUpdate()).loop(None, field.grid).online is None
    dmd = make_predictor("dmd").fit(field, start=0, stop=24)
    legs = _two_legs(field, dmd)
    assert "model_update" not in _two_legs(field, dmd, update=None)[1]
    assert legs[1]["model_update"]["reason"].endswith("has no trainable weights")
    assert not legs[1]["model_update"]["kept"]


def test_states_evenly_spaced_only():
    """Training states are the most recent ones a whole, equal number of snapshots apart, at most ``window``."""
    up = OnlineUpdate(ModelUpdate(online="on", window=4))
    z = np.zeros((2, 3, 3), np.float32)
    for t in (0.0, 2.0, 5.0, 8.0, 11.0, 14.0):
        up.remember(z + t, t)
    states, interval = up.training_states(dt=1.0)
    assert interval == 3 and states.shape == (4, 2, 3, 3) and states[0, 0, 0, 0] == 5.0  # the window: 5, 8, 11, 14
    up = OnlineUpdate(ModelUpdate(online="on"))
    for t in (0.0, 2.0, 5.0):
        up.remember(z, t)
    assert up.training_states(dt=1.0)[0].shape[0] == 2  # 2 and 5: the run before the uneven gap is left out
    nan = z.copy()
    nan[0, 0, 0] = np.nan
    up.remember(nan, 6.0)
    assert np.isfinite(up.states_[-1][1]).all()  # land / missing cells filled with 0 for training


@pytest.mark.parametrize(
    "change, message",
    [
        ({"online": "sometimes"}, "model_update.online must be one of off, on, got 'sometimes'"),
        ({"budget_s": 0}, "model_update.budget_s must be a positive number, got 0"),
        ({"lr": float("nan")}, "model_update.lr must be a positive number, got nan"),
        ({"horizon": 1.5}, "model_update.horizon must be a positive integer, got 1.5"),
        ({"max_steps": 0}, "model_update.max_steps must be a positive integer or null, got 0"),
        ({"window": 1}, "model_update.window must be an integer >= 2, got 1"),
    ],
)
def test_bad_options_are_named(change, message):
    mu = ModelUpdate(**{"online": "on", **change})
    assert model_update_problem(mu) == message
    with pytest.raises(ModelError, match="^" + message.replace("(", r"\(").replace(")", r"\)") + "$"):
        LoopOptions(model_update=mu).loop(None, wave_field(T=4).grid)


MISSION = yaml.safe_load((Path(__file__).resolve().parents[1] / "missions" / "cylinder.yaml").read_text())


def test_the_mission_key():
    """``model_update`` in a mission: YAML's bare on/off read as the words; defaults off; bad values one line."""
    assert validate_mission(MISSION).model_update.online == "off"
    yaml_on = yaml.safe_load("model_update: {online: on, max_steps: 20, budget_s: 60}")
    cfg = validate_mission({**MISSION, **yaml_on})
    assert (cfg.model_update.online, cfg.model_update.max_steps, cfg.model_update.budget_s) == ("on", 20, 60.0)
    from passt_mav.loop.legstep import build_loop

    loop = build_loop(cfg, make_predictor("persistence"), cfg.grid())
    assert loop.online is not None and loop.online.options.max_steps == 20
    for bad, key in (({"budget_s": -1}, "model_update.budget_s"), ({"online": "yes"}, "model_update.online")):
        with pytest.raises(MissionConfigError, match=key) as exc:
            validate_mission({**MISSION, "model_update": bad})
        assert "\n" not in str(exc.value)
    with pytest.raises(MissionConfigError, match="model_update"):
        validate_mission({**MISSION, "model_update": {"budget": 5}})


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--model-update", "on", "--model-update-budget", "0"], "--model-update-budget must be a positive number"),
        (["--model-update", "on", "--model-update-steps", "0"], "--model-update-steps must be a positive integer"),
        (["--model-update", "on", "--engine", "lockstep"], "use --engine serial"),
    ],
)
def test_evaluate_options_bad_values_exit_2(argv, message, tmp_path, capsys):
    """One line naming the option, exit code 2, nothing written (the field is not even loaded)."""
    from passt_mav.cli import main

    out = tmp_path / "out"
    rc = main(["evaluate", "--data", "builtin:cylinder", "--model", "persistence", "--out", str(out), *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and message in err and len(err.splitlines()) == 1 and not out.exists()
