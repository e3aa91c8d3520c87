"""How much better a path could do in the same-loop protocol, with the truth to choose it.

    .venv/bin/python benchmarks/oracle_paths.py --data builtin:ocean --model builtin:ocean \
        --path-length 100 --trials 6 --candidates 16

Item 4 of issue 27 asks the information planner to end 20 % below a random walk in the same
model + GP loop (``passt-mav evaluate ... --methods information_loop@variance_reduction,random_loop``).
This benchmark runs that campaign (lockstep engine, Cholesky GP, ``bias`` on, the model's
200-snapshot background, sensor noise 0.02, samples read at each leg's end) with a third method
that cheats: an oracle planner that knows the truth.

``--oracle pick`` (default): each leg, the candidates are the information planner's own path and
``--candidates`` random walks from the same cell (the random walk baseline's planner, seeds
per leg). Each is flown through a copy of the loop (same GP, same fits, same prior blend and
memory) with the truth's samples (sensor noise as the loop's), and the one whose outcome is
closest to the truth is taken: ``--score recon`` by the reconstruction's RMSE at the leg's end,
``--score next`` by the mean RMSE of the next leg's forecast from it (the snapshots the protocol
scores). A greedy, one-leg oracle over a finite set: not a bound on every conceivable path, but
on how far choosing among such paths can go with perfect knowledge of where they help.

``--oracle error``: each leg, the beam search maximises the forecast's true squared error summed
over the path's distinct cells (sample where the estimate is wrong).

Printed (JSON): the final-window RMSE (field units, mean of the last ``--window`` snapshots, mean
over trials) of the information planner, the random walk and the oracle, their ratios, and how
often the oracle took the information planner's own path.

Measured (2026-11-27, ocean, L = 100, ``--score next``; docs/research/2026-11-27-information-reward.md, "What the truth would buy"):
with 64 candidates, trials 0-5, information 0.0307, random walk 0.0354, oracle 0.0273 m/s
(oracle / random 0.77; it kept the information path on 7 % of legs); with 16 candidates,
trials 0-1, 0.87. ``--oracle error``, trials 0-1: 0.0802 against the random walk's 0.0330.

The oracle needs the truth, which no loop may see, so it lives here and not in the package: it
replaces :meth:`PasstLoop.plan_leg` for the oracle's reward only, inside :func:`_oracle_installed`,
which restores it.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _loop_patch import add_item4_arguments, item4_final_rmse, loop_patched  # noqa: E402

ORACLE_REWARD = "oracle"


@contextlib.contextmanager
def _oracle_installed(field, *, mode: str, candidates: int, score: str, noise: float, picks: list):
    """Within the block, loops whose reward is :data:`ORACLE_REWARD` plan with the truth of ``field``."""
    from passt_mav.loop import passt as P
    from passt_mav.loop.measurement import rmse
    from passt_mav.planning import rewards as RW
    from passt_mav.planning.baselines import RandomPlanner

    times = np.asarray(field.times, float)
    orig_plan, orig_reward_map = P.PasstLoop.plan_leg, P.PasstLoop._reward_map

    def truth_index(t: float) -> int:
        k = int(np.argmin(np.abs(times - t)))
        if abs(times[k] - t) > 1e-6 * max(1.0, abs(t)):
            raise RuntimeError(f"the oracle needs a snapshot at t = {t}, nearest {times[k]}")
        return k

    def reward_map(self, fc, start, taken=None, avoid=None):
        if self.reward_name != ORACLE_REWARD or mode != "error":
            return orig_reward_map(self, fc, start, taken, avoid)
        err = fc[-1] - field.data[truth_index(self._oracle_t_end)]
        mask = ~self.land & RW.traversable(fc[1])
        self.info_ = None  # the beam search then sums the map over the path's distinct cells
        return np.where(mask, np.nansum(err**2, axis=0), 0.0), mask

    def flown(self, base, path, k: int) -> float:
        """The oracle's score of ``path``: the outcome of a copy of the loop updated with the truth's samples
        (the campaign's sensor model; the same noise draws for every candidate of a leg)."""
        sampler = P.FieldSampler(field, noise_std=noise, seed=[self.seed, self.leg_index], steps_per_leg=base.steps)
        trial = copy.deepcopy(self, memo={id(self.predictor): self.predictor})
        state = trial.update(replace(base, path=np.asarray(path)), sampler.sample_path(path, base.t_start))
        n = min(base.steps, len(times) - 1 - k)
        if score == "recon" or n < 1:
            return rmse(state, field.data[k])
        fc = trial.forecast(state, n)
        return float(np.mean([rmse(fc[j], field.data[k + j]) for j in range(1, n + 1)]))

    def plan_leg(self, state, start, t_start, dt=1.0, **kw):
        if self.reward_name != ORACLE_REWARD:
            return orig_plan(self, state, start, t_start, dt, **kw)
        S = self.steps_per_leg if kw.get("steps") is None else int(kw["steps"])
        self._oracle_t_end = float(t_start) + S * float(dt)
        if mode == "error":
            return orig_plan(self, state, start, t_start, dt, **kw)
        self.reward_name = "variance_reduction"  # the information planner's own path first
        try:
            base = orig_plan(self, state, start, t_start, dt, **kw)
        finally:
            self.reward_name = ORACLE_REWARD
        k = truth_index(self._oracle_t_end)
        mask = ~self.land & RW.traversable(base.forecast[1])
        paths = [base.path] + [
            RandomPlanner().plan(base.reward, start, self.path_length, seed=10_000 * self.leg_index + j, mask=mask)
            for j in range(candidates)
        ]
        scores = [flown(self, base, p, k) for p in paths]
        best = int(np.argmin(scores))
        picks.append(best)
        return replace(base, path=np.asarray(paths[best]))

    with loop_patched(
        ORACLE_REWARD,
        using_prior=mode == "pick",
        replacements=[(P.PasstLoop, "plan_leg", plan_leg), (P.PasstLoop, "_reward_map", reward_map)],
    ):
        yield


def main(argv=None) -> int:
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.loop.campaign import load_predictor

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_item4_arguments(ap)
    ap.add_argument("--oracle", choices=("pick", "error"), default="pick")
    ap.add_argument("--candidates", type=int, default=16, help="random walks beside the information path")
    ap.add_argument("--score", choices=("recon", "next"), default="recon")
    ap.add_argument("--memory", default="off", help="the planner memory of all three methods (off | fitted)")
    a = ap.parse_args(argv)
    field = resolve_field(a.data)
    predictor = load_predictor(a.model, field)
    picks: list[int] = []
    methods = [f"information_loop@{ORACLE_REWARD}", "information_loop@variance_reduction", "random_loop"]
    with _oracle_installed(field, mode=a.oracle, candidates=a.candidates, score=a.score, noise=a.noise, picks=picks):
        fin = item4_final_rmse(
            field,
            predictor,
            methods=methods,
            path_length=a.path_length,
            trials=a.trials,
            seed=a.seed,
            noise=a.noise,
            window=a.window,
            memory=a.memory,
        )
    info, rand, orc = fin[methods[1]], fin[methods[2]], fin[methods[0]]
    out = {
        "data": a.data, "model": a.model, "L": a.path_length, "trials": a.trials, "seed": a.seed,
        "oracle": a.oracle, "candidates": a.candidates if a.oracle == "pick" else None,
        "score": a.score if a.oracle == "pick" else None, "memory": a.memory,
        "final_rmse": {"information": info, "random_walk": rand, "oracle": orc},
        "information_over_random": info / rand, "oracle_over_random": orc / rand,
        "oracle_took_information_path": float(np.mean(np.asarray(picks) == 0)) if picks else None,
    }  # fmt: skip
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
