"""A recipe's fits as resumable stages: one network fitted with the recipe's settings
(:func:`fit_module`), networks fitted and checkpointed together (:func:`fit_stage`), and the
first models of a run (:func:`models_stage`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch
from tensordict import TensorDictBase

from torchrl_recon.data import FIT_KEYS, REWARD_FIT_KEYS
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.fit_buffers import split_buffers
from torchrl_recon.experiments.fit_speed import fit_speed
from torchrl_recon.experiments.recipe_models import build_models, dims
from torchrl_recon.fitting import (
    fit_reward,
    fit_uncertainty,
    load_checkpoint,
    save_checkpoint,
    world_model_fit,
)
from torchrl_recon.modules import LSTMWorldModel, RewardModel, UncertaintyEstimator


def fit_kwargs(ctx: RunContext, fit: str, prefix: str, *, population: bool = False) -> dict:
    """The keywords of the recipe's fit ``fit`` (``world_model``, ``uncertainty``, or ``reward``:
    the world model's block): its ``training.<fit>`` block, its speed
    (:func:`~.fit_speed.fit_speed`; ``population``: a fit of world-model members), the run's
    progress bar and logger, and ``prefix`` for its logs."""
    block = ctx.cfg.training["world_model" if fit == "reward" else fit]
    settings = {**block, **fit_speed(ctx.cfg, fit, population=population)}  # its speed replaced
    return settings | dict(progress=ctx.cfg.progress, logger=ctx.logger, log_prefix=prefix)


def fit_module(
    ctx: RunContext,
    module: LSTMWorldModel | UncertaintyEstimator | RewardModel,
    data: TensorDictBase,
    *,
    seed: int,
    prefix: str,
    fit_normalization: bool = True,
) -> float:
    """Fit the world model, an estimator or a learned reward on ``data``; returns the best
    validation loss. A learned reward takes the world model's fit settings (uncompiled)."""
    world, reward = isinstance(module, LSTMWorldModel), isinstance(module, RewardModel)
    rb, val_rb = split_buffers(ctx.cfg, data, seed, keys=REWARD_FIT_KEYS if reward else FIT_KEYS)
    fit = "reward" if reward else "world_model" if world else "uncertainty"
    members = world and module.num_members is not None  # online's first fit, as its refits
    kwargs = fit_kwargs(ctx, fit, prefix, population=members)
    kwargs |= {"mode": ctx.cfg.training.world_model_mode} if world else {}
    common = dict(val_buffer=val_rb, fit_normalization=fit_normalization, checkpoint_modules={})
    fit_fn = world_model_fit(module) if world else fit_reward if reward else fit_uncertainty
    return fit_fn(module, rb, seed=seed, **common, **kwargs).best_val_loss


def checkpoint_stage(
    ctx: RunContext, name: str, modules: Mapping[str, torch.nn.Module], fit: Callable[[], dict]
) -> dict:
    """Stage ``name``: ``fit()`` (returns the record), then ``modules`` checkpointed together as
    ``checkpoints/<name>.pt`` under their keys (loaded back when the stage is done)."""
    path = ctx.stages.path("checkpoints", f"{name}.pt")

    def run() -> dict:
        record = fit()
        save_checkpoint(path, dict(modules))
        return record

    record = ctx.stages.run(name, run)
    load_checkpoint(path, dict(modules))
    return record


def fit_stage(
    ctx: RunContext,
    name: str,
    data: TensorDictBase,
    modules: Mapping[str, torch.nn.Module],
    *,
    fit_normalization: bool = True,
) -> dict:
    """A :func:`checkpoint_stage` fitting ``modules`` on ``data`` (one seed, in order); the record
    holds ``val_loss`` for one module, else ``<key>_val_loss``."""
    one = len(modules) == 1

    def fit() -> dict:
        seed, record = torch.initial_seed() % (2**31), {}
        for key, module in modules.items():
            prefix = f"{name}/" if one else f"{name}/{key}/"
            loss = fit_module(
                ctx, module, data, seed=seed, prefix=prefix, fit_normalization=fit_normalization
            )
            record["val_loss" if one else f"{key}_val_loss"] = loss
        return record

    return checkpoint_stage(ctx, name, modules, fit)


def models_stage(
    ctx: RunContext, data: TensorDictBase, name: str
) -> tuple[LSTMWorldModel, UncertaintyEstimator, dict]:
    """Stage ``name``: the world model and the estimator fitted on ``data``, and its record."""
    world, estimator = build_models(ctx.cfg, *dims(data), ctx.device)
    record = fit_stage(ctx, name, data, {"world_model": world, "uncertainty": estimator})
    return world, estimator, record
