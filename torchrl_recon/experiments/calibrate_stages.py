"""The stages of the calibrate experiment: uncertainty estimators side by side on calibration,
out-of-distribution detection, cost, and the outcome of the two experiments with each.

Stages (each resumable): ``random_data`` → ``world_model`` → ``fit_<estimator>`` for each →
``evaluation`` (rank correlation with the world model's real error on imagined held-out
trajectories, AUROC for "error above its median", OOD AUROC) → ``timing`` (scoring K × H
windows and one CEM call, as ratios to the first ``reconstruction`` estimator) →
``outcome_<estimator>_{explore,control}`` (the two experiments at a reduced scale, each in its
own run directory under ``outcomes/``, run through the context's ``run_child``). Each stage
takes the :class:`~torchrl_recon.experiments.context.RunContext`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_recon.collectors import collect_random, validation_trajectories
from torchrl_recon.data import cut_sequences
from torchrl_recon.envs import close_env
from torchrl_recon.evaluation import auroc, imagined_uncertainty_and_error, spearman
from torchrl_recon.experiments.common import (
    build_env,
    build_estimator,
    build_world_model,
    cost_fn,
    fit_stage,
    random_data_stage,
    state_scale,
)
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.modules import LSTMWorldModel, UncertaintyEstimator, module_device
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.timing import interleaved_median_ms


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


def timing(
    cfg: DictConfig, world: LSTMWorldModel, estimators: dict[str, UncertaintyEstimator], data
) -> dict[str, Any]:
    """Scoring and CEM planning time per estimator (and CEM without u), per horizon, interleaved
    (stage ``timing``); on a CUDA device each call is timed until the device is done."""
    t, window = cfg.timing, cfg.models.window
    device = module_device(world)
    score = torch.no_grad()(lambda est, x: est.score_sequence(x))
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
            model = PlanningModel(world, cost, uncertainty=est)
            planner = CEMPlanner(model, Objective(beta=0.1), horizon=horizon, **cem)
            fns[f"{name}/score"] = lambda e=est, x=x: score(e, x)
            fns[f"{name}/cem"] = lambda p=planner: p.plan(*ctx)
        times = interleaved_median_ms(fns, t.repeats, device=device)
        row: dict[str, Any] = {"cem_without_u_ms": times["cem_without_u"]}
        for name in estimators:
            row[name] = {"score_ms": times[f"{name}/score"], "cem_ms": times[f"{name}/cem"]}
        out[f"H{horizon}"] = row
    return out


STAGES = ("random_data", "world_model", "fit_{estimator}", "evaluation", "timing")
STAGES += ("outcome_{estimator}_{kind}",)
"""Stage name templates, in run order (``{estimator}`` an estimator's name, ``{kind}`` explore
or control)."""
OUTCOME_KINDS = ("explore", "control")


def outcome_config(ctx: RunContext, spec: DictConfig, kind: str) -> DictConfig:
    """The ``kind`` recipe of ``outcomes`` with ``spec`` as its estimator, this run's seed,
    threads and window, its run directory ``outcomes/<estimator>/<kind>``."""
    cfg = ctx.cfg
    sub = ctx.recipes.load(
        ctx.recipes.resolve(cfg.outcomes[f"{kind}_recipe"]), list(cfg.outcomes[f"{kind}_overrides"])
    )
    sub.seed, sub.threads, sub.progress = cfg.seed, cfg.threads, False
    sub.output_dir = str(ctx.run_dir / "outcomes" / spec.name / kind)
    sub.logger.backend = "none"
    sub.models.window = cfg.models.window
    for key in ("kind", "hidden_size", "activation"):
        sub.models.uncertainty[key] = spec[key]
    sub.models.uncertainty.kwargs = OmegaConf.to_container(spec.kwargs, resolve=True)
    return sub


def _flat_outcomes(outcomes: dict[str, Any]) -> dict[str, float]:
    """``explore_ratio`` and ``control_<setting>_<metric>``: the outcomes as top-level numbers."""
    flat = {}
    if outcomes.get("explore"):
        flat["explore_ratio"] = outcomes["explore"]["ratio"]
    for setting, metrics in (outcomes.get("control") or {}).items():
        for key, value in metrics.items():
            flat[f"control_{setting}_{key}"] = value
    return flat


def fit_stages(
    ctx: RunContext, data
) -> tuple[LSTMWorldModel, dict[str, UncertaintyEstimator], dict[str, dict]]:
    """Fit the world model (stage ``world_model``) and each estimator (``fit_<name>``) on
    ``data``; returns them (in eval mode) and their stage records."""
    cfg = ctx.cfg
    obs_dim, action_dim = data["observation"].shape[-1], data["action"].shape[-1]
    world = build_world_model(cfg, obs_dim, action_dim).to(ctx.device)
    fits = {"world_model": fit_stage(ctx, "world_model", data, {"world_model": world})}
    estimators: dict[str, UncertaintyEstimator] = {}
    for spec in cfg.estimators:
        est = build_estimator(spec, obs_dim, action_dim, cfg.models.window).to(ctx.device)
        name = f"fit_{spec.name}"
        fits[spec.name] = fit_stage(ctx, name, data, {name: est})
        estimators[spec.name] = est.eval()
    world.eval()
    return world, estimators, fits


def evaluation_stage(
    ctx: RunContext, world: LSTMWorldModel, estimators: dict[str, UncertaintyEstimator], scale
) -> dict:
    """:func:`calibration_metrics` of each estimator on held-out trajectories and windows
    (stage ``evaluation``)."""
    cfg, ev = ctx.cfg, ctx.cfg.evaluation
    window = cfg.models.window

    def run() -> dict:
        seed = ctx.stage_seed("evaluation")
        env = build_env(cfg, seed=seed, episode_steps=window + ev.horizon)
        trajectories = validation_trajectories(
            env, count=ev.trajectories, length=window + ev.horizon, seed=seed, policy=ev.policy
        )
        held_out = collect_random(env, frames=ev.ood_windows * window, seed=seed + 1)
        high = env.action_spec.high.to(torch.float32)
        close_env(env)
        windows = cut_sequences(held_out, window)
        kw = dict(window=window, scale=scale, state_shift=ev.ood_state_shift, action_high=high)
        out = {}
        for name, est in estimators.items():
            torch.manual_seed(seed)  # MC dropout draws its masks from the global RNG
            out[name] = calibration_metrics(world, est, trajectories, windows, **kw)
        return {"estimators": out, "trajectories": ev.trajectories, "ood_windows": len(windows)}

    return ctx.stages.run("evaluation", run)


def outcome_stages(ctx: RunContext) -> dict[str, dict[str, Any]]:
    """The two experiments with each estimator (stages ``outcome_<estimator>_<kind>``), run
    through ``ctx.run_child``; their headline numbers."""
    cfg = ctx.cfg

    def outcome(spec: DictConfig, kind: str) -> dict:
        return {"result": ctx.run_child(outcome_config(ctx, spec, kind))}

    outcomes: dict[str, dict[str, Any]] = {}
    for spec in cfg.estimators:
        outcomes[spec.name] = {}
        for kind in OUTCOME_KINDS:
            if cfg.outcomes[f"{kind}_recipe"] is None:
                continue
            if ctx.run_child is None or ctx.recipes is None:
                raise ValueError(
                    "calibrate's outcomes run other recipes: run it through "
                    "torchrl_recon.experiments.runner.run (or set outcomes.*_recipe to null)."
                )
            record = ctx.stages.run(f"outcome_{spec.name}_{kind}", partial(outcome, spec, kind))
            outcomes[spec.name][kind] = record["result"]
    return outcomes


def calibrate_results(
    ctx: RunContext, fits: dict, evaluation: dict, times: dict, outcomes: dict
) -> dict[str, Any]:
    """The results dict: one row per estimator, times as ratios to the reference estimator."""
    cfg = ctx.cfg
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
            t = times[f"H{horizon}"]
            row[f"score_ms_H{horizon}"] = t[spec.name]["score_ms"]
            row[f"cem_ms_H{horizon}"] = t[spec.name]["cem_ms"]
            row[f"score_ratio_H{horizon}"] = t[spec.name]["score_ms"] / t[reference]["score_ms"]
            row[f"cem_ratio_H{horizon}"] = t[spec.name]["cem_ms"] / t[reference]["cem_ms"]
        row["outcomes"] = outcomes[spec.name]
        row.update(_flat_outcomes(outcomes[spec.name]))
        table[spec.name] = row
    return {
        **ctx.results_header(),
        "reference_estimator": reference,
        "horizons": list(cfg.timing.horizons),
        "mse_units": "squared multi-step prediction error per state dim divided by its standard "
        "deviation in the random data, averaged over the imagined steps",
        "estimators": table,
        "world_model_val_loss": fits["world_model"]["val_loss"],
        "timing": times,
        "wall_time_s": dict(ctx.stages.wall_time_s),
    }


def run(ctx: RunContext) -> dict[str, Any]:
    """Run (or resume) the calibrate experiment; return its results."""
    cfg = ctx.cfg
    data = random_data_stage(
        ctx, "random_data", frames=cfg.random_steps, episode_steps=cfg.random_episode_steps
    )
    scale = state_scale(data)
    world, estimators, fits = fit_stages(ctx, data)
    evaluation = evaluation_stage(ctx, world, estimators, scale)
    times = ctx.stages.run("timing", lambda: timing(cfg, world, estimators, data))
    return calibrate_results(ctx, fits, evaluation, times, outcome_stages(ctx))
