from __future__ import annotations

import warnings

import torch

from torchrl_recon.collectors import collect_random
from torchrl_recon.collectors.random_data import default_frames_per_batch
from torchrl_recon.envs import make_env


def test_default_batches_divide_the_frames_when_they_can():
    assert default_frames_per_batch(15000) == 1000
    assert default_frames_per_batch(1500) == 750
    assert default_frames_per_batch(50) == 50
    assert default_frames_per_batch(1499) == 1000  # prime: its only divisors are 1 and 1499


def test_odd_frame_counts_collect_no_extra_steps_and_the_same_data():
    def data(frames_per_batch):
        env = make_env("industrial_benchmark", seed=0, max_episode_steps=100)
        return collect_random(env, frames=1500, seed=3, frames_per_batch=frames_per_batch)

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # TorchRL warns when a batch would overshoot
        divided = data(None)
    overshooting = data(1000)
    assert divided.batch_size == overshooting.batch_size == torch.Size([1500])
    assert torch.equal(divided["observation"], overshooting["observation"])
    assert torch.equal(divided["action"], overshooting["action"])
