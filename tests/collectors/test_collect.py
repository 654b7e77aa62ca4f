from __future__ import annotations

import re
import warnings
from functools import partial

import pytest
import torch

from torchrl_recon.collectors import collect_random
from torchrl_recon.collectors.random_data import default_frames_per_batch
from torchrl_recon.envs import make_env


def test_default_batches_divide_the_frames_when_they_can():
    assert default_frames_per_batch(15000) == 1000
    assert default_frames_per_batch(1500) == 750
    assert default_frames_per_batch(50) == 50
    # prime: its only divisors up to 1000 are 1 and itself; the fewest near-equal batches
    assert default_frames_per_batch(1499) == 750  # 2 batches, 1 step dropped
    assert default_frames_per_batch(1019) == 510
    assert default_frames_per_batch(2003) == 668  # 3 batches of 668: 2004, 1 dropped


@pytest.mark.slow  # 6-9 s each; the other collect tests run in make test
@pytest.mark.parametrize("frames", [1500, 1019])
def test_odd_frame_counts_collect_few_extra_steps_and_the_same_data(frames):
    """1500 in batches of 750, 1019 in two of 510 (one step dropped): no TorchRL warning, and
    the data of batches of 1000 (981 steps collected and dropped for 1019), bit for bit."""

    def data(frames_per_batch):
        env = make_env("industrial_benchmark", seed=0, max_episode_steps=100)
        return collect_random(env, frames=frames, seed=3, frames_per_batch=frames_per_batch)

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # TorchRL warns when a batch would overshoot
        default = data(None)
    overshooting = data(1000)
    assert default.batch_size == overshooting.batch_size == torch.Size([frames])
    assert set(default.keys(True, True)) == set(overshooting.keys(True, True))
    for key in default.keys(True, True):
        assert torch.equal(default[key], overshooting[key]), key


def test_a_batch_of_envs_gives_env_major_contiguous_trajectories():
    def data():
        env = make_env("drone", seed=0, num_envs=3, parallel=False, max_episode_steps=10)
        return collect_random(env, frames=50, seed=1, frames_per_batch=30)

    first, again = data(), data()
    assert first.batch_size == torch.Size([50])  # 3 x 20 collected, the last env's tail dropped
    assert torch.equal(first["observation"], again["observation"])
    ids = first["collector", "traj_ids"]
    # env 0's two episodes, env 1's two, then 10 steps of env 2: each id one block
    assert ids.tolist() == [0] * 10 + [3] * 10 + [1] * 10 + [4] * 10 + [2] * 10
    assert (first["step_count"].squeeze(-1) == torch.arange(10).repeat(5)).all()


def test_validation_trajectories_from_a_batch_are_complete_and_spread_their_offsets():
    from torchrl_recon.collectors import validation_trajectories

    # A drone tilting past 0.005 rad ends early: rows are discarded and drawn again.
    env = make_env("drone", seed=0, num_envs=4, parallel=False, max_tilt=0.005)
    draw = partial(validation_trajectories, env, count=6, length=12, seed=0, policy="offset_noise")
    with pytest.raises(RuntimeError, match=r"Only \d of 6 trajectories reached 12 steps in 8"):
        draw(max_attempts=8)  # two batches of 4 rows are not enough
    val = draw()
    assert val.batch_size == torch.Size([6, 12])
    assert not val["next", "done"][:, :-1].any()
    assert (val["step_count"].squeeze(-1) == torch.arange(12)).all()
    # trajectory k has offset magnitude (k % 4) / 3: magnitude 0 leaves actions in [-0.5, 0.5]
    assert val["action"][0].abs().max() <= 0.5 and val["action"][4].abs().max() <= 0.5
    assert val["action"][3].abs().max() > 0.5


@pytest.mark.parametrize("num_envs", [1, 3])
def test_every_trajectory_starts_where_its_env_was_reset_and_no_start_repeats(num_envs):
    # Seeding after the collector's first reset used to put the env back at its seed's start
    # while the collector kept the first reset's observation: the first transition jumped
    # (0.17 in position where a step moves < 1e-3) and the next episode repeated that start.
    env = make_env("drone", seed=0, max_episode_steps=30, num_envs=num_envs, parallel=False)
    data = collect_random(env, frames=180 * num_envs, seed=0)
    ids = data["collector", "traj_ids"]
    position_step = (data["next", "observation"] - data["observation"])[:, :3].abs().amax(-1)
    assert position_step.max() < 1e-2, position_step.argmax()
    first = torch.cat([torch.tensor([True]), ids[1:] != ids[:-1]])
    starts = data["observation"][first]
    assert len(starts) >= 6 * num_envs
    assert torch.unique(starts, dim=0).shape[0] == starts.shape[0]


def test_episodes_stop_at_that_many_whole_episodes_and_leave_full_ones_unchanged():
    # Pendulum never terminates: 3 episodes of 20 steps fill a 60-step budget exactly
    env = partial(make_env, "Pendulum-v1", seed=0, max_episode_steps=20)
    whole = collect_random(env(), frames=60, seed=0)
    counted = collect_random(env(), frames=60, seed=0, episodes=3)
    assert torch.equal(whole["action"], counted["action"])
    # a drone under random actions crashes early: 4 episodes, far below the 4 × 500 budget
    drone = make_env("drone", seed=0, max_episode_steps=500)
    data = collect_random(drone, frames=2000, seed=0, frames_per_batch=100, episodes=4)
    done = data["next", "done"].reshape(len(data), -1).any(-1)
    assert int(done.sum()) == 4 and bool(done[-1]) and len(data) < 2000
    assert data["collector", "traj_ids"].unique().numel() == 4


def test_episodes_refuse_a_batched_env():
    env = make_env("drone", seed=0, num_envs=2, parallel=False)
    with pytest.raises(ValueError, match="episodes=2 needs a count >= 1 and one env"):
        collect_random(env, frames=100, seed=0, episodes=2)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"frames": 2.5}, "frames must be an int >= 1, got 2.5."),
        ({"frames": 0}, "frames must be an int >= 1, got 0."),
        ({"frames": 10, "frames_per_batch": 0}, "frames_per_batch must be an int >= 1, got 0."),
    ],
)
def test_a_frame_count_that_is_not_a_positive_int_is_refused(kwargs, message):
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=10)
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        collect_random(env, seed=0, **kwargs)
