"""Uncertainty estimators side by side (issue 7): calibration, out-of-distribution detection,
cost, and the outcome of the two experiments with each.

Stages (each resumable): ``random_data`` → ``world_model`` → ``fit_<estimator>`` for each →
``evaluation`` (rank correlation with the world model's real error on imagined held-out
trajectories, AUROC for "error above its median", OOD AUROC) → ``timing`` (scoring K × H
windows and one CEM call, as ratios to the first ``reconstruction`` estimator) →
``outcome_<estimator>_{explore,control}`` (the two experiments at a reduced scale, each in its
own run directory under ``outcomes/``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import Logger

from torchrl_recon._timing import interleaved_median_ms
from torchrl_recon.collectors import collect_random, validation_trajectories
from torchrl_recon.data import cut_sequences
from torchrl_recon.evaluation import auroc, imagined_uncertainty_and_error, spearman
from torchrl_recon.experiments.common import (
    build_env,
    build_estimator,
    build_world_model,
    cost_fn,
    fit_module,
    random_data_stage,
    run_device,
    state_scale,
)
from torchrl_recon.experiments.stages import Stages, stage_seed
from torchrl_recon.modules import LSTMWorldModel, UncertaintyEstimator, module_device
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.training import load_checkpoint, save_checkpoint


def calibration_metrics(
    world: LSTMWorldModel,
    estimator: UncertaintyEstimator,
    trajectories,
    ood_windows,
    *,
    window: int,
    scale: torch.Tensor,
    state_shift: float,
    action_high: torch.Tensor,
) -> dict[str, float]:
    """How well ``estimator``'s u ranks real prediction error and flags out-of-distribution windows.

    ``trajectories`` ``[V, window + H]``: the world model imagines the last H steps; Σu of
    each imagined trajectory is compared with its real MSE (units of ``scale``): Spearman
    correlation and AUROC for "MSE above its median". ``ood_windows`` ``[W, T]`` real windows:
    AUROC of u on them (negatives) against the same windows with the states moved by
    ``state_shift``·``scale`` and with the actions held at ``action_high`` (positives).
    """
    with torch.no_grad():
        u_sum, mse = imagined_uncertainty_and_error(
            world, estimator, trajectories, window=window, scale=scale
        )
        above = mse > mse.median()
        device = module_device(estimator)
        obs, act = ood_windows["observation"].to(device), ood_windows["action"].to(device)
        scale, action_high = scale.to(device), action_high.to(device)
        u_in = estimator.score(obs, act)[:, 0]
        u_shift = estimator.score(obs + state_shift * scale, act)[:, 0]
        u_bound = estimator.score(obs, action_high.expand_as(act))[:, 0]
    return {
        "spearman": spearman(u_sum, mse),
        "auroc_error_above_median": auroc(u_sum[~above], u_sum[above]),
        "ood_auroc_state_shift": auroc(u_in, u_shift),
        "ood_auroc_action_bound": auroc(u_in, u_bound),
        "mean_trajectory_mse": float(mse.mean()),
    }


def _score_no_grad(estimator: UncertaintyEstimator, x: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return estimator.score_sequence(x)


def _timing(
    cfg: DictConfig,
    world: LSTMWorldModel,
    estimators: dict[str, UncertaintyEstimator],
    data,
) -> dict[str, Any]:
    """Scoring and CEM planning time per estimator (and CEM without u), per horizon, interleaved."""
    t, window = cfg.timing, cfg.models.window
    device = module_device(world)
    seqs = cut_sequences(data, window + 1).to(device)
    ctx = (seqs["observation"][0, :window], seqs["action"][0, :window], seqs["observation"][0, -1])
    features = torch.cat([data["observation"], data["action"]], -1).to(device)
    loc, spread = features.mean(0), features.std(0)
    cost = cost_fn(cfg)
    out: dict[str, Any] = {"threads": torch.get_num_threads(), "candidates": t.candidates}
    for horizon in t.horizons:
        generator = torch.Generator().manual_seed(horizon)
        x = loc + spread * torch.randn(
            t.candidates, window - 1 + horizon, features.shape[-1], generator=generator
        ).to(device)
        cem = dict(num_candidates=t.candidates, iterations=t.iterations, num_elites=t.num_elites)
        plain = CEMPlanner(PlanningModel(world, cost), Objective(), horizon=horizon, **cem)
        fns: dict[str, Callable[[], object]] = {"cem_without_u": lambda p=plain: p.plan(*ctx)}
        for name, est in estimators.items():
            planner = CEMPlanner(
                PlanningModel(world, cost, uncertainty=est),
                Objective(beta=0.1),
                horizon=horizon,
                **cem,
            )
            fns[f"{name}/score"] = lambda e=est, x=x: _score_no_grad(e, x)
            fns[f"{name}/cem"] = lambda p=planner: p.plan(*ctx)
        times = interleaved_median_ms(fns, t.repeats)
        row: dict[str, Any] = {"cem_without_u_ms": times["cem_without_u"]}
        for name in estimators:
            row[name] = {"score_ms": times[f"{name}/score"], "cem_ms": times[f"{name}/cem"]}
        out[f"H{horizon}"] = row
    return out


def _outcome(
    cfg: DictConfig, spec: DictConfig, kind: str, run_dir: Path, seed: int
) -> dict[str, Any] | None:
    """Run the ``kind`` experiment of ``outcomes`` with ``spec`` as its estimator; its headline numbers."""
    from torchrl_recon.experiments.recipe import load_recipe, resolve_recipe_path
    from torchrl_recon.experiments.runner import run

    recipe = resolve_recipe_path(cfg.outcomes[f"{kind}_recipe"])
    sub = load_recipe(recipe, list(cfg.outcomes[f"{kind}_overrides"]))
    sub.seed, sub.threads, sub.progress = seed, cfg.threads, False
    sub.output_dir = str(run_dir / "outcomes" / spec.name / kind)
    sub.logger.backend = "none"
    sub.models.window = cfg.models.window
    for key in ("kind", "hidden_size", "activation"):
        sub.models.uncertainty[key] = spec[key]
    sub.models.uncertainty.kwargs = OmegaConf.to_container(spec.kwargs, resolve=True)
    results = run(sub)
    if results is None:
        return None
    if kind == "explore":
        return {
            "random_mse": results["arms"]["random"]["mean"],
            "active_mse": results["arms"]["active"]["mean"],
            "ratio": results["ratio"],
            "p_value": (results.get("test") or {}).get("p_value"),
            "active_feasible_fraction": results.get("active_feasible_fraction"),
        }
    return {
        name: {k: s["mean"][k] for k in ("prediction_mse", "cost_error", "real_cost", "replans")}
        for name, s in results["settings"].items()
    }


def _flat_outcomes(outcomes: dict[str, Any]) -> dict[str, float]:
    """``explore_ratio`` and ``control_<setting>_<metric>``: the outcomes as top-level numbers."""
    flat = {}
    if outcomes.get("explore"):
        flat["explore_ratio"] = outcomes["explore"]["ratio"]
    for setting, metrics in (outcomes.get("control") or {}).items():
        for key, value in metrics.items():
            flat[f"control_{setting}_{key}"] = value
    return flat


def run_calibration(cfg: DictConfig, run_dir: Path, logger: Logger | None) -> dict[str, Any]:
    """Run (or resume) the estimator comparison in ``run_dir``; return its results."""
    stages = Stages(run_dir, seed=cfg.seed, stop_after=cfg.stop_after, logger=logger)
    window, ev = cfg.models.window, cfg.evaluation

    data = random_data_stage(
        cfg,
        stages,
        "random_data",
        frames=cfg.random_steps,
        episode_steps=cfg.random_episode_steps,
    )
    scale = state_scale(data)
    obs_dim, action_dim = data["observation"].shape[-1], data["action"].shape[-1]
    device = run_device(cfg)
    world = build_world_model(cfg, obs_dim, action_dim).to(device)

    def fit_stage(name: str, module) -> dict:
        path = stages.path("checkpoints", f"{name}.pt")

        def fit() -> dict:
            seed = torch.initial_seed() % (2**31)
            loss = fit_module(cfg, module, data, seed=seed, logger=logger, prefix=f"{name}/")
            save_checkpoint(path, {name: module})
            return {"val_loss": loss}

        record = stages.run(name, fit)
        load_checkpoint(path, {name: module})
        return record

    fits = {"world_model": fit_stage("world_model", world)}
    estimators: dict[str, UncertaintyEstimator] = {}
    for spec in cfg.estimators:
        est = build_estimator(spec, obs_dim, action_dim, window).to(device)
        fits[spec.name] = fit_stage(f"fit_{spec.name}", est)
        estimators[spec.name] = est.eval()
    world.eval()

    def evaluation_stage() -> dict:
        seed = stage_seed(cfg.seed, "evaluation")
        env = build_env(cfg, seed=seed, episode_steps=window + ev.horizon)
        trajectories = validation_trajectories(
            env, count=ev.trajectories, length=window + ev.horizon, seed=seed, policy=ev.policy
        )
        held_out = collect_random(env, frames=ev.ood_windows * window, seed=seed + 1)
        high = env.action_spec.high.to(torch.float32)
        env.close()
        windows = cut_sequences(held_out, window)
        out = {}
        for name, est in estimators.items():
            torch.manual_seed(seed)  # MC dropout draws its masks from the global RNG
            out[name] = calibration_metrics(
                world,
                est,
                trajectories,
                windows,
                window=window,
                scale=scale,
                state_shift=ev.ood_state_shift,
                action_high=high,
            )
        return {"estimators": out, "trajectories": ev.trajectories, "ood_windows": len(windows)}

    evaluation = stages.run("evaluation", evaluation_stage)
    timing = stages.run("timing", lambda: _timing(cfg, world, estimators, data))

    outcomes: dict[str, dict[str, Any]] = {}
    for spec in cfg.estimators:
        outcomes[spec.name] = {}
        for kind in ("explore", "control"):
            if cfg.outcomes[f"{kind}_recipe"] is None:
                continue
            name = f"outcome_{spec.name}_{kind}"
            record = stages.run(
                name,
                lambda spec=spec, kind=kind: {
                    "result": _outcome(cfg, spec, kind, Path(run_dir), cfg.seed)
                },
            )
            outcomes[spec.name][kind] = record["result"]

    reference = next(
        (s.name for s in cfg.estimators if s.kind == "reconstruction"), cfg.estimators[0].name
    )
    table = {}
    for spec in cfg.estimators:
        row = dict(evaluation["estimators"][spec.name])
        row["kind"] = spec.kind
        row["config"] = OmegaConf.to_container(spec, resolve=True)
        row["fit_val_loss"] = fits[spec.name]["val_loss"]
        row["fit_wall_time_s"] = fits[spec.name]["wall_time_s"]
        for horizon in cfg.timing.horizons:
            t = timing[f"H{horizon}"]
            row[f"score_ms_H{horizon}"] = t[spec.name]["score_ms"]
            row[f"cem_ms_H{horizon}"] = t[spec.name]["cem_ms"]
            row[f"score_ratio_H{horizon}"] = t[spec.name]["score_ms"] / t[reference]["score_ms"]
            row[f"cem_ratio_H{horizon}"] = t[spec.name]["cem_ms"] / t[reference]["cem_ms"]
        row["outcomes"] = outcomes[spec.name]
        row.update(_flat_outcomes(outcomes[spec.name]))
        table[spec.name] = row
    return {
        "experiment": "calibrate",
        "env": cfg.env.name,
        "seed": cfg.seed,
        "reference_estimator": reference,
        "horizons": list(cfg.timing.horizons),
        "mse_units": "squared multi-step prediction error per state dim divided by its standard "
        "deviation in the random data, averaged over the imagined steps",
        "estimators": table,
        "world_model_val_loss": fits["world_model"]["val_loss"],
        "timing": timing,
        "wall_time_s": dict(stages.wall_time_s),
    }
