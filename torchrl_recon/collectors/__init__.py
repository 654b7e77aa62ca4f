"""Data collection: random exploration, simple action sources and sequence datasets."""

from __future__ import annotations

from torchrl_recon.collectors.datasets import (
    EpisodesTooShort,
    concat_trajectories,
    first_episodes,
    renumber_trajectories,
    validation_trajectories,
)
from torchrl_recon.collectors.policies import OffsetNoisePolicy
from torchrl_recon.collectors.random_data import collect, collect_random

__all__ = [
    "EpisodesTooShort",
    "OffsetNoisePolicy",
    "collect",
    "collect_random",
    "concat_trajectories",
    "first_episodes",
    "renumber_trajectories",
    "validation_trajectories",
]
