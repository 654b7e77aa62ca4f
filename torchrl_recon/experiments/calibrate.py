"""The calibrate experiment (its resumable :data:`STAGES`, recipe check and ``EXPERIMENT``):
uncertainty estimators side by side on calibration, out-of-distribution detection, cost, and
the outcome of the two experiments with each (:func:`outcome_stages`)."""

from __future__ import annotations

import itertools
import sys
from functools import partial
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_recon.collectors import EpisodesTooShort, collect_random, validation_trajectories
from torchrl_recon.data import cut_sequences, long_trajectories
from torchrl_recon.envs import closing_env
from torchrl_recon.errors import RecipeError
from torchrl_recon.evaluation import calibration_metrics
from torchrl_recon.experiments.config import CalibrateConfig, EstimatorSpec
from torchrl_recon.experiments.context import RecipeLoader, RunContext
from torchrl_recon.experiments.experiment_type import ExperimentType
from torchrl_recon.experiments.fit_stages import fit_stage
from torchrl_recon.experiments.random_data import random_data_stage
from torchrl_recon.experiments.recipe_checks import (
    RecipeErrors,
    data_errors,
    duplicate_errors,
    estimator_errors,
)
from torchrl_recon.experiments.recipe_env import build_env, cost_fn
from torchrl_recon.experiments.recipe_models import build_estimator, build_world_model, dims
from torchrl_recon.experiments.report_units import state_scale
from torchrl_recon.modules import LSTMWorldModel, UncertaintyEstimator, module_device
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.runs.timing import interleaved_median_ms

STAGES = ("random_data", "world_model", "fit_{estimator}", "evaluation", "timing")
STAGES += ("outcome_{estimator}_{kind}",)
"""Stage name templates, in run order (``{kind}`` explore or control)."""
OUTCOME_KINDS = ("explore", "control")


def timing(
    cfg: DictConfig, world: LSTMWorldModel, estimators: dict[str, UncertaintyEstimator], data
) -> dict[str, Any]:
    """Stage ``timing``: scoring K × H windows and one CEM call per estimator (and CEM without
    u), per horizon, interleaved; on a CUDA device each call is timed until the device is done."""
    t, window, device = cfg.timing, cfg.models.window, module_device(world)
    seqs = cut_sequences(data, window + 1).to(device)
    ctx = (seqs["observation"][0, :window], seqs["action"][0, :window], seqs["observation"][0, -1])
    features = torch.cat([data["observation"], data["action"]], -1).to(device)
    loc, spread = features.mean(0), features.std(0)
    cost = cost_fn(cfg)
    cem = dict(num_candidates=t.candidates, iterations=t.iterations, num_elites=t.num_elites)
    out: dict[str, Any] = {"threads": torch.get_num_threads(), "candidates": t.candidates}
    for horizon in t.horizons:
        generator = torch.Generator().manual_seed(horizon)
        x = loc + spread * torch.randn(
            t.candidates, window - 1 + horizon, features.shape[-1], generator=generator
        ).to(device)
        plain = CEMPlanner(PlanningModel(world, cost), Objective(), horizon=horizon, **cem)
        fns = {"cem_without_u": partial(plain.plan, *ctx)}
        for name, est in estimators.items():
            model = PlanningModel(world, cost, uncertainty=est)
            planner = CEMPlanner(model, Objective(beta=0.1), horizon=horizon, **cem)
            fns[f"{name}/score"] = partial(torch.no_grad()(est.score_sequence), x)
            fns[f"{name}/cem"] = partial(planner.plan, *ctx)
        times = interleaved_median_ms(fns, t.repeats, device=device)
        out[f"H{horizon}"] = {"cem_without_u_ms": times["cem_without_u"]} | {
            name: {"score_ms": times[f"{name}/score"], "cem_ms": times[f"{name}/cem"]}
            for name in estimators
        }
    return out


def fit_stages(
    ctx: RunContext, data
) -> tuple[LSTMWorldModel, dict[str, UncertaintyEstimator], dict[str, dict]]:
    """Stages ``world_model`` and ``fit_<name>``: the world model and each estimator fitted on
    ``data``; returns them (in eval mode) and their stage records."""
    world = build_world_model(ctx.cfg, *dims(data)).to(ctx.device)
    fits = {"world_model": fit_stage(ctx, "world_model", data, {"world_model": world})}
    estimators: dict[str, UncertaintyEstimator] = {}
    for spec in ctx.cfg.estimators:
        est = build_estimator(spec, *dims(data), ctx.cfg.models.window).to(ctx.device)
        name = f"fit_{spec.name}"
        fits[spec.name] = fit_stage(ctx, name, data, {name: est})
        estimators[spec.name] = est.eval()
    return world.eval(), estimators, fits


def short_episodes_error(cfg: DictConfig, found: str) -> RecipeError:
    """Why the evaluation cannot run on an env whose episodes end before its held-out
    trajectories of ``models.window + evaluation.horizon`` steps (``found`` says what was seen),
    and the keys to change.

    Examples:
        >>> cfg = OmegaConf.create({"env": {"name": "Short-v0"}, "models": {"window": 5},
        ...     "evaluation": {"horizon": 10}})
        >>> print(short_episodes_error(cfg, "no random episode lasted 15 steps"))  # doctest: +ELLIPSIS
        calibrate on Short-v0: the evaluation imagines evaluation.horizon = 10 steps after a real context of models.window = 5 steps, ...
    """
    h, w = cfg.evaluation.horizon, cfg.models.window
    return RecipeError(
        f"calibrate on {cfg.env.name}: the evaluation imagines evaluation.horizon = {h} steps "
        f"after a real context of models.window = {w} steps, on held-out trajectories of "
        f"{w + h} steps that the env must not end; {found}: lower models.window + "
        "evaluation.horizon to what most episodes last, or study this env with the control or "
        "online kinds, which run on episodes that end early."
    )


def evaluation_stage(
    ctx: RunContext, world: LSTMWorldModel, estimators: dict[str, UncertaintyEstimator], scale
) -> dict:
    """Stage ``evaluation``: :func:`~torchrl_recon.evaluation.calibration_metrics` of each
    estimator on held-out trajectories and windows."""
    cfg, ev, window = ctx.cfg, ctx.cfg.evaluation, ctx.cfg.models.window

    def run() -> dict:
        seed, length = ctx.stage_seed("evaluation"), window + ev.horizon
        with closing_env(build_env(cfg, seed=seed, episode_steps=length)) as env:
            try:
                trajectories = validation_trajectories(
                    env, count=ev.trajectories, length=length, seed=seed, policy=ev.policy
                )
            except EpisodesTooShort as err:
                found = f"only {err.done} of {err.attempts} attempts lasted {length} steps"
                found += f" (median {err.median}, longest {err.longest})"
                raise short_episodes_error(cfg, found) from None
            held_out = collect_random(env, frames=ev.ood_windows * window, seed=seed + 1)
            high = env.action_spec.high.to(torch.float32)
        windows = cut_sequences(held_out, window)
        kw = dict(window=window, scale=scale, state_shift=ev.ood_state_shift, action_high=high)
        out = {}
        for name, est in estimators.items():
            torch.manual_seed(seed)  # MC dropout draws its masks from the global RNG
            out[name] = calibration_metrics(world, est, trajectories, windows, **kw)
        return {"estimators": out, "trajectories": ev.trajectories, "ood_windows": len(windows)}

    return ctx.stages.run("evaluation", run)


def outcome_stages(ctx: RunContext) -> dict[str, dict[str, Any]]:
    """Stages ``outcome_<estimator>_<kind>``: the ``outcomes`` recipe of each kind with each
    estimator (this run's seed, threads and window; run directory ``outcomes/<estimator>/<kind>``),
    run through ``ctx.run_child``; their headline numbers."""
    cfg = ctx.cfg
    kinds = [k for k in OUTCOME_KINDS if cfg.outcomes[f"{k}_recipe"] is not None]
    if kinds and (ctx.run_child is None or ctx.recipes is None):
        raise ValueError(
            "calibrate's outcomes run other recipes: run it through "
            "torchrl_recon.experiments.runner.run (or set outcomes.*_recipe to null)."
        )

    def outcome(spec: DictConfig, kind: str) -> dict:
        recipe = ctx.recipes.resolve(cfg.outcomes[f"{kind}_recipe"])
        sub = ctx.recipes.load(recipe, list(cfg.outcomes[f"{kind}_overrides"]))
        sub.seed, sub.threads, sub.progress = cfg.seed, cfg.threads, False
        sub.output_dir = str(ctx.run_dir / "outcomes" / spec.name / kind)
        sub.logger.backend, sub.models.window = "none", cfg.models.window
        for key in ("kind", "hidden_size", "activation"):
            sub.models.uncertainty[key] = spec[key]
        sub.models.uncertainty.kwargs = OmegaConf.to_container(spec.kwargs, resolve=True)
        return {"result": ctx.run_child(sub)}

    outcomes: dict[str, dict[str, Any]] = {spec.name: {} for spec in cfg.estimators}
    for spec, kind in itertools.product(cfg.estimators, kinds):
        record = ctx.stages.run(f"outcome_{spec.name}_{kind}", lambda s=spec, k=kind: outcome(s, k))
        outcomes[spec.name][kind] = record["result"]
    return outcomes


def run(ctx: RunContext) -> dict[str, Any]:
    """Run (or resume) the calibrate experiment; return its results: one row per estimator,
    times as ratios to the first ``reconstruction`` estimator (else the first)."""
    cfg = ctx.cfg
    data = random_data_stage(
        ctx, "random_data", frames=cfg.random_steps, episode_steps=cfg.random_episode_steps
    )
    length = cfg.models.window + cfg.evaluation.horizon  # refused before any fit, if it can be
    if length <= cfg.random_episode_steps and long_trajectories(data, length) == 0:
        raise short_episodes_error(cfg, f"no random episode lasted {length} steps")
    scale = state_scale(data)
    world, estimators, fits = fit_stages(ctx, data)
    evaluation = evaluation_stage(ctx, world, estimators, scale)
    times = ctx.stages.run("timing", lambda: timing(cfg, world, estimators, data))
    outcomes = outcome_stages(ctx)
    reference = next(
        (s.name for s in cfg.estimators if s.kind == "reconstruction"), cfg.estimators[0].name
    )
    table = {}
    for spec in cfg.estimators:
        row = table[spec.name] = dict(evaluation["estimators"][spec.name])
        row |= {"kind": spec.kind, "config": OmegaConf.to_container(spec, resolve=True)}
        fit = fits[spec.name]
        row |= {"fit_val_loss": fit["val_loss"], "fit_wall_time_s": fit["wall_time_s"]}
        for h in cfg.timing.horizons:
            mine, ref = times[f"H{h}"][spec.name], times[f"H{h}"][reference]
            row |= {f"{m}_ms_H{h}": mine[f"{m}_ms"] for m in ("score", "cem")}
            row |= {f"{m}_ratio_H{h}": mine[f"{m}_ms"] / ref[f"{m}_ms"] for m in ("score", "cem")}
        row["outcomes"] = found = outcomes[spec.name]
        if found.get("explore"):
            row["explore_ratio"] = found["explore"]["ratio"]
        for setting, metrics in (found.get("control") or {}).items():
            row |= {f"control_{setting}_{key}": value for key, value in metrics.items()}
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


def check(cfg: DictConfig, errors: RecipeErrors, recipes: RecipeLoader | None) -> None:
    """The estimator comparison recipe's own checks; its outcome recipes are loaded (and so
    checked, with this recipe's window) with ``recipes`` when given."""
    duplicate_errors(errors, "estimators", "estimator")
    for i, spec in enumerate(cfg.estimators):
        estimator_errors(errors, f"estimators[{i}]", spec)
    data_errors(errors, "random_episode_steps", "random_steps")
    for kind in OUTCOME_KINDS:
        recipe, key = cfg.outcomes[f"{kind}_recipe"], f"outcomes.{kind}_recipe"
        if recipe is None or recipes is None:
            continue
        try:
            path = recipes.resolve(recipe)
        except FileNotFoundError as e:
            errors.append(f"'{key}': {e}")
            continue
        overrides, window = list(cfg.outcomes[f"{kind}_overrides"]), cfg.models.window
        try:
            recipes.load(path, [*overrides, f"models.window={window}"])
        except (RecipeError, FileNotFoundError) as e:
            errors.append(
                f"'{key}' (with outcomes.{kind}_overrides {overrides} and this recipe's "
                f"models.window = {window}): {e}"
            )


def stage_values(cfg: DictConfig) -> dict:
    """``{estimator}`` and ``{kind}`` of the stage names."""
    return {"estimator": [s.name for s in cfg.estimators], "kind": OUTCOME_KINDS}


EXPERIMENT = ExperimentType.of_module(
    sys.modules[__name__],
    name="calibrate",
    help="uncertainty estimators side by side: error ranking, OOD detection, cost, outcomes",
    schema=CalibrateConfig,
    list_field=("estimators", EstimatorSpec),
)
