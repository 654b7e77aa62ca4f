"""Results dicts as the experiments write them, for the summary, check and archive tests."""

from __future__ import annotations

import json
import math
from pathlib import Path

from torchrl_recon.evaluation.mpc import METRICS


def explore_results(
    seed: int, random: list[float], active: list[float], env: str = "drone"
) -> dict:
    """An explore ``results.json`` whose means, stds and ratio agree with its values."""

    def arm(values: list[float]) -> dict:
        mean = math.fsum(values) / len(values)
        std = (
            math.sqrt(math.fsum((v - mean) ** 2 for v in values) / (len(values) - 1))
            if len(values) > 1
            else float("nan")
        )
        return {"mse": values, "mean": mean, "std": std}

    r, a = arm(random), arm(active)
    return {
        "experiment": "explore",
        "env": env,
        "seed": seed,
        "mse_units": "standardised squared error",
        "arms": {"random": r, "active": a},
        "ratio": a["mean"] / r["mean"],
        "test": {"name": "Welch t-test", "statistic": -1.0, "p_value": 0.3},
        "data": {"initial_steps": 300, "active_feasible_fraction": 0.5},
        "wall_time_s": {"initial_random": 1.0},
    }


def control_results(seed: int, mses: dict[str, list[float]], env: str = "drone") -> dict:
    """A control ``results.json``: one episode per value, every metric that value."""
    settings = {}
    for name, values in mses.items():
        episodes = [{k: v for k in METRICS} for v in values]
        finite = [v for v in values if not math.isnan(v)]
        mean = math.fsum(finite) / len(finite) if finite else float("nan")
        settings[name] = {
            "episodes": episodes,
            "mean": {k: mean for k in METRICS},
            "std": {k: 0.0 for k in METRICS},
        }
    return {"experiment": "control", "env": env, "seed": seed, "settings": settings}


def write_runs(root: Path, results: list[dict]) -> list[Path]:
    """Write each results dict as ``root/<env>/seed<n>/results.json``; return the files."""
    files = []
    for r in results:
        path = root / r["env"] / f"seed{r['seed']}" / "results.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(r, indent=1))
        files.append(path)
    return files


RANDOM = [10.0, 12.0, 11.0, 13.0, 9.0]
ACTIVE = [7.0, 8.0, 8.0, 9.0, 6.0]
"""Per-seed arm means of the known-value example (each the mean of two retrainings)."""


def known_explore(env: str = "drone") -> list[dict]:
    """Five seeds whose arm means are :data:`RANDOM` and :data:`ACTIVE`."""
    return [
        explore_results(s, [r - 1, r + 1], [a - 0.5, a + 0.5], env=env)
        for s, (r, a) in enumerate(zip(RANDOM, ACTIVE, strict=True))
    ]
