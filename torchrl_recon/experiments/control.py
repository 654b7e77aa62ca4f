"""The control experiment (uncertainty-aware MPC vs the cost-only baseline, the paper's §3.1
and Fig. 3) as an :class:`~torchrl_recon.experiments.experiment_type.ExperimentType`: its
stages (:mod:`.control_stages`), summary across seeds, tables, figures and headline numbers."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

from torchrl_recon.experiments import control_stages
from torchrl_recon.experiments.config import ControlConfig, ControlSetting
from torchrl_recon.experiments.control_seeds import TESTED, across_seeds
from torchrl_recon.experiments.control_stages import METRICS, episode_mean_std
from torchrl_recon.experiments.experiment_type import ExperimentType, Figures
from torchrl_recon.experiments.plots import plot_control_errors, plot_trajectory
from torchrl_recon.experiments.recipe_checks import control_errors
from torchrl_recon.experiments.stats import mean_std
from torchrl_recon.experiments.tables import fmt, pm, render


def summarize_env(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per setting, mean ± sample std over all episodes of all seeds of one env (NaN values,
    from episodes without a planned step, are left out); and ``across_seeds``: the per-seed
    means with paired tests against the first setting and a trend test over the u bands
    (:func:`~torchrl_recon.experiments.control_seeds.across_seeds`)."""
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    seeds = [r.get("seed") for r in runs]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"control results of env {runs[0]['env']!r} repeat a seed: {seeds}")
    names = list(dict.fromkeys(n for r in runs for n in r["settings"]))  # in order of appearance
    settings: dict[str, Any] = {}
    for name in names:
        episodes = [ep for r in runs for ep in r["settings"].get(name, {}).get("episodes", [])]
        metrics = [m for m in METRICS if any(m in ep for ep in episodes)]
        mean, std = episode_mean_std(episodes, metrics)
        settings[name] = {
            "mean": mean,
            "std": std,
            "n_episodes": len(episodes),
            "ended_in_warmup": sum(
                r["settings"].get(name, {}).get("ended_in_warmup", 0) for r in runs
            ),
            "seeds": [r.get("seed") for r in runs if name in r["settings"]],
        }
    randoms = [x for r in runs for x in r.get("random_policy", {}).get("env_returns", [])]
    if randoms:
        mean, std = mean_std(randoms)
        settings["random policy"] = {
            "mean": {"env_return": mean},
            "std": {"env_return": std},
            "n_episodes": len(randoms),
        }
    return {"seeds": seeds, "settings": settings, "across_seeds": across_seeds(runs, names)}


def settings_table(title: str, settings: Mapping[str, Any]) -> str:
    """``title`` over one row per setting: its episodes (those that ended before their first
    plan, whose planned-step metrics are left out, in brackets) and mean ± std of each metric."""
    metrics = [m for m in METRICS if any(m in s.get("mean", {}) for s in settings.values())]
    rows = []
    for name, s in settings.items():
        n = s.get("n_episodes") or len(s.get("episodes", []))
        unplanned = s.get("ended_in_warmup")
        n_text = f"{n} ({unplanned} in warm-up)" if unplanned else str(n)
        rows.append([name, n_text] + [pm(s["mean"].get(m), s["std"].get(m)) for m in metrics])
    return title + "\n" + render(["setting", "episodes", *metrics], rows)


def result_table(r: Mapping[str, Any]) -> str:
    """The table of one control results dict."""
    title = (
        f"control — {r.get('env')} seed {r.get('seed')}: mean ± std over episodes"
        f" (re-plan threshold {fmt(r.get('replan_threshold'))})"
    )
    settings = dict(r["settings"])
    if "random_policy" in r:
        settings["random policy"] = r["random_policy"] | {
            "n_episodes": len(r["random_policy"]["env_returns"])
        }
    return settings_table(title, settings)


def seeds_table(env: str, seeds: Mapping[str, Any]) -> str:
    """The across-seed table of one env: per setting and tested metric, mean ± std across the
    per-seed means and the paired p-values against the reference; then the trend tests."""
    ref = seeds["reference"]
    rows = []
    for name, s in seeds["settings"].items():
        row = [name, str(len(s["seeds"]))]
        for metric in TESTED:
            tests = s["vs_reference"].get(metric, {})
            row += [
                pm(s["mean"][metric], s["std"][metric]),
                fmt((tests.get("paired_t") or {}).get("p_value"), 3),
                fmt((tests.get("wilcoxon") or {}).get("p_value"), 3),
            ]
        rows.append(row)
    header = ["setting", "seeds"]
    for metric in TESTED:
        header += [f"{metric} across seeds", f"t p vs {ref}", f"W p vs {ref}"]
    lines = [
        f"control — {env}: per-seed means, mean ± std across seeds (tests paired by seed)",
        render(header, rows),
    ]
    for metric, trend in seeds["trend"].items():
        test = f"L = {fmt(trend.get('statistic'))}, p = {fmt(trend.get('p_value'), 3)}"
        found = f"{' < '.join(trend['order'])}: {test}" if "order" in trend else trend["note"]
        lines.append(f"trend over the u bands ({metric}): {found}")
    return "\n".join(lines)


def summary_table(r: Mapping[str, Any]) -> str:
    """Per env of a control summary: the table over all episodes, then the across-seed one."""
    parts = []
    for env, s in r["envs"].items():
        title = f"control — {env}, seeds {s['seeds']}: mean ± std over all episodes"
        parts.append(settings_table(title, s["settings"]))
        if s.get("across_seeds"):
            parts.append(seeds_table(env, s["across_seeds"]))
    return "\n\n".join(parts)


def headline(results: Mapping[str, Any]) -> dict[str, float]:
    """Each setting's mean of each metric, as ``<setting>/<metric>``."""
    return {
        f"{name}/{key}": value
        for name, s in results.get("settings", {}).items()
        for key, value in s.get("mean", {}).items()
    }


def outcome(results: Mapping[str, Any]) -> dict[str, Any]:
    """The numbers calibrate keeps of a control run: per setting, the means."""
    return {
        name: {k: s["mean"][k] for k in ("prediction_mse", "cost_error", "real_cost", "replans")}
        for name, s in results["settings"].items()
    }


def figures(results: Mapping[str, Any]) -> Figures:
    """``control_errors.png`` and, when the results hold a trajectory example, ``trajectory.png``."""
    out = [("control_errors.png", plot_control_errors(results))]
    example = results.get("trajectory_example")
    if example and len(example.get("real", [])) > 0:
        out.append(("trajectory.png", plot_trajectory(example)))
    return out


def summary_figures(summary: Mapping[str, Any], results: list[Mapping[str, Any]]) -> Figures:
    """``control_errors_<env>.png`` for each env of the summary, with each seed's mean as a dot."""
    figures = []
    for env, s in summary["envs"].items():
        seeds = (s.get("across_seeds") or {}).get("settings", {})
        settings = {
            name: {**entry, "per_seed": seeds.get(name, {}).get("per_seed", {})}
            for name, entry in s["settings"].items()
        }
        figure = plot_control_errors({"env": env, **s, "settings": settings})
        figures.append((f"control_errors_{env}.png", figure))
    return figures


def check(cfg, errors, recipes) -> None:
    """The control recipe's own value checks."""
    control_errors(cfg, errors)


def stage_values(cfg) -> dict:
    """``{setting}`` of the stage names: the recipe's settings."""
    return {"setting": [s.name for s in cfg.settings]}


EXPERIMENT = ExperimentType.of_module(
    sys.modules[__name__],
    control_stages,
    name="control",
    help="uncertainty-aware MPC vs the cost-only baseline: prediction and cost errors (§3.1, Fig. 3)",
    schema=ControlConfig,
    list_field=("settings", ControlSetting),
)
