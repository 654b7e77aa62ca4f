"""The exploration experiment (the paper's §3.2 and Table 1), one repeat per seed: its resumable
:data:`STAGES`, its recipe check and its ``EXPERIMENT``."""

from __future__ import annotations

import copy
import sys

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from torchrl_recon.collectors import (
    EpisodesTooShort,
    collect,
    concat_trajectories,
    validation_trajectories,
)
from torchrl_recon.envs import closing_env
from torchrl_recon.errors import RecipeError
from torchrl_recon.evaluation import population_multi_step_errors
from torchrl_recon.experiments.batching import batches
from torchrl_recon.experiments.config import ExploreConfig
from torchrl_recon.experiments.context import RecipeLoader, RunContext
from torchrl_recon.experiments.experiment_type import ExperimentType
from torchrl_recon.experiments.fit_buffers import split_buffers
from torchrl_recon.experiments.fit_speed import fit_speed_errors
from torchrl_recon.experiments.fit_stages import fit_kwargs, fit_stage, models_stage
from torchrl_recon.experiments.random_data import random_data_stage
from torchrl_recon.experiments.recipe_checks import RecipeErrors, data_errors, planner_errors
from torchrl_recon.experiments.recipe_env import build_env
from torchrl_recon.experiments.recipe_models import build_world_model, dims
from torchrl_recon.experiments.recipe_planning import build_planner, planning_model
from torchrl_recon.experiments.report_units import state_scale
from torchrl_recon.fitting import fit_population
from torchrl_recon.modules import WorldModelPopulation
from torchrl_recon.policies import ExplorationPolicy, exploration_objective
from torchrl_recon.policies.mpc import FEASIBLE, REPLANNED
from torchrl_recon.reports.explore import ARMS
from torchrl_recon.reports.stats import mean_std

_NEXT = tuple(("next", k) for k in ("observation", "reward", "done", "terminated", "truncated"))
DATA_KEYS = ("observation", "action", "is_init", "step_count", *_NEXT, ("collector", "traj_ids"))
"""What a dataset keeps of a collection (the policies' planning state is not data)."""
MSE_UNITS = (
    "mean over validation trajectories, predicted steps and state dims of the squared error of open-loop "
    "multi-step predictions (real context of `window` steps, then `validation.steps` steps from the real "
    "actions), each state dim divided by its standard deviation in the initial random data (shared by both arms)"
)
STAGES = ("validation", "initial_random", "initial_models", "guided_data_{n}", "guided_refit_{n}")
STAGES += ("random_arm", "retrain_{n}")
"""Stage name templates, in run order (``{n}`` a round or a group of ``retrainings_per_fit``
retrainings, fitted as one population); ``guided_refit_<r>`` runs between rounds."""


def validation_stage(ctx: RunContext) -> TensorDictBase:
    """Held-out trajectories ``[trajectories, window + validation.steps]``, ``num_envs`` at a time.

    Raises:
        RecipeError: the env ends the random episodes sooner (:func:`short_validation_error`).
    """
    cfg, count = ctx.cfg, ctx.cfg.validation.trajectories
    length = cfg.models.window + cfg.validation.steps

    def run():
        seed = ctx.stage_seed("validation")
        env = build_env(cfg, seed=seed, episode_steps=length, num_envs=cfg.num_envs)
        with closing_env(env):
            try:
                val = validation_trajectories(
                    env, count=count, length=length, seed=seed, policy=cfg.validation.policy
                )
            except EpisodesTooShort as err:
                raise short_validation_error(cfg, err) from None
        ctx.stages.save_data("validation", val.select(*DATA_KEYS, strict=False).reshape(-1))
        return {"trajectories": count, "length": length}

    ctx.stages.run("validation", run)
    return ctx.stages.load_data("validation").reshape(count, length)


def short_validation_error(cfg: DictConfig, err: EpisodesTooShort) -> RecipeError:
    """Why Table 1's protocol cannot run on an env whose random episodes end early (e.g.
    InvertedPendulum's, of 3-8 steps), and the keys to change.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"env": {"name": "Short-v0"}, "models": {"window": 5},
        ...     "validation": {"trajectories": 4, "steps": 20, "policy": "random"}})
        >>> err = EpisodesTooShort(done=0, count=4, length=25, attempts=40, median=3, longest=3)
        >>> print(short_validation_error(cfg, err))  # doctest: +ELLIPSIS
        explore on Short-v0: Table 1's validation MSE predicts validation.steps = 20 steps open loop after a real context of models.window = 5 steps, on validation.trajectories = 4 trajectories of 25 steps that the env must not end (validation.policy = random); only 0 of 40 attempts lasted 25 steps (median 3, longest 3): ...
    """
    v, window = cfg.validation, cfg.models.window
    return RecipeError(
        f"explore on {cfg.env.name}: Table 1's validation MSE predicts validation.steps = "
        f"{v.steps} steps open loop after a real context of models.window = {window} steps, on "
        f"validation.trajectories = {v.trajectories} trajectories of {err.length} steps that the "
        f"env must not end (validation.policy = {v.policy}); only {err.done} of {err.attempts} "
        f"attempts lasted {err.length} steps (median {err.median}, longest {err.longest}): this "
        "env's episodes end too early for that protocol. Lower models.window + validation.steps "
        f"to what most random episodes last (about {err.median}), or study this env with the "
        "control or online kinds, which run on episodes that end early."
    )


def guided_round_stage(
    ctx: RunContext, world, estimator, r: int, rounds: int, frames: int
) -> tuple[dict, TensorDictBase]:
    """Stage ``guided_data_<r>``: ``frames`` steps of the exploration policy planning with
    ``world`` and ``estimator`` (``num_envs`` envs planned in one call); its record and data."""
    cfg, guided, name = ctx.cfg, ctx.cfg.guided, f"guided_data_{r}"

    def run():
        model = planning_model(cfg, world, estimator)  # the env's action bounds
        objective = exploration_objective(ratio=guided.ratio, cap=guided.cap, beta=guided.beta)
        policy = ExplorationPolicy(build_planner(guided.planner, model, objective))
        seed = ctx.stage_seed(name)
        env = build_env(cfg, seed=seed, policy=policy, num_envs=cfg.num_envs)
        desc = f"guided exploration {r + 1}/{rounds}"
        with closing_env(env):  # the collector has closed a batched env already
            data = collect(env, policy, frames=frames, seed=seed, progress=cfg.progress, desc=desc)
        planned = data[REPLANNED].squeeze(-1)
        ctx.stages.save_data(name, data.select(*DATA_KEYS))
        feasible = int(data[FEASIBLE].squeeze(-1)[planned].sum())
        return {"steps": data.numel(), "plans": int(planned.sum()), "feasible_plans": feasible}

    record = ctx.stages.run(name, run)
    return record, ctx.stages.load_data(name)


def retrain_stage(
    ctx: RunContext,
    group: int,
    retrainings: range,
    arms: dict[str, TensorDictBase],
    validation: TensorDictBase,
    scale: torch.Tensor,
) -> dict[str, dict[str, list]]:
    """Stage ``retrain_<group>``: retrainings ``retrainings`` of a fresh world model on each
    arm's data, fitted as one population; per arm the validation MSE (units of ``scale``), best
    validation loss and fit steps of each.

    Retraining i starts both arms from the same weights (seeded by ``retrain_<i>``); an arm's
    members share one split of its data (seeded by ``retrain_split``) and one sample per step
    (``fit_population(shared_sampling=True)``), as the paper's retrainings on the same data do.
    """
    cfg, name, n = ctx.cfg, f"retrain_{group}", len(retrainings)

    def run():
        seeds, initial = [ctx.stage_seed(f"retrain_{i}") for i in retrainings], []
        for seed in seeds:
            torch.manual_seed(seed)
            initial.append(build_world_model(cfg, *dims(arms["random"])).to(ctx.device))
        splits = [split_buffers(cfg, arms[arm], ctx.stage_seed("retrain_split")) for arm in ARMS]
        # each arm's retrainings: the last arm takes the initial networks, the others copies
        members = [w if arm == ARMS[-1] else copy.deepcopy(w) for arm in ARMS for w in initial]
        fits = fit_population(
            members,
            [rb for rb, _ in splits for _ in retrainings],
            seeds=seeds * len(ARMS),
            val_buffers=[val_rb for _, val_rb in splits for _ in retrainings],
            mode=cfg.training.world_model_mode,
            shared_sampling=True,
            **fit_kwargs(ctx, "world_model", f"{name}/", population=True),
        )
        population = WorldModelPopulation.from_members(members)
        window = cfg.models.window
        errors = population_multi_step_errors(population, validation, window=window, scale=scale)
        mse, record = errors.mean((-2, -1)).tolist(), {"retrainings": list(retrainings)}
        for a, arm in enumerate(ARMS):
            mine = slice(a * n, (a + 1) * n)
            losses, steps = [f.best_val_loss for f in fits[mine]], [f.steps for f in fits[mine]]
            record[arm] = {"mse": mse[mine], "val_loss": losses, "steps": steps}
        return record

    return ctx.stages.run(name, run)


def run(ctx: RunContext) -> dict:
    """Run (or resume) one repeat of the exploration experiment; return its results."""
    cfg, guided = ctx.cfg, ctx.cfg.guided
    validation = validation_stage(ctx)  # first: an env that ends it early is refused before any fit
    initial = random_data_stage(
        ctx, "initial_random", frames=cfg.initial_random_steps, keys=DATA_KEYS
    )
    scale = state_scale(initial)
    world, estimator, _ = models_stage(ctx, initial, "initial_models")
    # guided exploration in rounds, both networks refitted on all data after each but the last
    rounds = batches(guided.steps, cfg.env.episode_steps * guided.refit_every_episodes)
    parts, plans, feasible = [], 0, 0
    for r, steps in enumerate(rounds):
        record, data = guided_round_stage(ctx, world, estimator, r, len(rounds), len(steps))
        plans, feasible = plans + record["plans"], feasible + record["feasible_plans"]
        parts.append(data)
        if r < len(rounds) - 1:
            grown = concat_trajectories(initial, *parts)
            modules = {"world_model": world, "uncertainty": estimator}
            fit_stage(ctx, f"guided_refit_{r}", grown, modules, fit_normalization=False)
    random_arm = random_data_stage(ctx, "random_arm", frames=cfg.random_steps, keys=DATA_KEYS)
    arms = {
        "random": concat_trajectories(initial, random_arm),
        "active": concat_trajectories(initial, *parts),
    }
    mse: dict[str, list[float]] = {arm: [] for arm in ARMS}
    for g, group in enumerate(batches(cfg.retrainings, cfg.retrainings_per_fit)):
        record = retrain_stage(ctx, g, group, arms, validation, scale)
        for arm in ARMS:
            for i, value in zip(group, record[arm]["mse"], strict=True):
                mse[arm].append(value)
                if ctx.logger is not None:
                    ctx.logger.log_scalar(f"validation_mse/{arm}", value, step=i)
    summary = {}
    for arm, values in mse.items():
        mean, std = mean_std(values, dtype=torch.float32)  # as recorded since the first runs
        summary[arm] = {"mse": values, "mean": mean, "std": std}
    test = {"name": "Welch t-test, active vs random, across retrainings"}
    test |= {"statistic": float("nan"), "p_value": float("nan")}
    if cfg.retrainings > 1:
        from scipy import stats  # here: importing scipy.stats costs every command ~0.5 s

        welch = stats.ttest_ind(mse["active"], mse["random"], equal_var=False)
        test |= {"statistic": float(welch.statistic), "p_value": float(welch.pvalue)}
    return {
        **ctx.results_header(),
        "mse_units": MSE_UNITS,
        "arms": summary,
        "ratio": summary["active"]["mean"] / summary["random"]["mean"],
        "test": test,
        "data": {
            "initial_steps": initial.numel(),
            "random_arm_steps": random_arm.numel(),
            "active_arm_steps": sum(p.numel() for p in parts),
            "active_feasible_fraction": feasible / plans if plans else float("nan"),
        },
        "wall_time_s": dict(ctx.stages.wall_time_s),
    }


def check(cfg: DictConfig, errors: RecipeErrors, recipes: RecipeLoader | None) -> None:
    """The explore recipe's own checks (the fits' speed: :func:`~.fit_speed.fit_speed_errors`)."""
    g = cfg.guided
    data_errors(errors, "env.episode_steps", "initial_random_steps")
    fit_speed_errors(errors)
    planner_errors(
        errors,
        "guided.planner",
        lambda: exploration_objective(ratio=g.ratio, cap=g.cap, beta=g.beta),
        f"with the exploration objective: alpha 0, guided.beta = {g.beta}",
    )


EXPERIMENT = ExperimentType.of_module(
    sys.modules[__name__],
    name="explore",
    help="active vs random exploration: validation MSE of models fitted on each (§3.2, Table 1)",
    schema=ExploreConfig,
)
