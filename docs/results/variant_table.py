"""Markdown table of exploration variants: active/random ratio per seed, paired test against a base.

Run: python docs/results/variant_table.py docs/results/explore_variants/minitaur [--base base]
     python docs/results/variant_table.py docs/results/explore_variants_full/minitaur \
         --base-root docs/results/explore/minitaur
     python docs/results/variant_table.py docs/results/explore_population/drone \
         --base-root docs/results/explore/drone

The directory holds ``<variant>/seed<n>/results.json`` (explore runs), or is one variant's
``seed<n>/`` directories itself; ``--base-root`` takes the
base from another directory of ``seed<n>/results.json`` (e.g. the main runs). For each variant it prints
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
    """``{variant: {seed: results}}`` of every ``<variant>/seed<n>/results.json`` under ``root``;
    a ``root`` that holds ``seed<n>/`` runs itself is one variant, named after it."""
    if any(root.glob("seed*/results.json")):
        return {root.name: load_seeds(root)}
    variants = sorted({path.parent.parent for path in root.glob("*/seed*/results.json")})
    return {variant.name: load_seeds(variant) for variant in variants}


def load_seeds(root: Path) -> dict[int, dict]:
    """``{seed: results}`` of every ``seed<n>/results.json`` under ``root``."""
    return {
        int(path.parent.name.removeprefix("seed")): json.loads(path.read_text())
        for path in sorted(root.glob("seed*/results.json"))
    }


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
    parser.add_argument("--base-root", type=Path, help="take the base's seed<n>/ runs from here")
    args = parser.parse_args()
    runs = load(args.root)
    if args.base_root is not None:
        base = load_seeds(args.base_root)
        if not base:
            parser.error(f"--base-root {args.base_root}: no seed<n>/results.json found there")
        runs[args.base] = base
    print(table(runs, args.base))


if __name__ == "__main__":
    main()
