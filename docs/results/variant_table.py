"""Markdown table of exploration variants: active/random ratio per seed, paired test against a base.

Run: python docs/results/variant_table.py docs/results/explore_variants/minitaur [--base base]

The directory holds ``<variant>/seed<n>/results.json`` (explore runs). For each variant it prints
the ratio of each seed, their mean ± std, a paired t-test across the seeds both variants ran
against ``--base``, the mean fraction of active plans that found a candidate above the Σu
threshold, and the mean validation MSE of each arm.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from scipy import stats


def load(root: Path) -> dict[str, dict[int, dict]]:
    """``{variant: {seed: results}}`` of every ``<variant>/seed<n>/results.json`` under ``root``."""
    out: dict[str, dict[int, dict]] = {}
    for path in sorted(root.glob("*/seed*/results.json")):
        seed = int(path.parent.name.removeprefix("seed"))
        out.setdefault(path.parent.parent.name, {})[seed] = json.loads(path.read_text())
    return out


def table(runs: dict[str, dict[int, dict]], base: str = "base") -> str:
    rows = [
        "| variant | ratio per seed | mean ± std | paired p vs base | feasible active plans "
        "| random MSE | active MSE |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    names = [base, *sorted(n for n in runs if n != base)] if base in runs else sorted(runs)
    for name in names:
        by_seed = runs[name]
        ratios = [by_seed[s]["ratio"] for s in sorted(by_seed)]
        common = sorted(set(by_seed) & set(runs.get(base, {})))
        p = "–"
        if name != base and len(common) >= 2:
            ours = [by_seed[s]["ratio"] for s in common]
            theirs = [runs[base][s]["ratio"] for s in common]
            p = "same" if ours == theirs else f"{stats.ttest_rel(ours, theirs).pvalue:.2g}"
        std = f"{statistics.stdev(ratios):.3f}" if len(ratios) > 1 else "–"

        def mean_of(key: str, by_seed: dict = by_seed) -> float:
            return statistics.mean(statistics.mean(r["arms"][key]["mse"]) for r in by_seed.values())

        feasible = statistics.mean(r["data"]["active_feasible_fraction"] for r in by_seed.values())
        rows.append(
            f"| {name} | {', '.join(f'{r:.3f}' for r in ratios)} | "
            f"{statistics.mean(ratios):.3f} ± {std} | {p} | {feasible:.2f} | "
            f"{mean_of('random'):.3f} | {mean_of('active'):.3f} |"
        )
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("--base", default="base")
    args = parser.parse_args()
    print(table(load(args.root), args.base))


if __name__ == "__main__":
    main()
