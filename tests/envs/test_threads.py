"""TorchRL's batched envs reset torch's thread count when they close; ours keep the run's."""

from __future__ import annotations

import pytest
import torch

from torchrl_recon.collectors import collect_random
from torchrl_recon.envs import close_env, closing_env, keep_num_threads, make_env


def test_a_batched_collection_and_its_close_keep_one_thread():
    # On a machine with 2+ cores TorchRL set the count back to its import-time value (1 -> 2)
    # when the collector shut the SerialEnv down: a recipe's `threads: 1` became 2.
    with keep_num_threads():
        torch.set_num_threads(1)
        env = make_env("drone", seed=0, num_envs=2, parallel=False)
        collect_random(env, frames=40, seed=0)
        assert torch.get_num_threads() == 1
        close_env(env)
        assert env.is_closed and torch.get_num_threads() == 1


def test_closing_an_unused_batched_env_keeps_one_thread():
    with keep_num_threads():
        torch.set_num_threads(1)
        env = make_env("industrial_benchmark", seed=0, num_envs=3, parallel=False)
        env.rollout(3)
        close_env(env)
        close_env(env)  # closed already: nothing happens
        assert torch.get_num_threads() == 1


@pytest.mark.slow  # 9 s; the batched env closing on success is tested above
def test_a_failed_collection_closes_its_batched_env_and_keeps_one_thread():
    # A stage that raised (or was interrupted) mid-collection left its env open before
    # closing_env: a ParallelEnv's workers outlived the failed stage.
    with keep_num_threads():
        torch.set_num_threads(1)
        env = make_env("industrial_benchmark", seed=0, num_envs=2, parallel=True)
        try:
            with closing_env(env):
                env.rollout(2)
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            pass
        assert env.is_closed and torch.get_num_threads() == 1
