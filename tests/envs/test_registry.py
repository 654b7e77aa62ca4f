from __future__ import annotations

import gymnasium as gym
import pytest

import torchrl_recon  # noqa: F401  (registers the envs)
from torchrl_recon.envs import ENVS


@pytest.mark.parametrize("name", sorted(ENVS))
def test_state_names_match_the_observation(name):
    entry = ENVS[name]
    kwargs = {"self_collision": False} if name == "minitaur" else {}
    env = gym.make(entry.gym_id, **kwargs)
    try:
        assert env.observation_space.shape == (len(entry.state_names),)
        assert len(set(entry.state_names)) == len(entry.state_names)
    finally:
        env.close()
