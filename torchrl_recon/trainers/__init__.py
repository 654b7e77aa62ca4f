"""The library's parts in TorchRL's ``Trainer``: hooks that turn a ``torchrl.trainers.Trainer``
into the online model-based agent, each usable alone in a Trainer of one's own, and the
agent's own Trainer and loop built from them (docs/torchrl_trainer.md). The parts in TorchRL's
config store are in ``torchrl_recon.trainers.configs`` (importing it stores them)."""

from __future__ import annotations

from torchrl_recon.trainers.buffer import ReplayBufferSteps
from torchrl_recon.trainers.checkpoint import VerifiedCheckpoint, VerifiedTrainer, verify_checkpoint
from torchrl_recon.trainers.collector import (
    IterationCollector,
    OnlineCollector,
    TimedPolicy,
    env_keys,
    play,
)
from torchrl_recon.trainers.fit import ModelFitStepper
from torchrl_recon.trainers.log_iteration import LogIteration
from torchrl_recon.trainers.normalization import FitNormalization
from torchrl_recon.trainers.online import OnlineTrainer, learn_online

__all__ = [
    "FitNormalization",
    "IterationCollector",
    "LogIteration",
    "ModelFitStepper",
    "OnlineCollector",
    "OnlineTrainer",
    "ReplayBufferSteps",
    "TimedPolicy",
    "VerifiedCheckpoint",
    "VerifiedTrainer",
    "env_keys",
    "learn_online",
    "play",
    "verify_checkpoint",
]
