"""The uncertainty-aware control experiment (the paper's §3.1 and Fig. 3): its resumable
:data:`STAGES` (a setting's, one part record per batch of ``num_envs`` episodes), its recipe
check and its ``EXPERIMENT``."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from torchrl_recon.collectors import first_episodes
from torchrl_recon.envs import closing_env
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.evaluation import episode_metrics, planned_trajectory
from torchrl_recon.experiments.batching import batches
from torchrl_recon.experiments.config import ControlConfig, ControlSetting
from torchrl_recon.experiments.context import RecipeLoader, RunContext
from torchrl_recon.experiments.experiment_type import ExperimentType
from torchrl_recon.experiments.fit_stages import models_stage
from torchrl_recon.experiments.random_data import random_data_stage, warmup_mode
from torchrl_recon.experiments.recipe_checks import (
    RecipeErrors,
    data_errors,
    duplicate_errors,
    planner_errors,
)
from torchrl_recon.experiments.recipe_env import build_env, env_entry
from torchrl_recon.experiments.recipe_planning import (
    build_planner,
    mpc_policy,
    planning_model,
    replan_threshold,
    setting_objective,
)
from torchrl_recon.experiments.report_units import state_scale
from torchrl_recon.planners import PlanningModel
from torchrl_recon.planners.beta import cost_to_u_ratio, window_uncertainty
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.reports.stats import episode_mean_std, mean_std

STAGES = ("random_data", "models", "setting_{setting}", "random_policy")
"""Stage name templates, in run order (``{setting}`` a setting's name)."""


@dataclass
class Controller:
    """What every setting's episodes share (``scale``: the state scale of the reported MSE;
    ``warmup``: the resolved warm-up, ``random``, ``zeros`` or ``plan``)."""

    model: PlanningModel
    threshold: float
    beta_unit: float
    scale: torch.Tensor
    warmup: str = "random"


def play_episodes(
    ctx: RunContext, name: str, batch: range, policy: MPCPolicy | None = None
) -> list[TensorDictBase]:
    """Episodes ``batch`` side by side, ``e`` seeded with ``stage_seed("<name>_<e>")`` (the torch
    RNG with the first), cut at each one's first done; ``policy`` None takes uniform random
    actions. Ended envs wait (TorchRL partial steps) until all are done or ``env.episode_steps``."""
    seeds = [ctx.stage_seed(f"{name}_{e}") for e in batch]
    steps, batched = ctx.cfg.env.episode_steps, len(seeds) > 1
    with closing_env(build_env(ctx.cfg, seed=seeds if batched else seeds[0], policy=policy)) as env:
        torch.manual_seed(seeds[0])
        td = env.rollout(steps, policy, break_when_all_done=batched).cpu()  # else: any done
    return first_episodes(td) if batched else [td]


def episode_batch(
    ctx: RunContext, setting: DictConfig, planner, controller: Controller, batch: range
) -> list[TensorDictBase]:
    """The MPC episodes ``batch`` of ``setting`` (:func:`play_episodes` of ``setting_<name>``)."""
    mode, steps = controller.warmup, None  # plan: from the first step
    if mode != "plan":
        steps = max(ctx.cfg.warmup_random_steps, controller.model.context_length)
    policy = mpc_policy(ctx.cfg, planner, controller.threshold, warmup_steps=steps, warmup=mode)
    return play_episodes(ctx, f"setting_{setting.name}", batch, policy)


def batch_part(
    ctx: RunContext, setting: DictConfig, planner, controller: Controller, batch: range
) -> dict:
    """The part record of a batch of episodes: their metrics (logged; ``metrics`` for a batch
    of one, else ``episodes``) and episode 0's ``trajectory_example``."""
    tds = episode_batch(ctx, setting, planner, controller, batch)
    episodes = [episode_metrics(td, controller.scale) for td in tds]
    for e, metrics in zip(batch, episodes, strict=True):
        for key, value in metrics.items():
            if ctx.logger is not None and value == value:  # NaN (no planned step): not logged
                ctx.logger.log_scalar(f"{setting.name}/{key}", value, step=e)
    example = None
    if batch[0] == 0:
        dims = tds[0]["next", "observation"].shape[-1]
        names = list(env_entry(ctx.cfg).state_names) or [f"s{i}" for i in range(dims)]
        example = {"setting": setting.name, **planned_trajectory(tds[0]), "state_names": names}
    part = {"metrics": episodes[0]} if len(episodes) == 1 else {"episodes": episodes}
    return part | {"trajectory_example": example}


def setting_stage(ctx: RunContext, setting: DictConfig, controller: Controller) -> dict:
    """Stage ``setting_<name>``: all episodes of ``setting``, one part record per batch of
    ``num_envs``, so a setting stopped half way resumes at its next unfinished batch."""
    name = f"setting_{setting.name}"

    def run():
        objective, beta = setting_objective(setting, controller.beta_unit)
        planner = build_planner(setting.planner, controller.model, objective)
        groups = batches(ctx.cfg.episodes, ctx.cfg.num_envs)
        parts = ctx.stages.run_parts(
            name,
            len(groups),
            lambda b: batch_part(ctx, setting, planner, controller, groups[b]),
            show_progress=ctx.cfg.progress,
        )
        episodes = []
        for b, (part, batch) in enumerate(zip(parts, groups, strict=True)):
            found = part["episodes"] if "episodes" in part else [part.get("metrics")]
            if len(found) != len(batch) or not all(isinstance(m, dict) for m in found):
                raise DamagedFileError(
                    f"{ctx.stages.run_dir / 'stages' / name / f'part_{b}.json'}: expected the "
                    f"metrics of episodes {batch.start}..{batch.stop - 1} ({len(batch)} dicts), "
                    f"found {len(found)}; it was written with another num_envs or damaged: "
                    "delete it to compute those episodes again."
                )
            episodes += found
        mean, std = episode_mean_std(episodes)
        record = {"episodes": episodes, "mean": mean, "std": std}
        record["trajectory_example"] = parts[0]["trajectory_example"] if parts else None
        costs = [e.get("predicted_cost") for e in episodes]  # NaN: the episode planned no step
        record["ended_in_warmup"] = sum(c != c for c in costs)
        if setting.band is not None:  # the across-seed trend test orders the settings by it
            record["band"] = {k: setting.band[k] for k in ("low", "high", "kind")}
        return record | ({"beta_effective": beta} if setting.beta_relative else {})

    return ctx.stages.run(name, run)


def random_policy_stage(ctx: RunContext) -> dict:
    """Stage ``random_policy``: the env returns of ``episodes`` episodes of uniform random
    actions, of the settings' length, ``num_envs`` at a time."""

    def run() -> dict:
        returns = [
            float(td["next", "reward"].double().sum())
            for batch in batches(ctx.cfg.episodes, ctx.cfg.num_envs)
            for td in play_episodes(ctx, "random_policy", batch)
        ]
        mean, std = mean_std(returns)
        return {"env_returns": returns, "mean": {"env_return": mean}, "std": {"env_return": std}}

    record = ctx.stages.run("random_policy", run)
    record.pop("wall_time_s", None)
    return record


def run(ctx: RunContext) -> dict:
    """Run (or resume) the control experiment; return its results."""
    cfg = ctx.cfg
    frames, steps = cfg.random_episodes * cfg.random_episode_steps, cfg.random_episode_steps
    data = random_data_stage(ctx, "random_data", frames=frames, episode_steps=steps)
    scale = state_scale(data)
    world, estimator, _ = models_stage(ctx, data, "models")
    length = max(cfg.models.window, cfg.training.slice_len)
    per_window_u = window_uncertainty(data, estimator, sequence_length=length)
    threshold = replan_threshold(cfg, per_window_u)
    relative = any(s.beta_relative for s in cfg.settings)
    beta_unit = cost_to_u_ratio(data, per_window_u) if relative else 1.0
    model = planning_model(cfg, world, estimator)  # the env's action bounds
    controller = Controller(model, threshold, beta_unit, scale, warmup_mode(cfg, data))
    results, example = {}, None
    for setting in cfg.settings:
        record = results[setting.name] = setting_stage(ctx, setting, controller)
        first = record.pop("trajectory_example", None)  # kept once, for the first setting
        example = example or first
        record.pop("wall_time_s", None)
    return {
        **ctx.results_header(),
        "replan_threshold": threshold,
        **({"beta_unit": beta_unit} if relative else {}),
        **({"warmup": controller.warmup} if controller.warmup != "random" else {}),
        "mse_units": "squared prediction error per state dim divided by its standard deviation in the random data",
        "settings": results,
        "random_policy": random_policy_stage(ctx),
        "trajectory_example": example,
        "wall_time_s": dict(ctx.stages.wall_time_s),
    }


def check(cfg: DictConfig, errors: RecipeErrors, recipes: RecipeLoader | None) -> None:
    """The control recipe's own checks."""
    data_errors(errors, "random_episode_steps")
    warmup = max(cfg.warmup_random_steps, cfg.models.window)
    errors.need(
        "env.episode_steps",
        cfg.env.episode_steps > warmup,
        f"above max(warmup_random_steps, models.window) = {warmup} (or no step is planned)",
    )
    duplicate_errors(errors, "settings", "setting")
    for i, s in enumerate(cfg.settings):
        planner_errors(
            errors,
            f"settings[{i}].planner",
            lambda s=s: setting_objective(s, 1.0)[0],
            f"with settings[{i}].alpha = {s.alpha}, beta = {s.beta}",
        )


def stage_values(cfg: DictConfig) -> dict:
    """``{setting}`` of the stage names: the recipe's settings."""
    return {"setting": [s.name for s in cfg.settings]}


EXPERIMENT = ExperimentType.of_module(
    sys.modules[__name__],
    name="control",
    help="uncertainty-aware MPC vs the cost-only baseline: prediction and cost errors (§3.1, Fig. 3)",
    schema=ControlConfig,
    list_field=("settings", ControlSetting),
)
