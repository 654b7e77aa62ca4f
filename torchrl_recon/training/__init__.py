"""Training entry points and self-contained checkpoints."""

from __future__ import annotations

from torchrl_recon.training.checkpoint import load_checkpoint, load_modules, save_checkpoint
from torchrl_recon.training.fit import (
    FitResult,
    fit_population,
    fit_uncertainty,
    fit_world_members,
    fit_world_model,
    train_loss_module,
    world_model_fit,
)

__all__ = [
    "FitResult",
    "fit_population",
    "fit_uncertainty",
    "fit_world_members",
    "fit_world_model",
    "load_checkpoint",
    "load_modules",
    "save_checkpoint",
    "train_loss_module",
    "world_model_fit",
]
