"""Train a predictor on a field window and write its checkpoint (used by ``passt-mav model train``).

passt-mav model train --data builtin:cylinder --start 200 --stop 300 --epochs 200 --out DIR/knode_cylinder
"""

from __future__ import annotations

import time
from dataclasses import dataclass

#: training recipes for the KNODE (constructor options); explicit options override them
RECIPES: dict[str, dict] = {
    # how the model is used in the PASST loop: started from a GP reconstruction, rolled out over a leg
    "loop": {
        "loss": "rollout",
        "horizon": 10,
        "curriculum": 0.3,
        "noise": "gp",
        "val_frac": 0.2,
        "patience": 60,
        "train_batch": 32,
        "zero_init": True,
    },
    # the paper: one-step MSE over all pairs, white input noise
    "paper": {"loss": "one_step", "noise": "white", "val_frac": 0.0},
}


def train(
    data: str,
    *,
    out: str,
    model: str = "knode",
    start: int | None = None,
    stop: int | None = None,
    epochs: int = 100,
    seed: int = 0,
    lr: float = 1e-3,
    n_batches: int = 1,
    substeps: int = 6,
    method: str = "euler",
    kernel_variance: float = 0.1,
    noise_var: float = 1e-3,
    device: str = "cpu",
    threads: int | None = None,
    progress: bool = True,
    command: str | None = None,
    log=None,
    recipe: str = "loop",
    overrides: dict | None = None,
    skill: bool = True,
) -> dict:
    """Fit predictor ``model`` on ``data`` (``builtin:NAME`` or a .nc path), save it to ``out``; returns the summary.

    ``recipe``: a key of :data:`RECIPES`, with ``overrides`` on top. ``log(epoch, loss)``
    is called after every KNODE epoch (e.g. to write a log file). With ``skill`` and a
    validation window, the skill report (MSE vs lookahead on the validation window
    against persistence and DMD, from true and from GP-reconstructed states) is printed
    and stored in the checkpoint's JSON under ``"skill"``.
    """
    from passt_mav.fields.datasets import resolve_field
    from passt_mav.models.base import make_predictor

    _seed_and_threads(seed, threads)
    field = resolve_field(data, series=True)
    job = _TrainJob(data=data, out=out, start=start, stop=stop, seed=seed, recipe=recipe, command=command)
    if model != "knode":
        return _train_other(model, field, job)
    opts = _recipe_options(recipe, overrides)
    p = make_predictor(
        "knode",
        epochs=epochs,
        seed=seed,
        lr=lr,
        n_batches=n_batches,
        substeps=substeps,
        method=method,
        kernel_variance=kernel_variance,
        noise_var=noise_var,
        device=device,
        progress=progress,
        **opts,
    )
    return _train_knode(p, field, job, opts, log=log, skill=skill)


@dataclass(frozen=True)
class _TrainJob:
    """A training run's provenance: the data spec, the checkpoint path ``out``, the window
    ``start..stop-1``, the seed, the KNODE recipe and the command line recorded in the checkpoint."""

    data: str
    out: str
    start: int | None
    stop: int | None
    seed: int
    recipe: str
    command: str | None


def _seed_and_threads(seed: int, threads: int | None) -> None:
    """Seed numpy's and torch's global generators with ``seed``; use ``threads`` torch CPU threads (None: leave)."""
    import numpy as np
    import torch

    if threads is not None:
        torch.set_num_threads(int(threads))
    np.random.seed(seed)
    torch.manual_seed(seed)


def _recipe_options(recipe: str, overrides: dict | None) -> dict:
    """The KNODE constructor options of ``recipe`` (a key of :data:`RECIPES`) with ``overrides`` on top."""
    if recipe not in RECIPES:
        from passt_mav.errors import ModelError

        raise ModelError(f"unknown recipe {recipe!r}; choose one of {', '.join(RECIPES)}")
    return {**RECIPES[recipe], **(overrides or {})}


def _train_other(model: str, field, job: _TrainJob) -> dict:
    """Fit a non-KNODE predictor ``model`` on the job's window and save it; returns the summary."""
    from passt_mav.models.base import make_predictor

    p = make_predictor(model).fit(field, start=job.start, stop=job.stop)
    path = p.save(job.out, command=job.command, extra={"data": job.data})
    return {"out": str(path), "model": model, "data": job.data, "data_hash": field.data_hash()}


def _lineage(p) -> list[dict]:
    """A fine-tuning run's lineage: the commands that made its start model, oldest first, so the
    checkpoint can be rebuilt from scratch by running them and then this run's command."""
    meta0 = getattr(p, "init_metadata_", None) or {}
    return list(meta0.get("lineage", [])) + [
        {
            "command": meta0.get("command"),
            "wall_s": meta0.get("wall_s"),
            "epochs": meta0.get("epochs"),
            "best_epoch": meta0.get("best_epoch"),
        }
    ]


def _train_knode(p, field, job: _TrainJob, opts: dict, *, log, skill: bool) -> dict:
    """Fit the KNODE ``p`` (built with the recipe options ``opts``) on the job's window and save it;
    with ``skill`` and a validation window the skill report is added to the checkpoint. Returns the summary."""
    import torch

    t0 = time.perf_counter()
    p.fit(field, start=job.start, stop=job.stop, callback=log)
    wall = time.perf_counter() - t0
    extra = {"data": job.data, "threads": torch.get_num_threads(), "recipe": job.recipe, "wall_s": round(wall, 2)}
    if opts.get("init"):
        extra["lineage"] = _lineage(p)
    path = p.save(job.out, command=job.command, extra=extra)
    summary = {
        "out": str(path),
        "model": "knode",
        "recipe": job.recipe,
        "data": job.data,
        "data_hash": p.data_hash_,
        "epochs": p.epochs_trained_,
        "best_epoch": p.best_epoch_,
        "seed": job.seed,
        "final_loss": p.final_loss_,
        "final_epoch_loss": p.loss_curve_[-1] if p.loss_curve_ else None,
        "first_epoch_loss": p.loss_curve_[0] if p.loss_curve_ else None,
        "n_params": p.n_params(),
        "knowledge": p.knowledge,
        **({"knowledge_info": p.knowledge_info_} if p.knowledge_info_ else {}),
        "wall_s": round(wall, 2),
        "s_per_epoch": round(wall / max(1, p.epochs_trained_), 3),
    }
    if skill and p.val_window_ is not None:
        from passt_mav.models.evaluate import skill_report

        rep = skill_report(
            p,
            field,
            train=tuple(p.train_window_),
            val=tuple(p.val_window_),
            horizon=int(opts.get("horizon", 10)),
            seed=job.seed,
        )
        p.save(job.out, command=job.command, extra={**extra, "skill": rep})
        summary["skill"] = rep
    return summary
