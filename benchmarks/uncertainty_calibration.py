"""Uncertainty estimators side by side: does u rank the real error, flag unfamiliar inputs, and
at what cost? The autoencoder against an ensemble, MC dropout and RND.

Run: python benchmarks/uncertainty_calibration.py [--env industrial_benchmark] [--smoke] [key=value ...]

The same run as ``torchrl-recon calibrate recipes/<env>/calibrate.yaml [key=value ...]``: all
estimators are fitted on the same random data; for each it prints Spearman(Σu, real multi-step
error) and AUROC for "error above its median" on imagined held-out trajectories, OOD AUROC
(states moved 3σ; actions held at the bound), and the time to score K = 1000 × H windows and of
one CEM call with it, as ratios to the autoencoder measured in the same run; then the outcome
of the exploration and control experiments at a reduced scale with each. It writes
``results.json`` and ``calibration.png`` to the run directory (resumable: re-run to continue).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchrl_recon.cli import run_recipe

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--env",
        default="industrial_benchmark",
        choices=("industrial_benchmark", "drone", "minitaur"),
    )
    parser.add_argument("--smoke", action="store_true", help="the tiny smoke-test recipe")
    args, overrides = parser.parse_known_args()
    recipe = RECIPES / args.env / ("calibrate_smoke.yaml" if args.smoke else "calibrate.yaml")
    return run_recipe("calibrate", recipe, overrides)


if __name__ == "__main__":
    sys.exit(main())
