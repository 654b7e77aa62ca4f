"""Uncertainty-aware model-based control: the paper's §3.1 and Fig. 3."""

from __future__ import annotations

import math
from pathlib import Path

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.record.loggers import Logger

from torchrl_recon.data import cut_sequences
from torchrl_recon.envs import get_entry
from torchrl_recon.experiments.common import (
    build_env,
    build_models,
    build_planner,
    cost_fn,
    fit_both_stage,
    random_data_stage,
    run_device,
    state_scale,
)
from torchrl_recon.experiments.stages import Stages, stage_seed
from torchrl_recon.planners import Objective, PlanningModel, UncertaintyBand, cost_to_u_ratio
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.policies.mpc import FEASIBLE, PRED_COST, PRED_NEXT, PRED_U, REPLANNED

METRICS = (
    "prediction_mse",
    "cost_error",
    "real_cost",
    "predicted_cost",
    "replans",
    "mean_u",
    "feasible_fraction",
)


def episode_metrics(td: TensorDictBase, scale: torch.Tensor) -> dict[str, float]:
    """Predicted-vs-real metrics of one MPC episode (steps taken from a plan only).

    ``prediction_mse`` is in units of ``scale`` per state dim; costs are summed over planned steps.
    """
    planned = ~torch.isnan(td[PRED_COST].squeeze(-1))
    replanned = td[REPLANNED].squeeze(-1)
    if not planned.any():
        return {k: float("nan") for k in METRICS} | {"replans": 0, "steps": int(td.shape[0])}
    err = (td[PRED_NEXT][planned] - td["next", "observation"][planned]) / scale
    predicted_cost = float(td[PRED_COST].squeeze(-1)[planned].sum())
    real_cost = float(-td["next", "reward"].squeeze(-1)[planned].sum())
    feasible = td[FEASIBLE].squeeze(-1)[replanned]
    return {
        "prediction_mse": float(err.pow(2).mean()),
        "cost_error": abs(predicted_cost - real_cost),
        "real_cost": real_cost,
        "predicted_cost": predicted_cost,
        "replans": int(replanned.sum()),
        "mean_u": float(td[PRED_U].squeeze(-1)[planned].mean()),
        "feasible_fraction": float(feasible.float().mean()) if feasible.numel() else float("nan"),
        "steps": int(td.shape[0]),
    }


def episode_mean_std(episodes: list[dict]) -> tuple[dict, dict]:
    """Mean and std over episodes of each metric in :data:`METRICS` (NaN episodes skipped).

    Examples:
        >>> mean, std = episode_mean_std([{k: 1.0 for k in METRICS}, {k: 3.0 for k in METRICS}])
        >>> mean["prediction_mse"], round(std["prediction_mse"], 3)
        (2.0, 1.414)
    """
    mean, std = {}, {}
    for key in METRICS:
        values = torch.tensor([e[key] for e in episodes], dtype=torch.float64)
        values = values[~torch.isnan(values)]
        mean[key] = float(values.mean()) if len(values) else float("nan")
        std[key] = float(values.std()) if len(values) > 1 else 0.0
    return mean, std


def run_control(cfg: DictConfig, run_dir: Path, logger: Logger | None) -> dict:
    """Run (or resume) the control experiment in ``run_dir``; return its results."""
    stages = Stages(run_dir, seed=cfg.seed, stop_after=cfg.stop_after, logger=logger)

    data = random_data_stage(
        cfg,
        stages,
        "random_data",
        frames=cfg.random_episodes * cfg.random_episode_steps,
        episode_steps=cfg.random_episode_steps,
    )
    scale = state_scale(data)
    obs_dim, action_dim = data["observation"].shape[-1], data["action"].shape[-1]
    world, estimator = build_models(cfg, obs_dim, action_dim)
    fit_both_stage(cfg, stages, "models", data, world, estimator, logger=logger)

    device = run_device(cfg)
    with torch.no_grad():
        seqs = cut_sequences(data, max(cfg.models.window, cfg.training.slice_len)).to(device)
        per_window_u = estimator.score(seqs["observation"], seqs["action"]).flatten().cpu()
    threshold = (
        float(per_window_u.quantile(cfg.replan.threshold_quantile)) * cfg.replan.threshold_scale
    )
    if cfg.replan.threshold_on == "cumulative":
        threshold *= cfg.replan.every  # Σu over `every` steps at the same per-step level
    relative = any(s.beta_relative for s in cfg.settings)
    beta_unit = cost_to_u_ratio(data, per_window_u) if relative else 1.0
    model = PlanningModel(world, cost_fn(cfg), uncertainty=estimator)

    results, example = {}, None
    for setting in cfg.settings:
        name = f"setting_{setting.name}"

        def run_setting(setting=setting, name=name):
            band = (
                None
                if setting.band is None
                else UncertaintyBand(setting.band.low, setting.band.high, setting.band.kind)
            )
            beta = setting.beta * beta_unit if setting.beta_relative else setting.beta
            objective = Objective(
                alpha=setting.alpha,
                beta=beta,
                band=band,
                cost_threshold=setting.cost_threshold,
            )
            planner = build_planner(setting.planner, model, objective)

            def run_episode(e: int) -> dict:
                policy = MPCPolicy(
                    planner,
                    replan=cfg.replan.mode,
                    replan_every=cfg.replan.every,
                    threshold=threshold if cfg.replan.mode == "uncertainty" else None,
                    threshold_on=cfg.replan.threshold_on,
                    error_threshold=cfg.replan.error_threshold,
                    warmup_steps=max(cfg.warmup_random_steps, model.context_length),
                )
                episode_seed = stage_seed(cfg.seed, f"{name}_{e}")
                env = build_env(
                    cfg,
                    seed=episode_seed,
                    episode_steps=cfg.env.episode_steps,
                    policy_device=device,
                )
                env.append_transform(policy.make_tensordict_primer())
                torch.manual_seed(episode_seed)
                td = env.rollout(cfg.env.episode_steps, policy, break_when_any_done=True).cpu()
                env.close()
                metrics = episode_metrics(td, scale)
                if logger is not None:
                    for key, value in metrics.items():
                        if not (isinstance(value, float) and math.isnan(value)):
                            logger.log_scalar(f"{setting.name}/{key}", value, step=e)
                state_names = get_entry(cfg.env.name).state_names
                example = _trajectory(td, setting.name, state_names) if e == 0 else None
                return {"metrics": metrics, "trajectory_example": example}

            # one record per episode: a setting stopped half way resumes at its next episode
            parts = stages.run_parts(name, cfg.episodes, run_episode, show_progress=cfg.progress)
            episodes = [part["metrics"] for part in parts]
            first = parts[0]["trajectory_example"] if parts else None
            mean, std = episode_mean_std(episodes)
            record = {"episodes": episodes, "mean": mean, "std": std, "trajectory_example": first}
            return record | ({"beta_effective": beta} if setting.beta_relative else {})

        record = stages.run(name, run_setting)
        first = record.pop("trajectory_example", None)  # kept once, for the first setting
        example = example or first
        record.pop("wall_time_s", None)
        results[setting.name] = record

    return {
        "experiment": "control",
        "env": cfg.env.name,
        "seed": cfg.seed,
        "replan_threshold": threshold,
        **({"beta_unit": beta_unit} if relative else {}),
        "mse_units": "squared prediction error per state dim divided by its standard deviation in the random data",
        "settings": results,
        "trajectory_example": example,
        "wall_time_s": dict(stages.wall_time_s),
    }


def _trajectory(td: TensorDictBase, setting: str, state_names: tuple[str, ...] = ()) -> dict:
    """Real and predicted next states, u and re-plans of one episode (planned steps), for a Fig. 2 plot."""
    planned = ~torch.isnan(td[PRED_COST].squeeze(-1))
    real = td["next", "observation"][planned]
    return {
        "setting": setting,
        "real": real.tolist(),
        "predicted": td[PRED_NEXT][planned].tolist(),
        "uncertainty": td[PRED_U].squeeze(-1)[planned].tolist(),
        "replanned": td[REPLANNED].squeeze(-1)[planned].tolist(),
        "state_names": list(state_names) or [f"s{i}" for i in range(real.shape[-1])],
    }
