"""The online experiment (its stages, recipe check and ``EXPERIMENT``): random data, a first
fit, then per iteration an MPC play stage and a warm-started refit
(:mod:`torchrl_recon.training.online` does the work)."""

from __future__ import annotations

import sys
import time

from omegaconf import DictConfig
from tensordict import TensorDictBase

from torchrl_recon.envs import closing_env
from torchrl_recon.experiments.common import (
    build_env,
    build_planner,
    check_random_data,
    checkpoint_stage,
    models_stage,
    mpc_policy,
    planning_model,
    random_data_stage,
    replan_threshold,
    warmup_mode,
)
from torchrl_recon.experiments.config import OnlineConfig
from torchrl_recon.experiments.context import RecipeLoader, RunContext
from torchrl_recon.experiments.experiment_type import ExperimentType
from torchrl_recon.experiments.recipe_checks import RecipeErrors, data_errors, planner_errors
from torchrl_recon.planners import Objective, PlanningModel, window_uncertainty
from torchrl_recon.policies import ExplorationPolicy, exploration_objective
from torchrl_recon.reports.stats import mean_std
from torchrl_recon.training.online import (
    FitSchedule,
    append_steps,
    episode_returns,
    fit_models,
    new_steps_metrics,
    play,
    shared_keys,
)

STAGES = ("random_data", "models", "play_{n}", "refit_{n}")
"""Stage name templates, in run order (``{n}`` the iteration, from 1)."""


def play_stage(
    ctx: RunContext, n: int, model: PlanningModel, data: TensorDictBase, warmup: str
) -> dict:
    """Stage ``play_<n>``: ``steps_per_iteration`` steps of MPC (re-planning threshold from all
    ``data`` so far) or, in the rounds that explore, exploration, with the current models and
    the resolved ``warmup``, stored as ``buffers/play_<n>``; its record: :func:`new_steps_metrics`,
    the seconds spent planning and in the env, and which ``policy`` played."""
    cfg, name = ctx.cfg, f"play_{n}"

    def run() -> dict:
        start, threshold, e = time.perf_counter(), None, cfg.exploration
        exploring = n <= e.iterations
        if exploring:
            objective = exploration_objective(ratio=e.ratio, cap=e.cap, beta=e.beta)
            mpc = ExplorationPolicy(build_planner(cfg.planner, model, objective), warmup=warmup)
        else:
            if str(cfg.replan.mode) == "uncertainty":
                length = cfg.training.slice_len
                u = window_uncertainty(data, model.uncertainty, sequence_length=length)
                threshold = replan_threshold(cfg, u)
            planner = build_planner(cfg.planner, model, Objective(alpha=cfg.alpha, beta=cfg.beta))
            mpc = mpc_policy(cfg, planner, threshold, warmup=warmup)
        seed = ctx.stage_seed(name)
        with closing_env(build_env(cfg, seed=seed, policy=mpc)) as env:
            new, plan_s = play(
                env, mpc, frames=cfg.steps_per_iteration, seed=seed, progress=cfg.progress
            )
        ctx.stages.save_data(name, new.select(*shared_keys(data, new)))  # the env's keys
        seen = new_steps_metrics(model.world_model, model.uncertainty, new, cfg.training.slice_len)
        record = seen | {"plan_s": plan_s, "env_s": time.perf_counter() - start - plan_s}
        record["policy"] = "explore" if exploring else "mpc"
        if ctx.logger is not None:
            for key in ("model_error", "mean_u", "replans"):
                ctx.logger.log_scalar(f"online/{key}", record[key], step=n)
        return record

    return ctx.stages.run(name, run)


def reads_uncertainty(cfg: DictConfig, n: int) -> bool:
    """Whether a plan from iteration ``n`` on reads the estimator's u: β ≠ 0, re-planning on u,
    or a round that explores.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"beta": 0.0, "replan": {"mode": "every_step"},
        ...     "exploration": {"iterations": 2}})
        >>> reads_uncertainty(cfg, 2), reads_uncertainty(cfg, 3)
        (True, False)
    """
    return cfg.beta != 0 or str(cfg.replan.mode) == "uncertainty" or n <= cfg.exploration.iterations


def refit_stage(
    ctx: RunContext, n: int, model: PlanningModel, data: TensorDictBase, new_steps: int
) -> dict:
    """Stage ``refit_<n>``: a :func:`~.common.checkpoint_stage` refitting the networks warm on
    ``data`` (the ``new_steps`` last are this round's) as :class:`OnlineConfig` says; the
    estimator too when a later plan reads it (:func:`reads_uncertainty`) or always."""
    cfg, t, name = ctx.cfg, ctx.cfg.training, f"refit_{n}"
    sizes = {k: t[k] for k in ("slice_len", "num_slices", "val_fraction")}
    sizes |= {k: cfg[k] for k in ("refit_steps", "refit_old_steps")}
    refit_u = cfg.refit_uncertainty == "always" or reads_uncertainty(cfg, n + 1)
    schedule = FitSchedule(
        **t.world_model,
        mode=str(t.world_model_mode),
        refit_uncertainty=refit_u,
        uncertainty=dict(t.uncertainty),
        **sizes,
    )
    modules = {"world_model": model.world_model, "uncertainty": model.uncertainty}

    def fit() -> dict:
        start, seed = time.perf_counter(), ctx.stage_seed(name)
        losses = fit_models(
            *modules.values(),
            data,
            schedule,
            seed=seed,
            warm=True,
            new_steps=new_steps,
            progress=cfg.progress,
            logger=ctx.logger,
            log_prefix=f"{name}/",
        )
        return {"val_loss": losses, "fit_s": time.perf_counter() - start}

    return checkpoint_stage(ctx, name, modules, fit)


def run(ctx: RunContext) -> dict:
    """Run (or resume) the online experiment; return its results."""
    cfg = ctx.cfg
    data = random_data_stage(ctx, "random_data", frames=cfg.random_steps)
    check_random_data(cfg, data)  # two episodes to split, before any fit
    warmup = warmup_mode(cfg, data)  # from the random data only, once
    world, estimator, first = models_stage(ctx, data, "models")
    model = planning_model(cfg, world, estimator)
    iterations = []
    for n in range(1, cfg.iterations + 1):
        played = play_stage(ctx, n, model, data, warmup)
        new = ctx.stages.load_data(f"play_{n}")
        data = append_steps(data, new)
        refit = refit_stage(ctx, n, model, data, len(new))
        iterations.append({"iteration": n, "env_steps": len(data), **played, **refit})
    random_returns = episode_returns(data[: cfg.random_steps])
    late = [r for it in iterations[len(iterations) // 2 :] for r in it["returns"]]
    return ctx.results_header() | {
        **({"warmup": warmup} if warmup != "random" else {}),
        "random": {"returns": random_returns, "mean_return": mean_std(random_returns)[0]},
        "first_fit": first,
        "iterations": iterations,
        "mean_return_last_half": mean_std(late)[0],
        "env_steps": len(data),
    }


def check(cfg: DictConfig, errors: RecipeErrors, recipes: RecipeLoader | None) -> None:
    """The online recipe's own checks: episodes long enough for a training slice and, where
    they never end early (no ``env.termination``), random data that holds two of them (else the
    data are checked once collected, :func:`~.common.check_random_data`), the planner built with
    the recipe's objective (and the exploration objective when the first rounds explore)."""
    ends_early = cfg.env.termination is not None
    data_errors(errors, "env.episode_steps", None if ends_early else "random_steps")
    planner_errors(
        errors,
        "planner",
        lambda: Objective(alpha=cfg.alpha, beta=cfg.beta),
        f"with alpha = {cfg.alpha}, beta = {cfg.beta}",
    )
    e = cfg.exploration
    errors.need(
        "exploration.iterations",
        e.iterations <= cfg.iterations,
        f"at most iterations = {cfg.iterations} (the rounds that explore)",
    )
    if e.iterations > 0:
        planner_errors(
            errors,
            "planner",
            lambda: exploration_objective(ratio=e.ratio, cap=e.cap, beta=e.beta),
            f"with the exploration objective: alpha 0, exploration.beta = {e.beta}",
        )


EXPERIMENT = ExperimentType.of_module(
    sys.modules[__name__],
    name="online",
    help="learn a task online: act with MPC, add the data, refit warm, repeat (PETS's loop)",
    schema=OnlineConfig,
)
