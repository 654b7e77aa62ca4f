"""Markdown tables of control runs from their stage records, finished or not (docs/reproduction.md).

Run: python docs/results/control_tables.py docs/results/control/<env>/seed0 [...] [--write-partial]

For each run directory it prints one row per setting (prediction MSE, cost-prediction error,
real cost, re-plans, feasible plans; mean ± std over episodes; Welch p against the baseline).
A setting still running is shown with the episodes it has finished
(``stages/setting_<name>/part_<i>.json``) and marked "k of n episodes". With
``--write-partial`` it also assembles the settings of a run that has no ``results.json`` yet
into ``results_partial.json`` and draws its plots next to it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml
from scipy import stats

from torchrl_recon.reports import save_figures
from torchrl_recon.reports.stats import episode_mean_std
from torchrl_recon.runs.archive import run_records


def stage_records(run: Path) -> dict[str, bytes]:
    """``{"stages/...json": content}`` of a run: its own files, and for a published run the
    members of its folder's ``records.tar.xz`` (read in memory, checked against the manifest)."""
    records = {k: v for k, v in run_records(run).items() if k.startswith("stages/")}
    for path in sorted((run / "stages").rglob("*.json")):
        records[path.relative_to(run).as_posix()] = path.read_bytes()
    return records


def settings_so_far(run: Path) -> dict[str, dict]:
    """``{setting: record}`` in the recipe's order: finished settings, then partly run ones.

    A partly run setting (≥ 2 finished episodes, no stage record yet) gets the record of its
    finished episodes plus ``"unfinished": "k of n episodes"``.
    """
    config = yaml.safe_load((run / "config.yaml").read_text())
    records, out = stage_records(run), {}
    for name in (s["name"] for s in config["settings"]):
        if f"stages/setting_{name}.json" in records:
            out[name] = json.loads(records[f"stages/setting_{name}.json"])
            continue
        prefix = f"stages/setting_{name}/part_"
        parts = sorted(
            (k for k in records if k.startswith(prefix) and k.endswith(".json")),
            key=lambda k: int(k[len(prefix) : -len(".json")]),
        )
        if len(parts) < 2:
            continue
        finished = [json.loads(records[k]) for k in parts]
        episodes = [r["metrics"] for r in finished]
        mean, std = episode_mean_std(episodes)
        out[name] = {
            "episodes": episodes,
            "mean": mean,
            "std": std,
            "trajectory_example": finished[0]["trajectory_example"],
            "unfinished": f"{len(parts)} of {config['episodes']} episodes",
        }
    return out


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

        label = f"{name} ({record['unfinished']})" if "unfinished" in record else name
        rows.append(
            f"| {label} | {m['prediction_mse']:.3g} ± {s['prediction_mse']:.3g} | "
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
        "partial": "the run has not ended: finished settings (stages/setting_*.json) and the "
        "finished episodes of a running one (marked unfinished)",
        "settings": {
            n: {k: v for k, v in r.items() if k != "trajectory_example"}
            for n, r in settings.items()
        },
        "trajectory_example": example,
    }
    (run / "results_partial.json").write_text(json.dumps(results, indent=1))
    save_figures(results, run)  # control_errors.png, trajectory.png: as a finished run draws them


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--write-partial", action="store_true")
    args = parser.parse_args()
    for run in args.runs:
        settings = settings_so_far(run)
        print(f"{run}\n\n{table(settings)}\n")
        if args.write_partial and not (run / "results.json").exists():
            write_partial(run, settings)


if __name__ == "__main__":
    main()
