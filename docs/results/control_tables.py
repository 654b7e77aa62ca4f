"""Markdown tables of control runs from their stage records, finished or not (docs/reproduction.md).

Run: python docs/results/control_tables.py docs/results/control/<env>/seed0 [...] [--write-partial]

For each run directory it prints one row per finished setting (prediction MSE, cost-prediction
error, real cost, re-plans, feasible plans; mean ± std over episodes; Welch p against the
baseline). With ``--write-partial`` it also assembles the finished settings of a run that has
no ``results.json`` yet into ``results_partial.json`` and draws its plots next to it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml
from scipy import stats

from torchrl_recon.experiments.plots import plot_control_errors, plot_trajectory


def finished_settings(run: Path) -> dict[str, dict]:
    """``{setting: stage record}`` of the finished settings, in the recipe's order."""
    order = [s["name"] for s in yaml.safe_load((run / "config.yaml").read_text())["settings"]]
    stages = run / "stages"
    return {
        name: json.loads((stages / f"setting_{name}.json").read_text())
        for name in order
        if (stages / f"setting_{name}.json").exists()
    }


def table(settings: dict[str, dict]) -> str:
    base = settings["baseline"]["episodes"]
    rows = [
        "| setting | prediction MSE | p vs baseline | \\|predicted − real\\| Σcost | real Σcost "
        "| p vs baseline | re-plans / episode | feasible plans |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, record in settings.items():
        m, s = record["mean"], record["std"]

        def p(key: str, name: str = name, record: dict = record) -> str:
            if name == "baseline":
                return "–"
            ours = [e[key] for e in record["episodes"]]
            return f"{stats.ttest_ind(ours, [e[key] for e in base], equal_var=False).pvalue:.2g}"

        rows.append(
            f"| {name} | {m['prediction_mse']:.3g} ± {s['prediction_mse']:.3g} | "
            f"{p('prediction_mse')} | {m['cost_error']:.1f} ± {s['cost_error']:.1f} | "
            f"{m['real_cost']:.1f} ± {s['real_cost']:.1f} | {p('real_cost')} | "
            f"{m['replans']:.1f} ± {s['replans']:.1f} | {m['feasible_fraction']:.2f} |"
        )
    return "\n".join(rows)


def write_partial(run: Path, settings: dict[str, dict]) -> None:
    example = next(
        (r["trajectory_example"] for r in settings.values() if r.get("trajectory_example")), None
    )
    meta = json.loads((run / "meta.json").read_text())
    results = {
        "experiment": "control",
        "env": meta["env"],
        "seed": meta["seed"],
        "partial": "settings finished so far, from stages/setting_*.json; the run has not ended",
        "settings": {
            n: {k: v for k, v in r.items() if k != "trajectory_example"}
            for n, r in settings.items()
        },
        "trajectory_example": example,
    }
    (run / "results_partial.json").write_text(json.dumps(results, indent=1))
    plot_control_errors(results).savefig(run / "control_errors.png", dpi=120)
    if example:
        plot_trajectory(example).savefig(run / "trajectory.png", dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--write-partial", action="store_true")
    args = parser.parse_args()
    for run in args.runs:
        settings = finished_settings(run)
        print(f"{run}\n\n{table(settings)}\n")
        if args.write_partial and not (run / "results.json").exists():
            write_partial(run, settings)


if __name__ == "__main__":
    main()
