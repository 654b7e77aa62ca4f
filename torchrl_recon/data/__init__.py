"""Replay-buffer helpers: sequence sampling, trajectory splits, save and load."""

from __future__ import annotations

from torchrl_recon.data.buffers import (
    FIT_KEYS,
    MASK_KEY,
    REWARD_FIT_KEYS,
    SHORT_EPISODES,
    TRAJ_KEY,
    GatherTensorStorage,
    buffer_contents,
    cut_sequences,
    load_buffer,
    load_buffer_data,
    long_trajectories,
    make_sequence_buffer,
    needs_padding,
    padded_trajectories,
    quiet_storage_init,
    save_buffer,
    sequence_buffers,
    split_by_trajectory,
)
from torchrl_recon.data.step_sampler import WINDOW_SAMPLINGS, StepUniformSliceSampler

__all__ = [
    "MASK_KEY",
    "FIT_KEYS",
    "REWARD_FIT_KEYS",
    "SHORT_EPISODES",
    "TRAJ_KEY",
    "GatherTensorStorage",
    "StepUniformSliceSampler",
    "WINDOW_SAMPLINGS",
    "buffer_contents",
    "cut_sequences",
    "load_buffer",
    "load_buffer_data",
    "long_trajectories",
    "make_sequence_buffer",
    "needs_padding",
    "padded_trajectories",
    "quiet_storage_init",
    "save_buffer",
    "sequence_buffers",
    "split_by_trajectory",
]
