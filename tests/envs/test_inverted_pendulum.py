"""InvertedPendulum-v5 (MuJoCo, ``pip install "torchrl-recon[mujoco]"``): its shipped cost and
termination, and fits on its random episodes, all shorter than a training slice."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("mujoco", reason='needs MuJoCo: pip install "torchrl-recon[mujoco]"')

from torchrl_recon.collectors import collect_random  # noqa: E402
from torchrl_recon.data import TRAJ_KEY, needs_padding  # noqa: E402
from torchrl_recon.envs import close_env, make_env  # noqa: E402
from torchrl_recon.envs.gym_costs import inverted_pendulum, inverted_pendulum_fallen  # noqa: E402
from torchrl_recon.fitting.online import FitSchedule, fit_models  # noqa: E402
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty  # noqa: E402


@pytest.fixture(scope="module")
def random_data():
    env = make_env("InvertedPendulum-v5", seed=0)
    try:
        yield collect_random(env, frames=200, seed=0)
    finally:
        close_env(env)


def test_cost_and_termination_are_the_envs(random_data):
    obs, action = random_data["observation"], random_data["action"]
    next_obs = random_data["next", "observation"]
    fallen = inverted_pendulum_fallen(obs, action, next_obs)
    assert torch.equal(fallen, random_data["next", "terminated"].reshape(-1))
    reward = random_data["next", "reward"].reshape(-1)
    torch.testing.assert_close(inverted_pendulum(obs, action, next_obs), -reward)


def test_fits_on_random_episodes_shorter_than_a_slice(random_data):
    _, lengths = torch.unique_consecutive(random_data[TRAJ_KEY], return_counts=True)
    schedule = FitSchedule(steps=6, eval_every=3, slice_len=20, num_slices=8, val_fraction=0.2)
    assert int(lengths.max()) < schedule.slice_len and needs_padding(20, random_data)
    torch.manual_seed(0)
    model = LSTMWorldModel(4, 1, window=10, hidden_size=16, dense_size=16)
    ae = ReconstructionUncertainty(4, 1, window=10, hidden_size=16)
    losses = fit_models(model, ae, random_data, schedule, seed=0, warm=False)
    assert all(torch.isfinite(torch.tensor(v)) for v in losses.values()), losses
