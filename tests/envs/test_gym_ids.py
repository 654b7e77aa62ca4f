"""make_env takes any gymnasium id, including ``module:EnvId`` for a user's own module."""

from __future__ import annotations

import textwrap
import uuid

import pytest
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv

from torchrl_recon.envs import ENVS, GymEntry, get_entry, make_env, register_env, registry

USER_MODULE = '''
import gymnasium as gym
import numpy as np
import torch


class TinyEnv(gym.Env):
    """s' = s + a in 2-D, actions in [-0.5, 0.5]."""

    def __init__(self, start: float = 1.0):
        self.start = start
        self.observation_space = gym.spaces.Box(-10.0, 10.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-0.5, 0.5, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.s = np.full(2, self.start, np.float32)
        return self.s.copy(), {}

    def step(self, action):
        self.s = (self.s + np.asarray(action, np.float32)).clip(-10, 10)
        return self.s.copy(), -float((self.s ** 2).sum()), False, False, {}


def tiny_cost(obs, action, next_obs):
    return next_obs.pow(2).sum(-1)


gym.register(id="{env_id}", entry_point="{module}:TinyEnv", max_episode_steps=12)
'''


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """A user's module on sys.path that registers ``TinyUser<hex>-v0`` when imported."""
    suffix = uuid.uuid4().hex[:8]
    module, env_id = f"byoenv_user_{suffix}", f"TinyUser{suffix}-v0"
    (tmp_path / f"{module}.py").write_text(
        textwrap.dedent(USER_MODULE).replace("{env_id}", env_id).replace("{module}", module)
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "USER_ENVS", {})
    return module, env_id


def pendulum_cost(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    return torch.atan2(obs[..., 1], obs[..., 0]).pow(2) + 0.1 * obs[..., 2].pow(2)


def test_a_gymnasium_id_makes_the_usual_torchrl_env():
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=7)
    td = env.rollout(20)
    assert td.shape == (7,) and td["next", "truncated"][-1].item()
    assert td["observation"].dtype == torch.float32 and td["observation"].shape == (7, 3)
    assert {"is_init", "step_count"} <= set(td.keys())
    assert env.action_spec.space.low.tolist() == [-2.0]
    env.close()


def test_a_generic_entry_has_the_gym_class_and_keywords_but_no_cost():
    entry = get_entry("Pendulum-v1")
    assert isinstance(entry, GymEntry) and entry.env_class() is PendulumEnv
    assert entry.max_episode_steps == 200 and entry.state_names == ()
    assert "g" in entry.keywords()
    with pytest.raises(TypeError, match="gravity"):
        make_env("Pendulum-v1", seed=0, gravity=3.0)
    make_env("Pendulum-v1", seed=0, g=3.0).close()
    with pytest.raises(ValueError, match=r"no torch cost.*register_env\('Pendulum-v1'"):
        entry.cost_fn()


def test_register_env_gives_a_name_and_a_cost(monkeypatch):
    monkeypatch.setattr(registry, "USER_ENVS", {})
    register_env(
        "Pendulum-v1",
        name="pendulum",
        cost=f"{__name__}:pendulum_cost",
        state_names=("cos", "sin", "omega"),
    )
    assert get_entry("pendulum").cost_fn() is pendulum_cost
    assert make_env("pendulum", seed=0).rollout(2)["observation"].shape == (2, 3)
    register_env(
        "Pendulum-v1",
        name="pendulum",
        cost=f"{__name__}:pendulum_cost",
        state_names=("cos", "sin", "omega"),
    )  # the same again: a no-op
    with pytest.raises(ValueError, match="already registered"):
        register_env("Pendulum-v1", name="pendulum")
    with pytest.raises(ValueError, match="shipped environment"):
        register_env("Pendulum-v1", name="drone")
    with pytest.raises(ValueError, match="module:function"):
        register_env("Pendulum-v1", name="p2", cost="pendulum_cost")


def test_module_colon_id_imports_the_users_module(user_module):
    module, env_id = user_module
    name = f"{module}:{env_id}"
    env = make_env(name, seed=0, start=2.0)
    td = env.rollout(50, lambda td: td.set("action", torch.full((2,), -0.5)))
    assert td.shape == (12,)  # the user's registration's episode limit
    assert td["next", "observation"][0].tolist() == [1.5, 1.5]
    assert env.action_spec.space.high.tolist() == [0.5, 0.5]
    env.close()
    entry = get_entry(name)
    assert entry.keywords() == {"start": 1.0}
    register_env(name, name="tiny", cost=f"{module}:tiny_cost")
    cost = get_entry("tiny").cost_fn()
    assert cost(td["observation"], td["action"], td["next", "observation"]).shape == (12,)


def test_module_colon_id_in_a_batch_of_envs(user_module):
    # Each env is built from the "module:EnvId" string, so ParallelEnv's spawned workers import
    # the module themselves (checked by hand: ~30 s of process start-up, too slow for the suite).
    module, env_id = user_module
    env = make_env(f"{module}:{env_id}", seed=0, num_envs=2, parallel=False)
    try:
        td = env.rollout(3)
        assert td.shape == (2, 3) and td["observation"].shape == (2, 3, 2)
    finally:
        env.close()


@pytest.mark.parametrize(
    "name, match",
    [
        (
            "NoSuchEnv-v0",
            r"Unknown environment 'NoSuchEnv-v0'.*gymnasium\.register\(id='NoSuchEnv-v0'",
        ),
        ("pendulum_typo", r"Unknown environment 'pendulum_typo'.*'drone'"),
        ("no_such_module_xyz:Foo-v0", r"cannot import module 'no_such_module_xyz'"),
    ],
)
def test_an_unknown_id_is_one_clear_error(name, match):
    with pytest.raises(ValueError, match=match):
        make_env(name, seed=0)


def test_shipped_entries_are_unchanged():
    assert get_entry("drone") is ENVS["drone"]
    assert not isinstance(get_entry("torchrl_recon/Minitaur-v0"), GymEntry)


def test_a_module_that_fails_while_importing_is_one_error_naming_it(tmp_path, monkeypatch):
    (tmp_path / "broken_env_module.py").write_text("raise RuntimeError('boom at import')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(
        ValueError,
        match=r"^Environment 'broken_env_module:Foo-v0': importing module 'broken_env_module' "
        r"failed: RuntimeError: boom at import$",
    ):
        make_env("broken_env_module:Foo-v0", seed=0)
