"""The exploration experiment (active vs random, the paper's §3.2 and Table 1) as an
:class:`~torchrl_recon.experiments.experiment_type.ExperimentType`: its stages
(:mod:`.explore_stages`), summary across seeds, tables, figures and headline numbers."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

from torchrl_recon.evaluation.significance import significance
from torchrl_recon.experiments import explore_stages
from torchrl_recon.experiments.config import ExploreConfig
from torchrl_recon.experiments.experiment_type import ExperimentType, Figures
from torchrl_recon.experiments.plots import plot_table1
from torchrl_recon.experiments.recipe_checks import explore_errors
from torchrl_recon.experiments.stats import mean_std, paired_tests
from torchrl_recon.experiments.tables import fmt, pm, render


def summarize_env(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Table 1 across seeds of one env: per seed, the arm means over retrainings; across seeds,
    mean ± sample std of those means for each arm, the ratio active / random of the means, a
    paired t-test (``scipy.stats.ttest_rel``, from 2 seeds) and a Wilcoxon signed-rank test
    (``scipy.stats.wilcoxon``, from 5 seeds); and ``significance``
    (:func:`~torchrl_recon.evaluation.significance.significance`): the mean per-seed ratio
    with its 95% bootstrap interval, the seeds in each direction, Cohen's d_z and how many seeds
    the observed spread needs to detect the paper's ratio."""
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    seeds = [r.get("seed") for r in runs]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"explore results of env {runs[0]['env']!r} repeat a seed: {seeds}")
    per_seed = {arm: [float(r["arms"][arm]["mean"]) for r in runs] for arm in ("random", "active")}
    arms = {}
    for arm, means in per_seed.items():
        mean, std = mean_std(means)
        pooled = [float(v) for r in runs for v in r["arms"][arm]["mse"]]
        arms[arm] = {
            "mean": mean,
            "std": std,
            "n_seeds": len(means),
            "std_all_retrainings": mean_std(pooled)[1],
            "n_retrainings": len(pooled),
        }
    random_mean, active_mean = arms["random"]["mean"], arms["active"]["mean"]
    ratio = active_mean / random_mean if random_mean else float("nan")
    tests = paired_tests(
        per_seed["active"],
        per_seed["random"],
        t_note="paired t-test across seeds of the per-seed arm means (active vs random)",
    )
    return {
        "seeds": seeds,
        "per_seed": {
            "random": per_seed["random"],
            "active": per_seed["active"],
            "ratio": [
                a / r if r else float("nan")
                for a, r in zip(per_seed["active"], per_seed["random"], strict=True)
            ],
            "within_seed_test": [r.get("test") for r in runs],
        },
        "arms": arms,
        "ratio": ratio,
        "tests": tests,
        "significance": significance(per_seed["active"], per_seed["random"], runs[0]["env"]),
        "mse_units": runs[0].get("mse_units", ""),
    }


def result_table(r: Mapping[str, Any]) -> str:
    """The table of one explore results dict: the arms over retrainings and their test."""
    arms = r["arms"]
    rows = [
        [arm, pm(arms[arm]["mean"], arms[arm]["std"]), str(len(arms[arm].get("mse", [])))]
        for arm in ("random", "active")
        if arm in arms
    ]
    text = [
        f"explore — {r.get('env')} seed {r.get('seed')}: validation MSE over retrainings",
        render(["arm", "MSE mean ± std", "retrainings"], rows),
        f"ratio active / random: {fmt(r.get('ratio'))}",
    ]
    test = r.get("test")
    if test:
        text.append(
            f"{test.get('name', 'test')}: statistic {fmt(test.get('statistic'))}, "
            f"p = {fmt(test.get('p_value'))}"
        )
    if r.get("mse_units"):
        text.append(f"MSE: {r['mse_units']}")
    return "\n".join(text)


def summary_table(r: Mapping[str, Any]) -> str:
    """Table 1 of an explore summary: one row per env (the arms, the ratio of their means, the
    mean per-seed ratio with its 95% bootstrap interval, the seeds where active is lower /
    higher, the paired tests and Cohen's d_z), then each env's power statement."""
    rows, power = [], []
    for env, s in r["envs"].items():
        t, w = s["tests"]["paired_t"], s["tests"]["wilcoxon"]
        sig = s.get("significance") or {}
        ci, sides = sig.get("ratio_ci") or {}, sig.get("directions") or {}
        rows.append(
            [
                env,
                str(len(s["seeds"])),
                pm(s["arms"]["random"]["mean"], s["arms"]["random"]["std"]),
                pm(s["arms"]["active"]["mean"], s["arms"]["active"]["std"]),
                fmt(s["ratio"], 3),
                f"{fmt(sig.get('mean_ratio'), 3)} [{fmt(ci.get('low'), 3)}, {fmt(ci.get('high'), 3)}]",
                f"{sides.get('active_lower', '-')}/{sides.get('active_higher', '-')}",
                fmt(t["p_value"], 3),
                fmt(w["p_value"], 3),
                fmt((sig.get("effect_size") or {}).get("cohens_dz"), 3),
            ]
        )
        if (sig.get("power") or {}).get("note"):
            power.append(f"power, {env}: {sig['power']['note']}")
    notes = sorted(
        {
            s["tests"][k]["note"]
            for s in r["envs"].values()
            for k in ("paired_t", "wilcoxon")
            if s["tests"][k]["note"].startswith("not computed")
        }
    )
    header = ["env", "seeds", "random", "active", "active/random", "mean ratio [95% CI]"]
    header += ["lower/higher", "t-test p", "Wilcoxon p", "d_z"]
    text = "Table 1 — validation MSE, mean ± std across seeds of the per-seed means\n" + render(
        header, rows
    )
    text += (
        "\nmean ratio: of the per-seed ratios, 95% percentile bootstrap over seeds (seeded);"
        " lower/higher: seeds where active is below / above random; d_z: Cohen's d of the"
        " per-seed differences active − random"
    )
    if power:
        text += "\n" + "\n".join(power)
    if notes:
        text += "\n" + "\n".join(f"note: {n}" for n in notes)
    return text


def headline(results: Mapping[str, Any]) -> dict[str, float]:
    """Arm means and stds, the ratio and the test's p-value."""
    scalars: dict[str, float] = {}
    for arm, stats in results.get("arms", {}).items():
        scalars[f"{arm}_mse_mean"] = stats["mean"]
        scalars[f"{arm}_mse_std"] = stats["std"]
    scalars["ratio"] = results.get("ratio", float("nan"))
    if results.get("test"):
        scalars["p_value"] = results["test"].get("p_value", float("nan"))
    return scalars


def outcome(results: Mapping[str, Any]) -> dict[str, Any]:
    """The numbers the estimator comparison keeps of an explore run."""
    return {
        "random_mse": results["arms"]["random"]["mean"],
        "active_mse": results["arms"]["active"]["mean"],
        "ratio": results["ratio"],
        "p_value": (results.get("test") or {}).get("p_value"),
        "active_feasible_fraction": (results.get("data") or {}).get("active_feasible_fraction"),
    }


def figures(results: Mapping[str, Any]) -> Figures:
    """``table1.png``."""
    return [("table1.png", plot_table1([results]))]


def summary_figures(summary: Mapping[str, Any], results: list[Mapping[str, Any]]) -> Figures:
    """``table1.png`` of all seeds."""
    return [("table1.png", plot_table1(results))]


def check(cfg, errors, recipes) -> None:
    """The explore recipe's own value checks."""
    explore_errors(cfg, errors)


def stage_values(cfg) -> dict:
    """``{arm}`` of the stage names: random or active."""
    return {"arm": explore_stages.ARMS}


EXPERIMENT = ExperimentType.of_module(
    sys.modules[__name__],
    explore_stages,
    name="explore",
    help="active vs random exploration: validation MSE of models fitted on each (§3.2, Table 1)",
    schema=ExploreConfig,
)
