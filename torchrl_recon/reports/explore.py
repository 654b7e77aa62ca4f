"""The exploration experiment's report (active vs random, the paper's §3.2 and Table 1): its
summary across seeds, tables, figures and headline numbers."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

from torchrl_recon.evaluation.significance import paired_tests, significance
from torchrl_recon.reports.plots import plot_table1
from torchrl_recon.reports.report import Figures, Report
from torchrl_recon.reports.stats import mean_std
from torchrl_recon.reports.tables import fmt, pm, render

ARMS = ("random", "active")
"""The arms of an explore run, in the order they are fitted."""


def _ratio(active: float, random: float) -> float:
    return active / random if random else float("nan")


def summarize_env(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Table 1 across seeds of one env: each arm's mean ± sample std of the per-seed means, their
    ratio, and the tests and :func:`~torchrl_recon.evaluation.significance.significance` of the
    per-seed pairs."""
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    seeds = [r.get("seed") for r in runs]
    per_seed = {arm: [float(r["arms"][arm]["mean"]) for r in runs] for arm in ARMS}
    arms = {}
    for arm, means in per_seed.items():
        pooled = [float(v) for r in runs for v in r["arms"][arm]["mse"]]
        mean, std = mean_std(means)
        arms[arm] = {
            "mean": mean,
            "std": std,
            "n_seeds": len(means),
            "std_all_retrainings": mean_std(pooled)[1],
            "n_retrainings": len(pooled),
        }
    active, random = per_seed["active"], per_seed["random"]
    note = "paired t-test across seeds of the per-seed arm means (active vs random)"
    return {
        "seeds": seeds,
        "per_seed": {
            **per_seed,
            "ratio": [_ratio(a, r) for a, r in zip(active, random, strict=True)],
            "within_seed_test": [r.get("test") for r in runs],
        },
        "arms": arms,
        "ratio": _ratio(arms["active"]["mean"], arms["random"]["mean"]),
        "tests": paired_tests(active, random, t_note=note),
        "significance": significance(active, random, runs[0]["env"]),
        "mse_units": runs[0].get("mse_units", ""),
    }


def result_table(r: Mapping[str, Any]) -> str:
    """The table of one explore results dict: the arms over retrainings and their test."""
    arms = r["arms"]
    rows = [
        [a, pm(arms[a]["mean"], arms[a]["std"]), str(len(arms[a].get("mse", [])))]
        for a in ARMS
        if a in arms
    ]
    title = f"explore — {r.get('env')} seed {r.get('seed')}: validation MSE over retrainings"
    text = [render(["arm", "MSE mean ± std", "retrainings"], rows, title)]
    text.append(f"ratio active / random: {fmt(r.get('ratio'))}")
    if test := r.get("test"):
        text.append(
            f"{test.get('name', 'test')}: statistic {fmt(test.get('statistic'))}, "
            f"p = {fmt(test.get('p_value'))}"
        )
    if r.get("mse_units"):
        text.append(f"MSE: {r['mse_units']}")
    return "\n".join(text)


def summary_table(r: Mapping[str, Any]) -> str:
    """Table 1 of an explore summary: one row per env, then each env's power statement."""
    rows, notes = [], []
    for env, s in r["envs"].items():
        sig = s.get("significance") or {}
        ci, sides = sig.get("ratio_ci") or {}, sig.get("directions") or {}
        arms = [pm(s["arms"][arm]["mean"], s["arms"][arm]["std"]) for arm in ARMS]
        ratio = (
            f"{fmt(sig.get('mean_ratio'), 3)} [{fmt(ci.get('low'), 3)}, {fmt(ci.get('high'), 3)}]"
        )
        lower = f"{sides.get('active_lower', '-')}/{sides.get('active_higher', '-')}"
        tests = [fmt(s["tests"][k]["p_value"], 3) for k in ("paired_t", "wilcoxon")]
        dz = fmt((sig.get("effect_size") or {}).get("cohens_dz"), 3)
        rows.append(
            [env, str(len(s["seeds"])), *arms, fmt(s["ratio"], 3), ratio, lower, *tests, dz]
        )
        if (sig.get("power") or {}).get("note"):
            notes.append(f"power, {env}: {sig['power']['note']}")
    not_computed = {t["note"] for s in r["envs"].values() for t in s["tests"].values()}
    notes += [f"note: {n}" for n in sorted(not_computed) if n.startswith("not computed")]
    header = "env|seeds|random|active|active/random|mean ratio [95% CI]|lower/higher|t-test p"
    header += "|Wilcoxon p|d_z"
    title = "Table 1 — validation MSE, mean ± std across seeds of the per-seed means"
    legend = (
        "mean ratio: of the per-seed ratios, 95% percentile bootstrap over seeds (seeded);"
        " lower/higher: seeds where active is below / above random; d_z: Cohen's d of the"
        " per-seed differences active − random"
    )
    return "\n".join([render(header.split("|"), rows, title), legend, *notes])


def headline(results: Mapping[str, Any]) -> dict[str, float]:
    """Arm means and stds, the ratio and the test's p-value."""
    arms = results.get("arms", {})
    scalars = {f"{arm}_mse_{k}": s[k] for arm, s in arms.items() for k in ("mean", "std")}
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


REPORT = Report.of_module(sys.modules[__name__], "explore")
