"""The online experiment's report (PETS's loop: act, add the data, refit warm, act again): its
summary across seeds, tables, the learning curve and headline numbers."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

import numpy as np

from torchrl_recon.reports.plots import plot_learning_curve, plot_seed_curves
from torchrl_recon.reports.report import Figures, Report
from torchrl_recon.reports.stats import mean_std
from torchrl_recon.reports.tables import fmt, pm, render


def summarize_env(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per iteration, the mean return over seeds (each seed's mean over its episodes), and the
    random policy's and the last half's mean ± sample std over seeds."""
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    counts = [len(r["iterations"]) for r in runs]
    count = min(counts)  # iterations every seed has
    per_iteration = [
        mean_std([_mean(r["iterations"][i]["returns"]) for r in runs], finite=True)
        for i in range(count)
    ]
    summary = {
        "seeds": [r.get("seed") for r in runs],
        "random": mean_std([r["random"]["mean_return"] for r in runs], finite=True),
        "last_half": mean_std([r["mean_return_last_half"] for r in runs], finite=True),
        "iterations": [{"mean": m, "std": s} for m, s in per_iteration],
        "env_steps": [runs[0]["iterations"][i]["env_steps"] for i in range(count)],
    }
    if len(set(counts)) > 1:  # said, not silently cut: the rows stop at the shortest seed's
        summary["iterations_per_seed"] = counts
    return summary


def result_table(r: Mapping[str, Any]) -> str:
    """One run: per iteration, env steps, mean return, model error, mean u, re-plans, times."""
    rows = [
        [str(it["iteration"]), str(it["env_steps"]), fmt(_mean(it["returns"]))]
        + [fmt(it["model_error"]), fmt(it["mean_u"]), str(it["replans"])]
        + [f"{it['fit_s']:.1f} / {it['plan_s']:.1f} / {it['env_s']:.1f}"]
        for it in r["iterations"]
    ]
    header = ["iter", "env steps", "return", "model error", "mean u", "replans", "fit/plan/env s"]
    title = (
        f"online {r['env']} seed {r['seed']}: random policy {fmt(r['random']['mean_return'])}, "
        f"last half {fmt(r['mean_return_last_half'])}"
        + (f", warm-up {r['warmup']}" if r.get("warmup") else "")
    )
    return render(header, rows, title)


def summary_table(r: Mapping[str, Any]) -> str:
    """Per env: the random policy, each iteration's mean return and the last half, over seeds."""
    parts = []
    for env, s in r["envs"].items():
        rows = [
            [str(i), str(steps), pm(it["mean"], it["std"])]
            for i, (it, steps) in enumerate(zip(s["iterations"], s["env_steps"], strict=True), 1)
        ]
        title = (
            f"online {env}, seeds {s['seeds']}: random policy {pm(*s['random'])}, "
            f"last half {pm(*s['last_half'])}"
        )
        if "iterations_per_seed" in s:
            title += (
                f" (iterations per seed {s['iterations_per_seed']}: the rows stop at "
                f"{len(s['iterations'])}; each seed's last half is its own)"
            )
        parts.append(render(["iter", "env steps", "return"], rows, title))
    return "\n\n".join(parts)


def headline(results: Mapping[str, Any]) -> dict[str, float]:
    """The random policy's and the last half's mean returns."""
    return {
        "random_return": results["random"]["mean_return"],
        "return_last_half": results["mean_return_last_half"],
    }


def figures(results: Mapping[str, Any]) -> Figures:
    """``learning_curve.png``."""
    return [("learning_curve.png", plot_learning_curve(results))]


def summary_figures(summary: Mapping[str, Any], results: list[Mapping[str, Any]]) -> Figures:
    """``learning_curves_<env>.png`` for each env of the summary: each seed's curve and their mean."""
    return [
        (
            f"learning_curves_{env}.png",
            plot_seed_curves({"MPC": [r for r in results if r["env"] == env]}),
        )
        for env in summary["envs"]
    ]


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


REPORT = Report.of_module(sys.modules[__name__], "online")
