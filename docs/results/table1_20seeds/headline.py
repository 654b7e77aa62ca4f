"""The headline table of ``docs/reproduction.md``: the paper's Table 1 ratios beside ours.

Run: python docs/results/table1_20seeds/headline.py   (prints a Markdown table)

It summarizes the published runs with ``torchrl_recon.reports.summarize`` (which
checks every ``results.json`` and the records archive first): IB and the Drone at up to 20
seeds with the shipped recipes, IB's ``offset_noise`` validation variant, and the Minitaur's
five full-scale repeats with the retrainings fitted as one population.
"""

from __future__ import annotations

from pathlib import Path

from torchrl_recon.reports import summarize

RESULTS = Path(__file__).resolve().parents[1]
ROWS = (  # label, folder, env
    ("Industrial Benchmark", "table1_20seeds/base/industrial_benchmark", "industrial_benchmark"),
    ("Drone", "table1_20seeds/base/drone", "drone"),
    ("Minitaur", "explore_population/minitaur", "minitaur"),
    (
        "IB, `offset_noise` validation",
        "table1_20seeds/offset_noise/industrial_benchmark",
        "industrial_benchmark",
    ),
)


def row(label: str, folder: str, env: str) -> str:
    s = summarize([RESULTS / folder])["envs"][env]
    sig, tests = s["significance"], s["tests"]
    ci, d, power = sig["ratio_ci"], sig["directions"], sig["power"]
    return (
        f"| {label} | {power['paper_ratio']:.2f} | {len(s['seeds'])} | "
        f"{sig['mean_ratio']:.3f} [{ci['low']:.3f}, {ci['high']:.3f}] | "
        f"{d['active_lower']}/{d['active_higher']} | {tests['paired_t']['p_value']:.2g} | "
        f"{tests['wilcoxon']['p_value']:.2g} | {sig['effect_size']['cohens_dz']:.2f} |"
    )


def main() -> None:
    print(
        "| environment | paper | seeds | ours: mean ratio [95% CI] | lower/higher | paired t p "
        "| Wilcoxon p | d_z |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for label, folder, env in ROWS:
        print(row(label, folder, env))


if __name__ == "__main__":
    main()
