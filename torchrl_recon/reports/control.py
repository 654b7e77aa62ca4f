"""The control experiment's report (uncertainty-aware MPC vs the cost-only baseline, the
paper's §3.1 and Fig. 3): its summary across seeds, tables, figures and headline numbers."""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from typing import Any

from torchrl_recon.evaluation.mpc import METRICS
from torchrl_recon.evaluation.significance import paired_tests, trend_test
from torchrl_recon.reports.plots import plot_control_errors, plot_trajectory
from torchrl_recon.reports.report import Figures, Report
from torchrl_recon.reports.stats import episode_mean_std, mean_std
from torchrl_recon.reports.tables import fmt, pm, render

TESTED = ("prediction_mse", "real_cost")
"""The metrics tested across seeds."""


def summarize_env(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per setting, mean ± sample std over all episodes of all seeds of one env (NaN values,
    from episodes without a planned step, are left out); and :func:`across_seeds`."""
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    seeds = [r.get("seed") for r in runs]
    names = list(dict.fromkeys(n for r in runs for n in r["settings"]))  # in order of appearance
    settings: dict[str, Any] = {}
    for name in names:
        records = [r["settings"].get(name, {}) for r in runs]
        episodes = [ep for record in records for ep in record.get("episodes", [])]
        mean, std = episode_mean_std(
            episodes, [m for m in METRICS if any(m in e for e in episodes)]
        )
        settings[name] = {
            "mean": mean,
            "std": std,
            "n_episodes": len(episodes),
            "ended_in_warmup": sum(record.get("ended_in_warmup", 0) for record in records),
            "seeds": [r.get("seed") for r in runs if name in r["settings"]],
        }
    if randoms := [x for r in runs for x in r.get("random_policy", {}).get("env_returns", [])]:
        mean, std = mean_std(randoms)
        settings["random policy"] = {
            "mean": {"env_return": mean},
            "std": {"env_return": std},
            "n_episodes": len(randoms),
        }
    return {"seeds": seeds, "settings": settings, "across_seeds": across_seeds(runs, names)}


def across_seeds(runs: Sequence[Mapping[str, Any]], names: Sequence[str]) -> dict[str, Any]:
    """Per setting the per-seed means of :data:`TESTED`, their mean ± std across seeds and paired
    tests against ``names[0]``; per metric, the trend test over the settings with an uncertainty
    band, from the lowest band to the highest.

    Examples:
        >>> runs = [{"seed": s, "settings": {
        ...     "baseline": {"episodes": [{"prediction_mse": 2.0 + s, "real_cost": 1.0}]},
        ...     "u_low": {"episodes": [{"prediction_mse": 1.0 + s, "real_cost": 1.0}]}}}
        ...     for s in range(3)]
        >>> out = across_seeds(runs, ["baseline", "u_low"])
        >>> out["settings"]["u_low"]["per_seed"]["prediction_mse"], out["reference"]
        ([1.0, 2.0, 3.0], 'baseline')
    """
    means = {
        name: {
            r["seed"]: episode_mean_std(r["settings"][name].get("episodes", []), TESTED)[0]
            for r in runs
            if name in r["settings"]
        }
        for name in names
    }
    per_seed = {m: {n: {s: v[m] for s, v in means[n].items()} for n in names} for m in TESTED}
    reference, settings = names[0], {}
    for name in names:
        seeds = sorted(per_seed[TESTED[0]][name])
        entry: dict[str, Any] = {"seeds": seeds, "per_seed": {}, "mean": {}, "std": {}}
        entry["vs_reference"] = {}
        for metric in TESTED:
            values, ref = per_seed[metric][name], per_seed[metric][reference]
            entry["per_seed"][metric] = [values[s] for s in seeds]
            entry["mean"][metric], entry["std"][metric] = mean_std(values.values())
            if name != reference:
                common = [s for s in seeds if s in ref]
                pairs = [values[s] for s in common], [ref[s] for s in common]
                entry["vs_reference"][metric] = paired_tests(*pairs)
        settings[name] = entry
    bands = {
        name: (float(band["low"]), float(band["high"]))
        for r in runs
        for name in names
        if (band := r["settings"].get(name, {}).get("band"))
    }
    order = sorted(bands, key=lambda n: bands[n])
    trend = {metric: trend_test(per_seed[metric], order) for metric in TESTED}
    return {"reference": reference, "settings": settings, "trend": trend}


def settings_table(title: str, settings: Mapping[str, Any]) -> str:
    """``title`` over one row per setting: its episodes (those that ended before their first
    plan, whose planned-step metrics are left out, in brackets) and mean ± std of each metric."""
    metrics = [m for m in METRICS if any(m in s.get("mean", {}) for s in settings.values())]
    rows = []
    for name, s in settings.items():
        n, unplanned = s.get("n_episodes") or len(s.get("episodes", [])), s.get("ended_in_warmup")
        n_text = f"{n} ({unplanned} in warm-up)" if unplanned else str(n)
        rows.append([name, n_text] + [pm(s["mean"].get(m), s["std"].get(m)) for m in metrics])
    return render(["setting", "episodes", *metrics], rows, title)


def result_table(r: Mapping[str, Any]) -> str:
    """The table of one control results dict."""
    title = (
        f"control — {r.get('env')} seed {r.get('seed')}: mean ± std over episodes"
        f" (re-plan threshold {fmt(r.get('replan_threshold'))}"
        + (f", warm-up {r['warmup']})" if r.get("warmup") else ")")
    )
    settings = dict(r["settings"])
    if "random_policy" in r:
        random = r["random_policy"]
        settings["random policy"] = random | {"n_episodes": len(random["env_returns"])}
    return settings_table(title, settings)


def seeds_table(env: str, seeds: Mapping[str, Any]) -> str:
    """The across-seed table of one env: per setting and tested metric, mean ± std across the
    per-seed means and the paired p-values against the reference; then the trend tests."""
    ref, rows, header = seeds["reference"], [], ["setting", "seeds"]
    for metric in TESTED:
        header += [f"{metric} across seeds", f"t p vs {ref}", f"W p vs {ref}"]
    for name, s in seeds["settings"].items():
        row = [name, str(len(s["seeds"]))]
        for metric in TESTED:
            tests = s["vs_reference"].get(metric, {})
            p = [fmt((tests.get(k) or {}).get("p_value"), 3) for k in ("paired_t", "wilcoxon")]
            row += [pm(s["mean"][metric], s["std"][metric]), *p]
        rows.append(row)
    title = f"control — {env}: per-seed means, mean ± std across seeds (tests paired by seed)"
    lines = [render(header, rows, title)]
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
    settings = results.get("settings", {})
    return {f"{n}/{k}": v for n, s in settings.items() for k, v in s.get("mean", {}).items()}


def outcome(results: Mapping[str, Any]) -> dict[str, Any]:
    """The numbers calibrate keeps of a control run: per setting, the means."""
    keys = ("prediction_mse", "cost_error", "real_cost", "replans")
    return {name: {k: s["mean"][k] for k in keys} for name, s in results["settings"].items()}


def figures(results: Mapping[str, Any]) -> Figures:
    """``control_errors.png`` and, when the results hold a trajectory example, ``trajectory.png``."""
    out = [("control_errors.png", plot_control_errors(results))]
    if (example := results.get("trajectory_example")) and len(example.get("real", [])) > 0:
        out.append(("trajectory.png", plot_trajectory(example)))
    return out


def summary_figures(summary: Mapping[str, Any], results: list[Mapping[str, Any]]) -> Figures:
    """``control_errors_<env>.png`` for each env of the summary, with each seed's mean as a dot."""
    envs = summary["envs"].items()
    return [
        (f"control_errors_{env}.png", plot_control_errors({"env": env, **s})) for env, s in envs
    ]


REPORT = Report.of_module(sys.modules[__name__], "control")
