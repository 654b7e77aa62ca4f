"""The calibrate experiment's report (uncertainty estimators side by side): its summary across
seeds, tables, figures and headline numbers."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

from torchrl_recon.reports.plots import plot_calibration
from torchrl_recon.reports.report import Figures, Report
from torchrl_recon.reports.stats import mean_std
from torchrl_recon.reports.tables import fmt, render

CALIBRATION_COLUMNS = (
    ("spearman", "Spearman(Σu, err)"),
    ("auroc_error_above_median", "AUROC err>median"),
    ("ood_auroc_state_shift", "OOD AUROC states"),
    ("ood_auroc_action_bound", "OOD AUROC actions"),
    ("score_ratio_H{h}", "score time ×AE H={h}"),
    ("cem_ratio_H{h}", "CEM time ×AE H={h}"),
    ("explore_ratio", "explore active/random"),
)


def _numeric(row: Mapping[str, Any]) -> list[str]:
    return [k for k, v in row.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]


def summarize_env(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per estimator, mean ± std across seeds of every numeric entry of its row.

    Every estimator and entry any seed has is kept, each over the seeds that have it
    (``n_seeds``: the estimator's), so seeds run with different estimator lists lose nothing.
    """
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    names = list(dict.fromkeys(name for r in runs for name in r["estimators"]))
    estimators: dict[str, Any] = {}
    for name in names:
        rows = [r["estimators"][name] for r in runs if name in r["estimators"]]
        keys = list(dict.fromkeys(k for row in rows for k in _numeric(row)))
        stats = {k: mean_std([row[k] for row in rows if k in row]) for k in keys}
        mean, std = ({k: s[i] for k, s in stats.items()} for i in (0, 1))
        estimators[name] = {"mean": mean, "std": std, "n_seeds": len(rows)}
    seeds = [r.get("seed") for r in runs]
    return {"seeds": seeds, "horizons": runs[0].get("horizons", []), "estimators": estimators}


def estimators_table(title: str, rows_by_name: Mapping[str, Any], horizons: list[int]) -> str:
    """One row per estimator; ``rows_by_name[name]`` maps column keys to numbers."""
    h = (horizons or [0])[0]
    header = ["estimator", *(label.format(h=h) for _, label in CALIBRATION_COLUMNS)]
    keys = [k.format(h=h) for k, _ in CALIBRATION_COLUMNS]
    rows = [[name, *(fmt(row.get(k), 3) for k in keys)] for name, row in rows_by_name.items()]
    return render(header, rows, title)


def result_table(r: Mapping[str, Any]) -> str:
    """The table of one calibrate results dict: one row per estimator."""
    title = (
        f"uncertainty estimators — {r.get('env')} seed {r.get('seed')} "
        f"(times as ratios to {r.get('reference_estimator')!r}, measured in the same run)"
    )
    return estimators_table(title, r["estimators"], r.get("horizons"))


def _means(s: Mapping[str, Any]) -> dict[str, Any]:
    return {name: e["mean"] for name, e in s["estimators"].items()}


def summary_table(r: Mapping[str, Any]) -> str:
    """One table per env of a calibrate summary (means across seeds)."""
    return "\n\n".join(
        estimators_table(
            f"uncertainty estimators — {env}, seeds {s['seeds']}: mean across seeds",
            _means(s),
            s["horizons"],
        )
        for env, s in r["envs"].items()
    )


def headline(results: Mapping[str, Any]) -> dict[str, float]:
    """Every number of every estimator's row, as ``<estimator>/<key>``."""
    return {
        f"{name}/{key}": value
        for name, row in results.get("estimators", {}).items()
        for key, value in row.items()
        if isinstance(value, (int, float))
    }


def figures(results: Mapping[str, Any]) -> Figures:
    """``calibration.png``."""
    return [("calibration.png", plot_calibration(results))]


def summary_figures(summary: Mapping[str, Any], results: list[Mapping[str, Any]]) -> Figures:
    """``calibration_<env>.png`` for each env of the summary."""
    return [
        (f"calibration_{env}.png", plot_calibration({**s, "env": env, "estimators": _means(s)}))
        for env, s in summary["envs"].items()
    ]


REPORT = Report.of_module(sys.modules[__name__], "calibrate")
