"""Our online agent beside mbrl-lib's PETS on one task: the table and learning curves of
``docs/online.md`` (issue 33).

Reads our runs (``<ours>/seed*/results.json``, written by ``torchrl-recon online``) and PETS's
(``<pets>/seed*/results.csv`` and ``timing.json``, written by ``benchmarks/peers/pets.py``),
and prints, per agent: the seeds, the random policy's return, the mean return of the last half
of the episodes (mean ± sample std over seeds, each seed's mean first), planning ms per step and
fit s per refit; then each episode's return (mean over seeds) against the env steps at its end,
random steps included (ours: ``random_steps``; PETS: its random first episode). ``--plot``
writes the learning curves. Runs in the project's environment (it only reads files).

Run: python benchmarks/peers/side_by_side.py --ours docs/results/online/Pendulum-v1
     --pets docs/results/peers/pets/pendulum --task pendulum --plot docs/results/peers/pendulum.png
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
from pathlib import Path

PETS_RANDOM_STEPS = {"pendulum": 200, "mountain_car": 999, "inverted_pendulum": 1000}
"""PETS's random first episode (``initial_exploration_steps``: one episode of ``pets.py``'s
default length), for runs whose ``timing.json`` predates its ``random_steps``."""


def _mean_std(values: list[float]) -> tuple[float, float]:
    if not values:
        return math.nan, math.nan
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def _median(values: list[float], spec: str) -> str:
    return format(statistics.median(values), spec) if values else "— (run stopped)"


def _seed_dirs(folder: Path, marker: str) -> list[Path]:
    found = sorted(p.parent for p in folder.glob(f"seed*/{marker}"))
    if not found:
        raise SystemExit(f"error: no seed*/{marker} below {folder}")
    return sorted(found, key=lambda p: int(p.name.removeprefix("seed")))


def ours(folder: Path) -> dict:
    """Our runs: per seed the (env steps, return) of each MPC episode, and the timings."""
    curves, randoms, plan_ms, fit_s = [], [], [], []
    for run in _seed_dirs(folder, "results.json"):
        r = json.loads((run / "results.json").read_text())
        curves.append([(it["env_steps"], x) for it in r["iterations"] for x in it["returns"]])
        randoms.append(r["random"]["mean_return"])
        for it in r["iterations"]:  # ms per plan (a step of every_step MPC)
            plan_ms.append(1000 * it["plan_s"] / max(it["replans"], 1))
            fit_s.append(it["fit_s"])
    return {"curves": curves, "random": randoms, "plan_ms": plan_ms, "fit_s": fit_s}


def pets(folder: Path, task: str) -> dict:
    """PETS's runs of ``task``: per seed the (env steps, return) of each episode after its random
    one; a run stopped before its end (no ``timing.json``) counts the episodes it finished."""
    curves, plan_ms, fit_s = [], [], []
    for run in _seed_dirs(folder, "results.csv"):
        with open(run / "results.csv") as f:
            rows = list(csv.DictReader(f))
        timing_file = run / "timing.json"
        timing = json.loads(timing_file.read_text()) if timing_file.exists() else {}
        first = int(timing.get("random_steps", PETS_RANDOM_STEPS[task]))
        curves.append(
            [(first + int(float(x["env_step"])), float(x["episode_reward"])) for x in rows]
        )
        if timing:
            plan_ms.append(timing["plan_ms_per_step"])
            fit_s.append(timing["fit_s_per_refit"])
    return {"curves": curves, "random": [], "plan_ms": plan_ms, "fit_s": fit_s}


def last_half(curve: list[tuple[int, float]]) -> float:
    """The mean return of the last half of a seed's episodes (the later one of an odd count)."""
    returns = [r for _, r in curve]
    return statistics.fmean(returns[len(returns) // 2 :]) if returns else math.nan


def table(agents: dict[str, dict]) -> str:
    lines = [
        "| agent | seeds | episodes | random policy | last half, mean ± std over seeds | "
        "plan ms/step | fit s/refit |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, a in agents.items():
        halves = [last_half(c) for c in a["curves"]]
        m, s = _mean_std(halves)
        rm, rs = _mean_std(a["random"])
        random = f"{rm:.0f} ± {rs:.0f}" if a["random"] else "—"
        episodes = "/".join(sorted({str(len(c)) for c in a["curves"]}))
        lines.append(
            f"| {name} | {len(a['curves'])} | {episodes} | {random} | {m:.0f} ± {s:.0f} "
            f"(per seed {', '.join(f'{h:.0f}' for h in halves)}) | "
            f"{_median(a['plan_ms'], '.1f')} | {_median(a['fit_s'], '.2f')} |"
        )
    lines += ["", "| agent | episode | env steps at its end | return, mean over seeds |"]
    lines += ["| --- | ---: | ---: | ---: |"]
    for name, a in agents.items():
        for i in range(min(len(c) for c in a["curves"])):
            steps = a["curves"][0][i][0]
            mean = statistics.fmean(c[i][1] for c in a["curves"])
            lines.append(f"| {name} | {i + 1} | {steps} | {mean:.0f} |")
    return "\n".join(lines)


def plot(agents: dict[str, dict], path: Path, title: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 3.5), layout="constrained")
    ax = fig.add_subplot()
    for color, (name, a) in enumerate(agents.items()):
        for curve in a["curves"]:
            ax.plot(*zip(*curve, strict=True), "-", color=f"C{color}", alpha=0.25, lw=0.8)
        n = min(len(c) for c in a["curves"])
        steps = [a["curves"][0][i][0] for i in range(n)]
        means = [statistics.fmean(c[i][1] for c in a["curves"]) for i in range(n)]
        ax.plot(steps, means, "o-", color=f"C{color}", label=f"{name} ({len(a['curves'])} seeds)")
    ax.set(xlabel="env steps (random ones included)", ylabel="episode return", title=title)
    ax.legend(loc="lower right")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ours", type=Path, required=True)
    parser.add_argument("--pets", type=Path, required=True)
    parser.add_argument("--task", choices=sorted(PETS_RANDOM_STEPS), required=True)
    parser.add_argument("--title", default="")
    parser.add_argument("--plot", type=Path)
    args = parser.parse_args()
    agents = {
        "ours (torchrl-recon online)": ours(args.ours),
        "PETS (mbrl-lib 0.2.0)": pets(args.pets, args.task),
    }
    print(table(agents))
    if args.plot:
        plot(agents, args.plot, args.title)
        print(f"\nfigure: {args.plot}")


if __name__ == "__main__":
    main()
