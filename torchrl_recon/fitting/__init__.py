"""Training entry points, the online fit schedule and self-contained checkpoints."""

from __future__ import annotations

from torchrl_recon.fitting.checkpoint import load_checkpoint, load_modules, save_checkpoint
from torchrl_recon.fitting.fit import (
    FitResult,
    fit_population,
    fit_reward,
    fit_uncertainty,
    fit_world_members,
    fit_world_model,
    train_loss_module,
    world_model_fit,
)
from torchrl_recon.fitting.fit_graph import CapturedStep
from torchrl_recon.fitting.online import FitSchedule, IterationRecord

__all__ = [
    "CapturedStep",
    "FitResult",
    "FitSchedule",
    "IterationRecord",
    "fit_population",
    "fit_reward",
    "fit_uncertainty",
    "fit_world_members",
    "fit_world_model",
    "load_checkpoint",
    "load_modules",
    "save_checkpoint",
    "train_loss_module",
    "world_model_fit",
]
