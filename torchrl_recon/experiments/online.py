"""The online experiment (its stages, recipe check and ``EXPERIMENT``): random data, a first
fit, then per iteration an MPC play stage and a warm-started refit, run as TorchRL's
``Trainer`` (:class:`~torchrl_recon.trainers.OnlineTrainer`) whose collector and fits are the
run directory's stages, so a stopped run resumes where it stopped."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_recon.envs import closing_env
from torchrl_recon.experiments.config import OnlineConfig
from torchrl_recon.experiments.context import RecipeLoader, RunContext
from torchrl_recon.experiments.experiment_type import ExperimentType
from torchrl_recon.experiments.fit_speed import fit_speed, fit_speed_errors
from torchrl_recon.experiments.fit_stages import checkpoint_stage, fit_stage
from torchrl_recon.experiments.random_data import (
    check_random_data,
    random_data_stage,
    warmup_mode,
)
from torchrl_recon.experiments.recipe_checks import RecipeErrors, data_errors, planner_errors
from torchrl_recon.experiments.recipe_env import build_env
from torchrl_recon.experiments.recipe_models import build_models, build_reward_model, dims
from torchrl_recon.experiments.recipe_planning import (
    build_planner,
    mpc_policy,
    planning_model,
    replan_threshold,
)
from torchrl_recon.fitting.online import FitSchedule, episode_returns, fit_models, shared_keys
from torchrl_recon.planners import Objective, PlanningModel
from torchrl_recon.planners.beta import window_uncertainty
from torchrl_recon.policies import ExplorationPolicy, exploration_objective
from torchrl_recon.policies.mpc import REPLANNED
from torchrl_recon.reports.stats import mean_std
from torchrl_recon.trainers import IterationCollector, ModelFitStepper, OnlineTrainer, play

STAGES = ("random_data", "models", "play_{n}", "refit_{n}")
"""Stage name templates, in run order (``{n}`` the iteration, from 1)."""


def play_stage(
    ctx: RunContext, n: int, model: PlanningModel, data: TensorDictBase, warmup: str
) -> dict:
    """Stage ``play_<n>``: ``steps_per_iteration`` steps of MPC (re-planning threshold from all
    ``data`` so far) or, in the rounds that explore, exploration, with the current models and
    the resolved ``warmup``, stored as ``buffers/play_<n>`` (the env's keys); its record: the
    re-plans, the seconds spent planning and in the env, and which ``policy`` played (the
    steps' returns, model error and u are :class:`~torchrl_recon.trainers.LogIteration`'s)."""
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
        return {
            "replans": int(new[REPLANNED].sum()),
            "plan_s": plan_s,
            "env_s": time.perf_counter() - start - plan_s,
            "policy": "explore" if exploring else "mpc",
        }

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


def recipe_schedule(cfg: DictConfig, *, refit_uncertainty: bool = True) -> FitSchedule:
    """The online recipe's fits as a :class:`~torchrl_recon.fitting.online.FitSchedule`: its
    ``training`` block with ``refit_steps`` and ``refit_old_steps``, their speed as
    :func:`~.fit_speed.fit_speed` reads it."""
    t = cfg.training
    sizes = {k: t[k] for k in ("slice_len", "num_slices", "val_fraction")}
    sizes |= {k: cfg[k] for k in ("refit_steps", "refit_old_steps")}
    return FitSchedule(
        **{**t.world_model, **fit_speed(cfg, "world_model", population=True)},
        mode=str(t.world_model_mode),
        sampling=str(t.window_sampling),
        short_episodes=str(t.get("short_episodes", "pad")),
        refit_uncertainty=refit_uncertainty,
        uncertainty={**t.uncertainty, **fit_speed(cfg, "uncertainty")},
        renormalize=bool(cfg.get("renormalize", False)),
        **sizes,
    )


def refit_stage(
    ctx: RunContext, n: int, model: PlanningModel, data: TensorDictBase, new_steps: int
) -> dict:
    """Stage ``refit_<n>``: a :func:`~.fit_stages.checkpoint_stage` refitting the networks warm on
    ``data`` (the ``new_steps`` last are this round's) as :class:`OnlineConfig` says; the
    estimator too when a later plan reads it (:func:`reads_uncertainty`) or always."""
    cfg, name = ctx.cfg, f"refit_{n}"
    refit_u = cfg.refit_uncertainty == "always" or reads_uncertainty(cfg, n + 1)
    schedule = recipe_schedule(cfg, refit_uncertainty=refit_u)
    modules = fitted_modules(model)

    def fit() -> dict:
        start, seed = time.perf_counter(), ctx.stage_seed(name)
        losses = fit_models(
            model.world_model,
            model.uncertainty,
            data,
            schedule,
            seed=seed,
            warm=True,
            new_steps=new_steps,
            progress=cfg.progress,
            logger=ctx.logger,
            log_prefix=f"{name}/",
            reward_model=model.reward_model,
        )
        return {"val_loss": losses, "fit_s": time.perf_counter() - start}

    return checkpoint_stage(ctx, name, modules, fit)


def fitted_modules(model: PlanningModel) -> dict[str, torch.nn.Module]:
    """The networks the online fits train and the stages checkpoint, by name: the world model,
    the estimator and, where the cost or termination is learned, the reward model."""
    modules = {"world_model": model.world_model, "uncertainty": model.uncertainty}
    if model.reward_model is not None:
        modules["reward_model"] = model.reward_model
    return modules


class StagedCollector(IterationCollector):
    """The online experiment's iterations as run-directory stages: iteration 0 is the random
    data (stage ``random_data``, collected before the models are built), iteration ``n`` the
    stage ``play_<n>`` (:func:`play_stage`; a done stage's steps are loaded back)."""

    def __init__(
        self,
        ctx: RunContext,
        model: PlanningModel,
        random_data: TensorDictBase,
        warmup: str,
        data: Callable[[], TensorDictBase],
    ) -> None:
        cfg = ctx.cfg
        super().__init__(
            iterations=cfg.iterations,
            steps_per_iteration=cfg.steps_per_iteration,
            random_steps=cfg.random_steps,
            explore_iterations=cfg.exploration.iterations,
        )
        self.ctx, self.model, self.random_data = ctx, model, random_data
        self.warmup, self.data = warmup, data

    def collect_iteration(self, iteration: int) -> TensorDictBase:
        if iteration == 0:
            self.batch_info = dict(iteration=0, policy="random", plan_s=0.0, env_s=0.0, replans=0)
            return self.random_data
        played = play_stage(self.ctx, iteration, self.model, self.data(), self.warmup)
        keys = ("policy", "plan_s", "env_s", "replans")
        self.batch_info = {"iteration": iteration} | {k: played[k] for k in keys}
        return self.ctx.stages.load_data(f"play_{iteration}")


class StagedFit(ModelFitStepper):
    """The online experiment's fits as run-directory stages: the first is stage ``models``
    (:func:`~.fit_stages.fit_stage`), the ``n``-th refit stage ``refit_<n>`` (:func:`refit_stage`);
    a done stage's checkpoint is loaded back. :attr:`stage_records` keeps each stage's record."""

    def __init__(self, ctx: RunContext, model: PlanningModel, replay_buffer: ReplayBuffer) -> None:
        super().__init__(
            model.world_model, model.uncertainty, replay_buffer, reward_model=model.reward_model
        )
        self.ctx, self.model = ctx, model
        self.stage_records: dict[int, dict] = {}

    def fit(self, data: TensorDictBase, *, index: int, new_steps: int) -> dict[str, float]:
        if index == 0:
            modules = fitted_modules(self.model)
            record = fit_stage(self.ctx, "models", data, modules)
            self.stage_records[0] = record
            return {k: record[f"{k}_val_loss"] for k in modules}
        record = refit_stage(self.ctx, index, self.model, data, new_steps)
        self.stage_records[index] = record
        return record["val_loss"]


def run(ctx: RunContext) -> dict:
    """Run (or resume) the online experiment through an
    :class:`~torchrl_recon.trainers.OnlineTrainer` whose collector and fits are the run
    directory's stages; return its results."""
    cfg = ctx.cfg
    data = random_data_stage(ctx, "random_data", frames=cfg.random_steps)
    check_random_data(cfg, data)  # two episodes to split, before any fit
    warmup = warmup_mode(cfg, data)  # from the random data only, once
    world, estimator = build_models(cfg, *dims(data), ctx.device)
    model = planning_model(cfg, world, estimator, build_reward_model(cfg, *dims(data), ctx.device))
    collector = StagedCollector(ctx, model, data, warmup, lambda: buffer[:])
    buffer = ReplayBuffer(storage=LazyTensorStorage(collector.total_frames))
    fits = StagedFit(ctx, model, buffer)
    trainer = OnlineTrainer(
        collector=collector,
        world_model=world,
        estimator=estimator,
        schedule=recipe_schedule(cfg),
        replay_buffer=buffer,
        stepper=fits,
        progress=cfg.progress,
        logger=ctx.logger,
        reward_model=model.reward_model,
    )
    trainer.train()
    iterations = []
    for record in trainer.records[1:]:
        n = record.iteration
        iterations.append(
            {
                "iteration": n,
                "env_steps": record.env_steps,
                "returns": record.episode_returns,
                "model_error": record.model_error,
                "mean_u": record.mean_uncertainty,
                "replans": record.replans,
                "plan_s": record.plan_s,
                "env_s": record.env_s,
                "policy": record.policy,
                **fits.stage_records[n],
            }
        )
    random_returns = episode_returns(data)
    late = [r for it in iterations[len(iterations) // 2 :] for r in it["returns"]]
    return ctx.results_header() | {
        **({"warmup": warmup} if warmup != "random" else {}),
        "random": {"returns": random_returns, "mean_return": mean_std(random_returns)[0]},
        "first_fit": fits.stage_records[0],
        "iterations": iterations,
        "mean_return_last_half": mean_std(late)[0],
        "env_steps": trainer.collected_frames,
    }


def check(cfg: DictConfig, errors: RecipeErrors, recipes: RecipeLoader | None) -> None:
    """The online recipe's own checks: episodes long enough for a training slice and, where
    they never end early (no ``env.termination``), random data that holds two of them (else the
    data are checked once collected, :func:`~.random_data.check_random_data`), the fits' speed
    (:func:`~.fit_speed.fit_speed_errors`, with members), the planner built with the recipe's
    objective (and the exploration objective when the first rounds explore)."""
    ends_early = cfg.env.termination is not None
    data_errors(errors, "env.episode_steps", None if ends_early else "random_steps")
    errors.need(
        "steps_per_iteration",
        cfg.steps_per_iteration >= cfg.env.episode_steps,
        f"at least env.episode_steps = {cfg.env.episode_steps} (each iteration plays new "
        "episodes from a reset: a shorter one ends none, and has no return to report)",
    )
    errors.need(
        "num_envs",
        cfg.num_envs == 1,
        "1 in the online kind (its iterations play one env; the random data would be the only "
        "batched part)",
    )
    replan = cfg.replan
    errors.need(
        "replan.threshold_on",
        str(replan.threshold_on) == "step" or str(replan.mode) == "uncertainty",
        f"step unless replan.mode is uncertainty (replan.mode = {replan.mode} never reads the "
        "threshold)",
    )
    planner_errors(
        errors,
        "planner",
        lambda: Objective(alpha=cfg.alpha, beta=cfg.beta),
        f"with alpha = {cfg.alpha}, beta = {cfg.beta}",
    )
    fit_speed_errors(errors, members=True)
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
