"""The learning curves of docs/standard_tasks.md: one figure per task, each published seed's
mean return per iteration and the mean over seeds for each variant, the random policy, and the
task's target and anchor.

Run: python docs/results/standard_task_curves.py   (writes docs/results/standard_tasks/<task>.png)
     python docs/results/standard_task_curves.py --table   (also prints each seed's table row)

The runs are read from ``docs/results/standard_tasks/<variant>/seed*/results.json``; a variant
with no published seed yet is left out of its figure.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from torchrl_recon.reports.plots import plot_seed_curves

HERE = Path(__file__).resolve().parent / "standard_tasks"
TASKS = {  # task -> (variant label -> folder, reference label -> return)
    "InvertedPendulum-v5": (
        {
            "β = 0": "InvertedPendulum-v5_one_step",
            "β = 2": "InvertedPendulum-v5_one_step_beta2",
            "β = 2, every ended episode kept": "InvertedPendulum-v5_one_step_beta2_pad",
            "the same, PETS's CEM": "InvertedPendulum-v5_one_step_beta2_pets_cem",
        },
        {"target: 1,000 steps up": 1000.0},
    ),
    "InvertedDoublePendulum-v5": (
        {"PETS's CEM 200 × 5 × H 10": "InvertedDoublePendulum-v5"},
        {"target: 9,000": 9000.0},
    ),
    "Reacher-v5": (
        {
            "β = 0": "Reacher-v5",
            "β = 2": "Reacher-v5_beta2",
            "PETS's CEM, β = 0": "Reacher-v5_pets_cem",
        },
        {"target: −5": -5.0, "SAC after 1M steps: about −4": -4.0},
    ),
}


def seeds_of(folder: str) -> list[dict]:
    """The results of every published seed of one variant, in seed order."""
    paths = sorted((HERE / folder).glob("seed*/results.json"), key=lambda p: int(p.parent.name[4:]))
    return [json.loads(p.read_text()) for p in paths]


def table_rows(label: str, runs: list[dict]) -> list[str]:
    """Markdown rows, one per seed: each iteration's mean return, the last half, the best
    episode of the last iteration."""
    rows = []
    for run in runs:
        means = ", ".join(
            f"{np.mean(it['returns']):.1f}".replace("-", "−") for it in run["iterations"]
        )
        last, best = run["mean_return_last_half"], max(run["iterations"][-1]["returns"])
        rows.append(
            f"| {run['seed']}, {label} | {means} | {last:.2f} | {best:.2f} |".replace("-", "−")
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--table", action="store_true", help="print each seed's table row")
    args = parser.parse_args()
    for task, (folders, references) in TASKS.items():
        variants = {label: seeds_of(folder) for label, folder in folders.items()}
        variants = {label: runs for label, runs in variants.items() if runs}
        if not variants:
            continue
        figure = plot_seed_curves(variants, references=references, title=task)
        path = HERE / f"{task}.png"
        figure.savefig(path, dpi=110)
        print(f"{path.relative_to(HERE.parents[1])}: {', '.join(variants)}")
        for label, runs in variants.items() if args.table else ():
            print("\n".join(table_rows(label, runs)))


if __name__ == "__main__":
    main()
