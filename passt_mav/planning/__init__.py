"""Planning: reward maps and grid-path planners behind one registry.

One entry point::

    path = plan("policy_gradient", reward, start=(r, c), budget=L, seed=0, mask=traversable)

``reward`` is ``(rows, cols)`` (NaN / ``mask`` False = land, not traversable);
``path`` is ``(L+1, 2)`` int ``(row, col)``, 8-connected, exactly ``L`` moves,
revisiting a cell only when every neighbour has been visited. Planners:
:data:`PLANNERS` (``information``: a beam search over whole paths, scored by the
reconstruction's variance reduction when the loop passes ``info=``); rewards: :data:`REWARDS` (:func:`compute_reward`).
Unknown names raise :class:`passt_mav.errors.PlannerError` listing the valid ones.
"""

from __future__ import annotations

import numpy as np

from passt_mav.errors import PlannerError
from passt_mav.planning.baselines import GreedyPlanner, LawnmowerPlanner, RandomPlanner
from passt_mav.planning.grid import check_path, path_reward, top_l_bound
from passt_mav.planning.information import InformationModel, InformationPlanner
from passt_mav.planning.policy_gradient import PolicyGradientPlanner
from passt_mav.planning.rewards import REWARDS, compute_reward, traversable

__all__ = [
    "PLANNERS",
    "REWARDS",
    "plan",
    "make_planner",
    "compute_reward",
    "traversable",
    "check_path",
    "path_reward",
    "top_l_bound",
    "PolicyGradientPlanner",
    "LawnmowerPlanner",
    "GreedyPlanner",
    "RandomPlanner",
    "InformationPlanner",
    "InformationModel",
]

#: name -> planner class (keyword-only options; ``.plan(reward, start, budget, seed, mask)``)
PLANNERS: dict[str, type] = {
    "policy_gradient": PolicyGradientPlanner,
    "lawnmower": LawnmowerPlanner,
    "greedy": GreedyPlanner,
    "random": RandomPlanner,
    "information": InformationPlanner,
}
_ALIASES = {"pg": "policy_gradient", "beam": "information"}


def make_planner(name: str, **kw):
    """Instantiate the planner ``name`` (see :data:`PLANNERS`) with options ``kw``."""
    key = _ALIASES.get(name, name)
    if key not in PLANNERS:
        raise PlannerError(f"unknown planner {name!r}; choose one of {', '.join(PLANNERS)}")
    try:
        return PLANNERS[key](**kw)
    except TypeError as exc:
        raise PlannerError(f"bad option for planner {key!r}: {exc}") from None


def plan(name: str, reward, start, budget: int, *, seed: int = 0, mask=None, **kw) -> np.ndarray:
    """Plan one leg: ``(budget+1, 2)`` int path from ``start`` on ``reward`` (see module doc)."""
    return make_planner(name, **kw).plan(reward, start, budget, seed=seed, mask=mask)
