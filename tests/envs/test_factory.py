"""Tests of the TorchRL env factory (torchrl_recon.envs.factory.make_env) and the env registry."""

from __future__ import annotations

import math
from collections.abc import Iterator

import gymnasium as gym
import pytest
import torch
from torchrl.envs import GymEnv, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

import torchrl_recon  # noqa: F401  (registers the environments)
from torchrl_recon.envs import ENVS, get_entry, make_env

# Cheapest constructor arguments per env (Minitaur without self-collision is ~1.5x faster).
FAST_KWARGS: dict[str, dict] = {
    "industrial_benchmark": {},
    "drone": {},
    "minitaur": {"self_collision": False},
}
NAMES = list(FAST_KWARGS)
OBS_DIM = {"industrial_benchmark": 6, "drone": 12, "minitaur": 34}
ACT_DIM = {"industrial_benchmark": 3, "drone": 4, "minitaur": 8}
# Random-action rollout lengths (Minitaur steps cost ~1 ms each, the others ~0.1 ms).
STEPS = {"industrial_benchmark": 50, "drone": 50, "minitaur": 20}


@pytest.fixture
def build() -> Iterator:
    """``make_env`` that closes every env it built when the test ends."""
    envs = []

    def _build(name: str, **kwargs):
        env = make_env(name, **{"seed": 0, **FAST_KWARGS[get_entry(name).name], **kwargs})
        envs.append(env)
        return env

    yield _build
    for env in envs:
        if not env.is_closed:
            env.close()


def _rollout(env, steps: int, *, torch_seed: int = 0, **kwargs):
    # Without a policy, rollout draws actions from action_spec.rand(), i.e. torch's global RNG.
    torch.manual_seed(torch_seed)
    return env.rollout(steps, **kwargs)


def _assert_same_tensordict(td1, td2) -> None:
    keys1 = set(td1.keys(True, True))
    assert keys1 == set(td2.keys(True, True))
    for key in keys1:
        torch.testing.assert_close(td1[key], td2[key], rtol=0, atol=0, msg=f"{key} differs")


# --------------------------------------------------------------------------- single envs


@pytest.mark.parametrize("name", NAMES)
def test_specs_and_float32(build, name):
    env = build(name)
    assert isinstance(env, TransformedEnv)
    assert isinstance(env.base_env, GymEnv)
    assert env.batch_size == torch.Size([])
    check_env_specs(env)

    assert env.observation_spec["observation"].dtype == torch.float32
    assert env.observation_spec["observation"].shape == (OBS_DIM[name],)
    assert env.action_spec.shape == (ACT_DIM[name],)
    assert env.reward_spec.dtype == torch.float32
    td = _rollout(env, 5)
    for key in ("observation", ("next", "observation"), ("next", "reward"), "action"):
        assert td[key].dtype == torch.float32, key
    assert td["observation"].shape == (td.shape[0], OBS_DIM[name])
    # The transforms every recipe expects are there.
    assert td["is_init"][0].item() and not td["is_init"][1:].any()
    assert td["next", "step_count"][:, 0].tolist() == list(range(1, td.shape[0] + 1))


@pytest.mark.parametrize("name", NAMES)
def test_rollout_reproducible(build, name):
    td1 = _rollout(build(name, seed=3), STEPS[name])
    td2 = _rollout(build(name, seed=3), STEPS[name])
    _assert_same_tensordict(td1, td2)
    if name != "minitaur":  # Minitaur's reset is deterministic, the others draw a start state
        td3 = _rollout(build(name, seed=4), STEPS[name])
        assert not torch.equal(td1["observation"][0], td3["observation"][0])


@pytest.mark.parametrize("name", NAMES)
def test_cost_fn_equals_minus_reward(build, name):
    env = build(name)
    # break_when_any_done=False: a Drone crash resets mid-rollout, the identity must still hold.
    td = _rollout(env, STEPS[name], break_when_any_done=False)
    cost = get_entry(name).cost_fn()(td["observation"], td["action"], td["next", "observation"])
    assert cost.shape == td.shape
    torch.testing.assert_close(cost, -td["next", "reward"].squeeze(-1))


def test_minitaur_squared_cost_equals_minus_reward(build):
    env = build("minitaur", cost="squared")
    td = _rollout(env, STEPS["minitaur"])
    cost = get_entry("minitaur").cost_fn()(
        td["observation"], td["action"], td["next", "observation"], cost="squared"
    )
    torch.testing.assert_close(cost, -td["next", "reward"].squeeze(-1))


@pytest.mark.parametrize("name", NAMES)
def test_short_name_and_gym_id(build, name):
    gym_id = get_entry(name).gym_id
    assert gym_id in gym.registry
    assert get_entry(gym_id) is get_entry(name) is ENVS[name]
    td_short = _rollout(build(name), 3)
    td_id = _rollout(build(gym_id), 3)
    _assert_same_tensordict(td_short, td_id)


def test_env_kwargs_reach_the_gym_env(build):
    env = build("drone", goal=(0.0, 0.0, 1.0), start_noise=0.0)
    unwrapped = env.base_env._env.unwrapped
    assert unwrapped.start_noise == 0.0
    td = _rollout(env, 5)
    cost = get_entry("drone").cost_fn()(
        td["observation"], td["action"], td["next", "observation"], goal=(0.0, 0.0, 1.0)
    )
    torch.testing.assert_close(cost, -td["next", "reward"].squeeze(-1))


# --------------------------------------------------------------------------- batched envs


def _check_batched(env, cls) -> None:
    assert isinstance(env, TransformedEnv)
    assert isinstance(env.base_env, cls)
    assert env.batch_size == torch.Size([2])
    check_env_specs(env)
    td = _rollout(env, 4)
    assert td.shape == (2, 4)
    assert td["observation"].dtype == torch.float32
    # Different seeds per sub-env: the start states differ.
    assert not torch.equal(td["observation"][0, 0], td["observation"][1, 0])


@pytest.mark.slow  # 12 s of process start-up; the batched env tests cover num_envs
def test_parallel_env(build):
    # The only ParallelEnv test: worker processes take seconds to start. Under pytest the
    # spawned workers never import torchrl_recon through __main__, so this also checks that the
    # factory registers the gymnasium ids inside the workers.
    env = build("drone", num_envs=2)
    _check_batched(env, ParallelEnv)


def test_serial_env(build):
    env = build("industrial_benchmark", num_envs=2, parallel=False)
    _check_batched(env, SerialEnv)
    # The first sub-env is seeded with ``seed``: it matches the single env of the same seed.
    batched = _rollout(build("industrial_benchmark", seed=5, num_envs=2, parallel=False), 3)
    single = _rollout(build("industrial_benchmark", seed=5), 3)
    torch.testing.assert_close(batched["observation"][0, 0], single["observation"][0])


def test_serial_env_minitaur_kwargs(build):
    env = build("minitaur", num_envs=2, parallel=False)
    assert env.batch_size == torch.Size([2])
    assert all(not sub._env.unwrapped.self_collision for sub in env.base_env._envs)
    td = _rollout(env, 3)
    assert td.shape == (2, 3)
    cost = get_entry("minitaur").cost_fn()(
        td["observation"], td["action"], td["next", "observation"]
    )
    torch.testing.assert_close(cost, -td["next", "reward"].squeeze(-1))


# --------------------------------------------------------------------------- truncation


def test_max_episode_steps_truncates(build):
    env = build("industrial_benchmark", max_episode_steps=7)  # IB never terminates
    td = _rollout(env, 20)
    assert td.shape == (7,)
    assert td["next", "truncated"][-1].item() and td["next", "done"][-1].item()
    assert not td["next", "truncated"][:-1].any()
    assert not td["next", "terminated"].any()

    td = _rollout(env, 20, break_when_any_done=False)
    truncated = td["next", "truncated"].squeeze(-1).nonzero().squeeze(-1).tolist()
    assert truncated == [6, 13]
    assert td["next", "step_count"][:, 0].tolist()[:8] == [1, 2, 3, 4, 5, 6, 7, 1]


def test_max_episode_steps_batched(build):
    env = build("industrial_benchmark", max_episode_steps=7, num_envs=2, parallel=False)
    td = _rollout(env, 20)
    assert td.shape == (2, 7)
    assert td["next", "truncated"][:, -1].all() and not td["next", "truncated"][:, :-1].any()


def test_default_limit_is_the_registered_one(build):
    env = build("industrial_benchmark")
    td = _rollout(env, 20)
    assert td.shape == (20,)
    assert not td["next", "done"].any()


# --------------------------------------------------------------------------- bad input


def test_unknown_name_lists_known_names():
    with pytest.raises(ValueError, match="Unknown environment 'pendulum'") as info:
        make_env("pendulum", seed=0)
    for entry in ENVS.values():
        assert repr(entry.name) in str(info.value)
        assert repr(entry.gym_id) in str(info.value)


def test_unknown_keyword_is_named():
    with pytest.raises(TypeError, match="not_a_kwarg"):
        make_env("drone", seed=0, not_a_kwarg=1)
    with pytest.raises(TypeError, match="setpont"):
        make_env("industrial_benchmark", seed=0, setpont=60.0)


@pytest.mark.parametrize("num_envs", [0, -1, 1.5, "2"])
def test_bad_num_envs(num_envs):
    with pytest.raises(ValueError, match="num_envs"):
        make_env("drone", seed=0, num_envs=num_envs)


@pytest.mark.parametrize("max_episode_steps", [0, -3, 2.5])
def test_bad_max_episode_steps(max_episode_steps):
    with pytest.raises(ValueError, match="max_episode_steps"):
        make_env("drone", seed=0, max_episode_steps=max_episode_steps)


def test_seed_is_required_and_int():
    with pytest.raises(TypeError):
        make_env("drone")  # keyword-only and required
    with pytest.raises(TypeError, match="seed"):
        make_env("drone", seed=1.5)


@pytest.mark.parametrize("name", ["industrial_benchmark", "drone"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_action_raises(build, name, bad):
    # The env's ValueError surfaces unchanged through GymEnv and the transforms.
    env = build(name)
    td = env.reset()
    td["action"] = torch.zeros(ACT_DIM[name])
    td["action"][1] = bad
    with pytest.raises(ValueError, match="NaN"):
        env.step(td)


def test_nan_action_raises_minitaur(build):
    env = build("minitaur")
    td = env.reset()
    td["action"] = torch.full((ACT_DIM["minitaur"],), math.nan)
    with pytest.raises(ValueError, match="NaN"):
        env.step(td)


class _DictObsEnv(gym.Env):
    """A gymnasium env whose observation is a Dict: make_env must refuse it by name."""

    def __init__(self):
        import numpy as np

        self.observation_space = gym.spaces.Dict(
            {"position": gym.spaces.Box(-1, 1, (2,), np.float32)}
        )
        self.action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return {"position": self.observation_space["position"].sample()}, {}

    def step(self, action):
        return {"position": self.observation_space["position"].sample()}, 0.0, False, False, {}


def test_make_env_refuses_dict_observations_and_discrete_actions():
    if "DictObsTest-v0" not in gym.registry:
        gym.register(id="DictObsTest-v0", entry_point=_DictObsEnv)
    with pytest.raises(ValueError, match=r"'DictObsTest-v0' has observations .*FlattenObservation"):
        make_env("DictObsTest-v0", seed=0)
    with pytest.raises(ValueError, match=r"'CartPole-v1' has a discrete action space"):
        make_env("CartPole-v1", seed=0)
