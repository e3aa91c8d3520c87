"""The loop's configurations by name: the one source of the defaults of the planner, the reward, the GP's
prior, blend, share, bias and nugget, and the planner's memory.

:data:`DEFAULT` is what a mission flies when its file says nothing else; the mission schema
(:mod:`passt_mav.mission.config`), the Python API (:class:`passt_mav.loop.passt.PasstLoop`,
:class:`~passt_mav.loop.passt.LoopOptions`), the offline campaign
(:class:`passt_mav.loop.campaign.CampaignOptions`) and ``passt-mav evaluate`` all take their defaults
from it. :data:`PAPER` is the paper's configuration (the policy-gradient planner on the predicted speed,
the model's forecast as the GP's prior without a blend, share, offset or rescaling); ``passt-mav paper``
runs it by name and ``passt-mav evaluate --preset paper`` reproduces it.

One name per setting, as the mission file spells it (``gp.prior_share`` is ``prior_share`` here and
``--prior-share`` on the command line); the loop's keywords that differ are mapped by
:meth:`Preset.loop_kwargs` and :meth:`Preset.campaign_kwargs`. This module imports nothing: the command
line reads it to build its help.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

__all__ = ["Preset", "DEFAULT", "PAPER", "PRESETS", "GP_PRIORS"]

#: the GP's prior mean: the model's forecast (the GP fits the residual) or none (the GP on the samples
#: alone, a constant mean: the paper's literal variant). Mission files written before may say
#: ``constant`` for ``none``.
GP_PRIORS = ("forecast", "none")


@dataclass(frozen=True)
class Preset:
    """One configuration of the loop (the mission file's names).

    planner: a name in ``passt_mav.planning.PLANNERS``; reward: a name in ``passt_mav.planning.REWARDS``;
    memory: the information reward's per-cell memory, "off" or "fitted"; prior: :data:`GP_PRIORS`;
    background: snapshots of the model's roll-out whose anomaly covariance the residual GP adds (0 =
    none); prior_blend: "off", "bma" or "select"; forgetting: the blend's forgetting factor per leg in
    [0, 1]; prior_share: the blend's fixed share in [0, 1]; bias: the residual GP may shift and rescale
    the forecast; nugget: what the GP's white variance above the sensor's is, "state" (the field's
    grid-scale error) or "noise"; guard: "on" or "off" (the loop's forecast checked against the model
    alone before each leg's samples enter the estimate).
    """

    planner: str = "policy_gradient"
    reward: str = "speed"
    memory: str = "off"
    prior: str = "forecast"
    background: int = 200
    prior_blend: str = "select"
    forgetting: float = 0.8
    prior_share: float = 0.05
    bias: bool = True
    nugget: str = "state"
    guard: str = "on"

    def as_dict(self) -> dict:
        """The settings by their mission names (JSON-able)."""
        return asdict(self)

    def gp_kwargs(self) -> dict:
        """The :class:`passt_mav.reconstruction.GPReconstructor` keywords this preset sets."""
        return {"bias": self.bias, "nugget": self.nugget}

    def loop_kwargs(self) -> dict:
        """The :class:`passt_mav.loop.passt.PasstLoop` keywords this preset sets (besides ``gp_kw``)."""
        return dict(
            planner=self.planner,
            reward=self.reward,
            memory=self.memory,
            prior=self.prior,
            background=self.background,
            prior_blend=self.prior_blend,
            forgetting=self.forgetting,
            share=self.prior_share,
            guard=self.guard,
        )

    def kwargs(self, **changes) -> dict:
        """Every :class:`passt_mav.loop.passt.PasstLoop` keyword this preset sets, ``gp_kw`` included, with
        ``changes`` (any ``PasstLoop`` keywords) applied; a ``gp_kw`` given is merged over the preset's."""
        gp_kw = {**self.gp_kwargs(), **(changes.pop("gp_kw", None) or {})}
        return {**self.loop_kwargs(), "gp_kw": gp_kw, **changes}

    def campaign_kwargs(self) -> dict:
        """The :func:`passt_mav.loop.campaign.run_campaign` keywords this preset sets (its GP prior is
        per method: the forecast for PASST, none for the GP-only baselines)."""
        return dict(
            planner=self.planner,
            reward=self.reward,
            memory=self.memory,
            background=self.background,
            prior_blend=self.prior_blend,
            prior_forgetting=self.forgetting,
            prior_share=self.prior_share,
            gp_bias=self.bias,
            gp_nugget=self.nugget,
            guard=self.guard,
        )


#: what a mission flies unless its file says otherwise (the schema's, the API's and evaluate's defaults)
DEFAULT = Preset()
#: the paper's configuration: ``passt-mav paper`` (and ``evaluate --preset paper``)
PAPER = Preset(prior_blend="off", prior_share=0.0, bias=False)
#: the presets by name (``--preset NAME``)
PRESETS = {"default": DEFAULT, "paper": PAPER}
