"""TorchRL loss modules for the world model and the uncertainty estimators."""

from __future__ import annotations

from torchrl_recon.objectives.reward_loss import RewardLoss
from torchrl_recon.objectives.sequences import as_sequences
from torchrl_recon.objectives.uncertainty_loss import UncertaintyLoss
from torchrl_recon.objectives.world_model_loss import WorldModelPredictionLoss

__all__ = ["RewardLoss", "UncertaintyLoss", "WorldModelPredictionLoss", "as_sequences"]
