"""Evaluation of world models and uncertainty estimates on real trajectories."""

from __future__ import annotations

from torchrl_recon.evaluation.calibration import (
    auroc,
    calibration_metrics,
    imagined_uncertainty_and_error,
    spearman,
)
from torchrl_recon.evaluation.mpc import episode_metrics, planned_trajectory
from torchrl_recon.evaluation.prediction import multi_step_errors, population_multi_step_errors

__all__ = [
    "auroc",
    "calibration_metrics",
    "episode_metrics",
    "imagined_uncertainty_and_error",
    "multi_step_errors",
    "planned_trajectory",
    "population_multi_step_errors",
    "spearman",
]
