"""Active (uncertainty-guided) vs random exploration: the paper's §3.2 and Table 1, one repeat per seed."""

from __future__ import annotations

import math
from pathlib import Path

import torch
from omegaconf import DictConfig
from scipy import stats
from torchrl.record.loggers import Logger

from torchrl_recon.collectors import (
    collect,
    concat_trajectories,
    validation_trajectories,
)
from torchrl_recon.evaluation import multi_step_errors
from torchrl_recon.experiments.common import (
    build_env,
    build_models,
    build_planner,
    cost_fn,
    fit_both_stage,
    fit_module,
    random_data_stage,
    state_scale,
)
from torchrl_recon.experiments.stages import Stages, stage_seed
from torchrl_recon.planners import PlanningModel
from torchrl_recon.policies import ExplorationPolicy, exploration_objective
from torchrl_recon.policies.mpc import FEASIBLE, REPLANNED

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


def run_explore(cfg: DictConfig, run_dir: Path, logger: Logger | None) -> dict:
    """Run (or resume) one repeat of the exploration experiment in ``run_dir``; return its results."""
    stages = Stages(run_dir, seed=cfg.seed, stop_after=cfg.stop_after, logger=logger)
    episode = cfg.env.episode_steps
    window = cfg.models.window

    random_steps = dict(episode_steps=episode, keys=DATA_KEYS)
    initial = random_data_stage(
        cfg, stages, "initial_random", frames=cfg.initial_random_steps, **random_steps
    )
    scale = state_scale(initial)
    obs_dim, action_dim = initial["observation"].shape[-1], initial["action"].shape[-1]
    world, estimator = build_models(cfg, obs_dim, action_dim)
    fit_both_stage(cfg, stages, "initial_models", initial, world, estimator, logger=logger)

    length = window + cfg.validation.steps

    def validation_stage():
        env = build_env(cfg, seed=stage_seed(cfg.seed, "validation"), episode_steps=length)
        val = validation_trajectories(
            env,
            count=cfg.validation.trajectories,
            length=length,
            seed=stage_seed(cfg.seed, "validation"),
            policy=cfg.validation.policy,
        )
        env.close()
        stages.save_data("validation", val.select(*DATA_KEYS, strict=False).reshape(-1))
        return {"trajectories": cfg.validation.trajectories, "length": length}

    stages.run("validation", validation_stage)
    validation = stages.load_data("validation").reshape(cfg.validation.trajectories, length)

    # Guided exploration, in rounds; after each round both networks are refitted on all data so far.
    guided = cfg.guided
    per_round = episode * guided.refit_every_episodes
    rounds = math.ceil(guided.steps / per_round)
    cost = cost_fn(cfg)
    guided_parts, feasible_counts = [], []
    for r in range(rounds):
        frames = min(per_round, guided.steps - r * per_round)
        name = f"guided_data_{r}"

        def guided_round(name=name, frames=frames, r=r):
            model = PlanningModel(world, cost, uncertainty=estimator)
            objective = exploration_objective(ratio=guided.ratio, cap=guided.cap, beta=guided.beta)
            policy = ExplorationPolicy(build_planner(guided.planner, model, objective))
            env = build_env(
                cfg,
                seed=stage_seed(cfg.seed, name),
                episode_steps=episode,
                policy_device=policy.device,
            )
            env.append_transform(policy.make_tensordict_primer())
            data = collect(
                env,
                policy,
                frames=frames,
                seed=stage_seed(cfg.seed, name),
                progress=cfg.progress,
                desc=f"guided exploration {r + 1}/{rounds}",
            )
            env.close()
            planned = data[REPLANNED].squeeze(-1)
            stages.save_data(name, data.select(*DATA_KEYS))
            return {
                "steps": data.numel(),
                "plans": int(planned.sum()),
                "feasible_plans": int(data[FEASIBLE].squeeze(-1)[planned].sum()),
            }

        record = stages.run(name, guided_round)
        feasible_counts.append((record["feasible_plans"], record["plans"]))
        guided_parts.append(stages.load_data(name))
        if r < rounds - 1:
            grown = concat_trajectories(initial, *guided_parts)
            fit_both_stage(
                cfg,
                stages,
                f"guided_refit_{r}",
                grown,
                world,
                estimator,
                logger=logger,
                fit_normalization=False,
            )

    random_arm = random_data_stage(
        cfg, stages, "random_arm", frames=cfg.random_steps, **random_steps
    )
    arms = {
        "random": concat_trajectories(initial, random_arm),
        "active": concat_trajectories(initial, *guided_parts),
    }

    mse: dict[str, list[float]] = {"random": [], "active": []}
    for i in range(cfg.retrainings):
        for arm, data in arms.items():
            name = f"retrain_{arm}_{i}"

            def retrain(data=data, name=name, i=i):
                seed = stage_seed(cfg.seed, f"retrain_{i}")  # both arms start from the same weights
                torch.manual_seed(seed)
                model, _ = build_models(cfg, obs_dim, action_dim)
                fit_module(cfg, model, data, seed=seed, logger=logger, prefix=f"{name}/")
                errors = multi_step_errors(model, validation, window=window, scale=scale)
                return {"mse": float(errors.mean())}

            mse[arm].append(stages.run(name, retrain)["mse"])
            if logger is not None:
                logger.log_scalar(f"validation_mse/{arm}", mse[arm][-1], step=i)

    summary = {
        arm: {
            "mse": v,
            "mean": float(torch.tensor(v).mean()),
            "std": float(torch.tensor(v).std()) if len(v) > 1 else 0.0,
        }
        for arm, v in mse.items()
    }
    if cfg.retrainings > 1:
        test = stats.ttest_ind(mse["active"], mse["random"], equal_var=False)
        statistic, p_value = float(test.statistic), float(test.pvalue)
    else:
        statistic = p_value = float("nan")
    plans = sum(p for _, p in feasible_counts)
    return {
        "experiment": "explore",
        "env": cfg.env.name,
        "seed": cfg.seed,
        "mse_units": MSE_UNITS,
        "arms": summary,
        "ratio": summary["active"]["mean"] / summary["random"]["mean"],
        "test": {
            "name": "Welch t-test, active vs random, across retrainings",
            "statistic": statistic,
            "p_value": p_value,
        },
        "data": {
            "initial_steps": initial.numel(),
            "random_arm_steps": random_arm.numel(),
            "active_arm_steps": sum(p.numel() for p in guided_parts),
            "active_feasible_fraction": (sum(f for f, _ in feasible_counts) / plans)
            if plans
            else float("nan"),
        },
        "wall_time_s": dict(stages.wall_time_s),
    }
