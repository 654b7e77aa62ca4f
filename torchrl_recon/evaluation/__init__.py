"""Evaluation of world models and uncertainty estimates on real trajectories."""

from __future__ import annotations

from torchrl_recon.evaluation.calibration import auroc, imagined_uncertainty_and_error, spearman
from torchrl_recon.evaluation.prediction import multi_step_errors, population_multi_step_errors

__all__ = [
    "auroc",
    "imagined_uncertainty_and_error",
    "multi_step_errors",
    "population_multi_step_errors",
    "spearman",
]
