"""Data without trajectory ids (from env.rollout) is a clear error naming the key and its writer."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import GymEnv

from torchrl_recon.data import cut_sequences, split_by_trajectory


@pytest.fixture(scope="module")
def rollout():
    env = GymEnv("Pendulum-v1")
    env.set_seed(0)
    return env.rollout(30)


def test_split_by_trajectory_names_the_missing_key(rollout):
    with pytest.raises(ValueError) as info:
        split_by_trajectory(rollout, 0.2, seed=0)
    message = str(info.value)
    assert "('collector', 'traj_ids')" in message and "collector" in message.lower()
    assert "td.set(('collector', 'traj_ids')" in message


def test_cut_sequences_names_the_missing_key(rollout):
    with pytest.raises(
        ValueError, match=r"cut_sequences needs trajectory ids under \('collector', 'traj_ids'\)"
    ):
        cut_sequences(rollout, 5)
    with pytest.raises(ValueError, match=r"under 'episode'"):
        cut_sequences(rollout, 5, traj_key="episode")


def test_setting_the_ids_as_the_message_says_works(rollout):
    data = rollout.clone()
    data.set(("collector", "traj_ids"), torch.arange(30) // 10)
    assert cut_sequences(data, 5).shape == (6, 5)
    train, val = split_by_trajectory(data, 0.34, seed=0)
    assert (len(train), len(val)) == (20, 10)
