"""The stages of the exploration experiment (the paper's §3.2 and Table 1), one repeat per seed.

``initial_random`` → ``initial_models`` → ``validation`` → ``guided_data_<r>`` (with
``guided_refit_<r>`` between rounds) → ``random_arm`` → ``retrain_<g>`` (both arms' retrainings
fitted as one population, in groups of ``retrainings_per_fit``); each stage takes the
:class:`~torchrl_recon.experiments.context.RunContext` and is resumable.
"""

from __future__ import annotations

import copy
import math

import torch
from scipy import stats
from tensordict import TensorDictBase

from torchrl_recon.collectors import (
    collect,
    concat_trajectories,
    validation_trajectories,
)
from torchrl_recon.envs import close_env
from torchrl_recon.evaluation import population_multi_step_errors
from torchrl_recon.experiments.common import (
    build_env,
    build_models,
    build_planner,
    build_world_model,
    fit_kwargs,
    fit_stage,
    planning_model,
    random_data_stage,
    split_buffers,
    state_scale,
)
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.stats import mean_std
from torchrl_recon.modules import WorldModelPopulation
from torchrl_recon.policies import ExplorationPolicy, exploration_objective
from torchrl_recon.policies.mpc import FEASIBLE, REPLANNED
from torchrl_recon.training import fit_population

# What a dataset keeps of a collection (the policies' planning state is not data).
DATA_KEYS = (
    "observation",
    "action",
    "is_init",
    "step_count",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("collector", "traj_ids"),
)
MSE_UNITS = (
    "mean over validation trajectories, predicted steps and state dims of the squared error of open-loop "
    "multi-step predictions (real context of `window` steps, then `validation.steps` steps from the real "
    "actions), each state dim divided by its standard deviation in the initial random data (shared by both arms)"
)


STAGES = (
    "initial_random",
    "initial_models",
    "validation",
    "guided_data_{n}",
    "guided_refit_{n}",
    "random_arm",
    "retrain_{n}",
)
"""Stage name templates, in run order (``{n}`` a round or a group of retrainings)."""
ARMS = ("random", "active")


def random_steps_stage(ctx: RunContext, name: str, frames: int) -> TensorDictBase:
    """``frames`` uniform random steps in the env's episodes (stage ``initial_random`` or
    ``random_arm``), keeping :data:`DATA_KEYS`."""
    episode = ctx.cfg.env.episode_steps
    return random_data_stage(ctx, name, frames=frames, episode_steps=episode, keys=DATA_KEYS)


def models_stage(ctx: RunContext, data: TensorDictBase, name: str):
    """Build the world model and the estimator and fit both on ``data`` (stage ``name``:
    explore's ``initial_models``, control's ``models``); returns them."""
    obs_dim, action_dim = data["observation"].shape[-1], data["action"].shape[-1]
    world, estimator = build_models(ctx.cfg, obs_dim, action_dim, ctx.device)
    fit_stage(ctx, name, data, {"world_model": world, "uncertainty": estimator})
    return world, estimator


def validation_stage(ctx: RunContext) -> TensorDictBase:
    """Held-out trajectories ``[trajectories, window + validation.steps]`` (stage ``validation``),
    drawn ``num_envs`` at a time."""
    cfg = ctx.cfg
    length = cfg.models.window + cfg.validation.steps

    def run():
        seed = ctx.stage_seed("validation")
        env = build_env(cfg, seed=seed, episode_steps=length, num_envs=cfg.num_envs)
        count = cfg.validation.trajectories
        val = validation_trajectories(
            env, count=count, length=length, seed=seed, policy=cfg.validation.policy
        )
        close_env(env)
        ctx.stages.save_data("validation", val.select(*DATA_KEYS, strict=False).reshape(-1))
        return {"trajectories": cfg.validation.trajectories, "length": length}

    ctx.stages.run("validation", run)
    return ctx.stages.load_data("validation").reshape(cfg.validation.trajectories, length)


def guided_round_stage(
    ctx: RunContext, world, estimator, r: int, rounds: int, frames: int
) -> tuple[dict, TensorDictBase]:
    """Round ``r`` of guided exploration (stage ``guided_data_<r>``): ``frames`` steps of the
    exploration policy planning with ``world`` and ``estimator`` (in ``num_envs`` envs at
    once, planned in one call); returns its record and data."""
    cfg, guided, name = ctx.cfg, ctx.cfg.guided, f"guided_data_{r}"

    def run():
        model = planning_model(cfg, world, estimator)  # the env's action bounds
        objective = exploration_objective(ratio=guided.ratio, cap=guided.cap, beta=guided.beta)
        policy = ExplorationPolicy(build_planner(guided.planner, model, objective))
        seed, steps = ctx.stage_seed(name), cfg.env.episode_steps
        env = build_env(
            cfg, seed=seed, episode_steps=steps, policy_device=policy.device, num_envs=cfg.num_envs
        )
        env.append_transform(policy.make_tensordict_primer())
        desc = f"guided exploration {r + 1}/{rounds}"
        data = collect(env, policy, frames=frames, seed=seed, progress=cfg.progress, desc=desc)
        close_env(env)  # the collector has closed a batched env already
        planned = data[REPLANNED].squeeze(-1)
        ctx.stages.save_data(name, data.select(*DATA_KEYS))
        return {
            "steps": data.numel(),
            "plans": int(planned.sum()),
            "feasible_plans": int(data[FEASIBLE].squeeze(-1)[planned].sum()),
        }

    record = ctx.stages.run(name, run)
    return record, ctx.stages.load_data(name)


def guided_stages(
    ctx: RunContext, initial: TensorDictBase, world, estimator
) -> tuple[list[TensorDictBase], list[tuple[int, int]]]:
    """Guided exploration in rounds; after each round but the last both networks are refitted
    on all data so far (stage ``guided_refit_<r>``). Returns the rounds' data and their
    (feasible plans, plans)."""
    guided = ctx.cfg.guided
    per_round = ctx.cfg.env.episode_steps * guided.refit_every_episodes
    rounds = math.ceil(guided.steps / per_round)
    parts, feasible_counts = [], []
    for r in range(rounds):
        frames = min(per_round, guided.steps - r * per_round)
        record, data = guided_round_stage(ctx, world, estimator, r, rounds, frames)
        feasible_counts.append((record["feasible_plans"], record["plans"]))
        parts.append(data)
        if r < rounds - 1:
            grown = concat_trajectories(initial, *parts)
            modules = {"world_model": world, "uncertainty": estimator}
            fit_stage(ctx, f"guided_refit_{r}", grown, modules, fit_normalization=False)
    return parts, feasible_counts


def retrain_groups(retrainings: int, per_fit: int | None) -> list[list[int]]:
    """The retrainings fitted together, in order: groups of ``per_fit`` (all in one if None).

    Examples:
        >>> retrain_groups(5, 2), retrain_groups(3, None)
        ([[0, 1], [2, 3], [4]], [[0, 1, 2]])
    """
    size = retrainings if per_fit is None else per_fit
    return [list(range(i, min(i + size, retrainings))) for i in range(0, retrainings, size)]


def retrain_stage(
    ctx: RunContext,
    group: int,
    retrainings: list[int],
    arms: dict[str, TensorDictBase],
    validation: TensorDictBase,
    scale: torch.Tensor,
) -> dict[str, dict[str, list]]:
    """Retrainings ``retrainings`` of a fresh world model on each arm's data, fitted as one
    population (stage ``retrain_<group>``); returns per arm the validation MSE (units of
    ``scale``), best validation loss and fit steps of each retraining, in order.

    Retraining i starts both arms from the same weights (seeded by ``retrain_<i>``). Each arm's
    data is split once (seeded by ``retrain_split``) into training and validation trajectories,
    and its members draw their batches from that one buffer as one sample per step
    (``fit_population(shared_sampling=True)``): the retrainings of an arm differ in their
    initialisation and the windows they see, as the paper's retrainings on the same data do.
    """
    cfg, name, window = ctx.cfg, f"retrain_{group}", ctx.cfg.models.window
    first = next(iter(arms.values()))
    obs_dim, action_dim = first["observation"].shape[-1], first["action"].shape[-1]

    def run():
        seeds, initial = [ctx.stage_seed(f"retrain_{i}") for i in retrainings], []
        for seed in seeds:
            torch.manual_seed(seed)
            initial.append(build_world_model(cfg, obs_dim, action_dim).to(ctx.device))
        n, members, buffers, val_buffers = len(retrainings), [], [], []
        for arm in ARMS:  # the last arm takes the initial networks, the others copies
            rb, val_rb = split_buffers(cfg, arms[arm], ctx.stage_seed("retrain_split"))
            members += [w if arm == ARMS[-1] else copy.deepcopy(w) for w in initial]
            buffers, val_buffers = buffers + [rb] * n, val_buffers + [val_rb] * n
        fits = fit_population(
            members,
            buffers,
            seeds=seeds * len(ARMS),
            val_buffers=val_buffers,
            mode=cfg.training.world_model_mode,
            shared_sampling=True,
            **fit_kwargs(cfg.training.world_model, cfg.progress, ctx.logger, f"{name}/"),
        )
        population = WorldModelPopulation.from_members(members)
        errors = population_multi_step_errors(population, validation, window=window, scale=scale)
        mse = errors.mean((-2, -1)).tolist()
        return {
            "retrainings": list(retrainings),
            **{
                arm: {
                    "mse": mse[a * n : (a + 1) * n],
                    "val_loss": [f.best_val_loss for f in fits[a * n : (a + 1) * n]],
                    "steps": [f.steps for f in fits[a * n : (a + 1) * n]],
                }
                for a, arm in enumerate(ARMS)
            },
        }

    return ctx.stages.run(name, run)


def explore_results(
    ctx: RunContext,
    mse: dict[str, list[float]],
    steps: dict[str, int],
    feasible_counts: list[tuple[int, int]],
) -> dict:
    """The results dict: arm statistics over retrainings, their ratio, a Welch t-test."""
    cfg = ctx.cfg
    summary = {}
    for arm, v in mse.items():
        mean, std = mean_std(v, dtype=torch.float32)  # as recorded since the first runs
        summary[arm] = {"mse": v, "mean": mean, "std": std}
    if cfg.retrainings > 1:
        test = stats.ttest_ind(mse["active"], mse["random"], equal_var=False)
        statistic, p_value = float(test.statistic), float(test.pvalue)
    else:
        statistic = p_value = float("nan")
    plans, feasible = sum(p for _, p in feasible_counts), sum(f for f, _ in feasible_counts)
    return {
        **ctx.results_header(),
        "mse_units": MSE_UNITS,
        "arms": summary,
        "ratio": summary["active"]["mean"] / summary["random"]["mean"],
        "test": {
            "name": "Welch t-test, active vs random, across retrainings",
            "statistic": statistic,
            "p_value": p_value,
        },
        "data": {**steps, "active_feasible_fraction": feasible / plans if plans else float("nan")},
        "wall_time_s": dict(ctx.stages.wall_time_s),
    }


def run(ctx: RunContext) -> dict:
    """Run (or resume) one repeat of the exploration experiment; return its results."""
    cfg = ctx.cfg
    initial = random_steps_stage(ctx, "initial_random", cfg.initial_random_steps)
    scale = state_scale(initial)
    world, estimator = models_stage(ctx, initial, "initial_models")
    validation = validation_stage(ctx)
    guided_parts, feasible_counts = guided_stages(ctx, initial, world, estimator)
    random_arm = random_steps_stage(ctx, "random_arm", cfg.random_steps)
    arms = {
        "random": concat_trajectories(initial, random_arm),
        "active": concat_trajectories(initial, *guided_parts),
    }
    mse: dict[str, list[float]] = {arm: [] for arm in ARMS}
    for g, group in enumerate(retrain_groups(cfg.retrainings, cfg.retrainings_per_fit)):
        record = retrain_stage(ctx, g, group, arms, validation, scale)
        for arm in ARMS:
            for i, value in zip(group, record[arm]["mse"], strict=True):
                mse[arm].append(value)
                if ctx.logger is not None:
                    ctx.logger.log_scalar(f"validation_mse/{arm}", value, step=i)
    steps = {
        "initial_steps": initial.numel(),
        "random_arm_steps": random_arm.numel(),
        "active_arm_steps": sum(p.numel() for p in guided_parts),
    }
    return explore_results(ctx, mse, steps, feasible_counts)
