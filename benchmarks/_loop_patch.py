"""What the same-loop benchmarks share: an alias reward and patched loop methods, restored after, and the
item-4 campaign they fly, with its command-line arguments.

A benchmark that plans with something no loop may hold (the truth, an experimental prior) flies it
as one more method of an ordinary campaign: ``information_loop@ALIAS``, where ALIAS is
registered as the ``variance_reduction`` reward map, and the loop's methods are swapped for the
benchmark's own only inside the block.
"""

from __future__ import annotations

import contextlib


@contextlib.contextmanager
def loop_patched(alias: str, *, using_prior: bool, replacements):
    """Within the block: reward ``alias`` maps to ``variance_reduction`` (in ``REWARDS_USING_PRIOR`` when
    ``using_prior``), and each ``(owner, name, function)`` of ``replacements`` is set on its owner.
    Everything is put back on exit, exceptions included."""
    from passt_mav.planning import rewards as RW

    saved_rewards, saved_using_prior = dict(RW.REWARDS), RW.REWARDS_USING_PRIOR
    saved_attrs = [(owner, name, getattr(owner, name)) for owner, name, _ in replacements]
    RW.REWARDS[alias] = RW.REWARDS["variance_reduction"]
    if using_prior:
        RW.REWARDS_USING_PRIOR = frozenset(RW.REWARDS_USING_PRIOR | {alias})
    for owner, name, fn in replacements:
        setattr(owner, name, fn)
    try:
        yield
    finally:
        for owner, name, fn in saved_attrs:
            setattr(owner, name, fn)
        RW.REWARDS.clear()
        RW.REWARDS.update(saved_rewards)
        RW.REWARDS_USING_PRIOR = saved_using_prior


def add_item4_arguments(ap) -> None:
    """The item-4 protocol's command-line arguments, the same in every same-loop benchmark (argparse parser
    ``ap``): data, model, path length, trials, seed, sensor noise, window."""
    ap.add_argument("--data", default="builtin:ocean")
    ap.add_argument("--model", default="builtin:ocean")
    ap.add_argument("--path-length", type=int, default=100)
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0, help="trial i uses seed + i, as in passt-mav evaluate")
    ap.add_argument("--noise", type=float, default=0.02, help="sensor noise (field units)")
    ap.add_argument("--window", type=int, default=50)


def item4_final_rmse(
    field,
    predictor,
    *,
    methods,
    path_length: int,
    trials: int,
    seed: int,
    noise: float,
    window: int,
    memory: str = "off",
) -> dict:
    """Each of ``methods``' final-window RMSE (field units, mean over trials) in issue 27 item 4's protocol:
    lockstep engine, Cholesky GP, ``bias`` on, the model's default background, samples at each leg's end."""
    from passt_mav.loop.campaign import run_campaign
    from passt_mav.reconstruction.background import DEFAULT_BACKGROUND

    res = run_campaign(
        field,
        predictor,
        path_lengths=(path_length,),
        trials=trials,
        seed=seed,
        engine="lockstep",
        gp_solver="cholesky",
        gp_bias=True,
        background=DEFAULT_BACKGROUND,
        noise=noise,
        window=window,
        memory=memory,
        methods=list(methods),
        progress=False,
    )
    per = res["per_L"].get(path_length, res["per_L"].get(str(path_length)))
    return per["final_rmse"]
