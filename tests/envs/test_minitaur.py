"""Tests for ``torchrl_recon/Minitaur-v0`` (behaviour documented in docs/envs/minitaur.md).

pybullet runs at a few hundred env steps/s here, so episodes are short and most tests turn
self-collision off (the reset state and the standing test do not depend on it).
"""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pybullet
import pytest
import torch

import torchrl_recon  # noqa: F401  (registers the gymnasium ids)
from torchrl_recon.envs.minitaur import MinitaurEnv, minitaur_cost
from torchrl_recon.envs.registry import get_entry


@pytest.fixture
def env():
    e = MinitaurEnv(self_collision=False)
    yield e
    e.close()


def _rollout(env: MinitaurEnv, actions: np.ndarray, seed: int = 0):
    obs, _ = env.reset(seed=seed)
    observations, rewards, terminated, infos = [obs], [], [], []
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        assert not trunc
        observations.append(obs)
        rewards.append(r)
        terminated.append(term)
        infos.append(info)
        if term:
            break
    return np.stack(observations), np.array(rewards), np.array(terminated), infos


def _random_actions(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (n, 8)).astype(np.float32)


# --- spec section 11, check 1 ---------------------------------------------------------------
def test_reset_state_matches_reference_settle():
    e = MinitaurEnv()  # reference setting: self-collision on
    try:
        obs, info = e.reset(seed=0)
        assert obs.shape == (34,) and obs.dtype == np.float32
        assert np.all(np.isfinite(obs))
        assert 0.15 <= obs[30] <= 0.17  # base height after the 100-step settle
        assert np.all((obs[:8] >= 1.4) & (obs[:8] <= 1.6))  # motor angles near pi/2
        assert np.all(np.abs(obs[16:24]) <= 5.7)
        assert obs[28] == 0.0 and obs[29] == 0.0  # displacement measured from the reset pose
        assert info == {"forward_progress": 0.0, "reference_reward": 0.0}
        assert e.observation_space.contains(obs)
    finally:
        e.close()


# --- check 2 ----------------------------------------------------------------------------------
def test_same_seed_same_actions_bit_identical(env):
    actions = _random_actions(80, seed=1)
    first = _rollout(env, actions, seed=3)
    second = _rollout(env, actions, seed=3)
    assert np.array_equal(first[0], second[0])
    assert np.array_equal(first[1], second[1])
    assert np.array_equal(first[2], second[2])


# --- check 3 (200 steps instead of 500 to keep the suite fast) --------------------------------
def test_zero_leg_action_keeps_standing(env):
    obs, rewards, terminated, _ = _rollout(env, np.zeros((200, 8), dtype=np.float32))
    assert len(rewards) == 200 and not terminated.any()
    assert obs[-1, 30] > 0.18  # legs extend to the a = 0 pose (~0.20 m)
    assert np.all(np.abs(obs[-1, :8] - 1.85) < 0.15)
    assert abs(obs[-1, 28]) < 0.05


# --- check 4 ----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("action_mode", "orientation", "height"),
    [
        ("leg", (1.0, 0.0, 0.0, 0.0), 0.3),  # upside down
        ("leg", pybullet.getQuaternionFromEuler((math.radians(40), 0.0, 0.0)), 0.3),  # 40 deg roll
        ("pwm", pybullet.getQuaternionFromEuler((0.0, math.radians(45), 0.0)), 0.3),  # 45 deg pitch
    ],
)
def test_tilt_terminates(action_mode, orientation, height):
    e = MinitaurEnv(action_mode=action_mode, self_collision=False)
    try:
        e.reset(seed=0)
        pybullet.resetBasePositionAndOrientation(
            e.robot_id, (0.0, 0.0, height), orientation, physicsClientId=e.client_id
        )
        _, _, terminated, truncated, _ = e.step(np.zeros(8, dtype=np.float32))
        assert terminated and not truncated
    finally:
        e.close()


def test_pwm_mode_starts_standing_and_ignores_height_test():
    e = MinitaurEnv(action_mode="pwm", self_collision=False)
    try:
        obs, _, terminated, _ = _rollout(e, np.zeros((100, 8), dtype=np.float32))
        assert 0.15 <= obs[0, 30] <= 0.17  # same PD settle as "leg" mode
        assert obs[-1, 30] < 0.13  # collapsed without motor torque ...
        assert not terminated.any()  # ... but only the tilt test ends a PWM episode
    finally:
        e.close()


# --- check 5 ----------------------------------------------------------------------------------
def test_reference_reward_recomputed_from_observations(env):
    obs, _, _, infos = _rollout(env, _random_actions(60, seed=2))
    forward = np.diff(obs[:, 28].astype(np.float64))
    energy = np.abs(np.einsum("ti,ti->t", obs[1:, 16:24].astype(np.float64), obs[1:, 8:16])) * 0.002
    expected = forward - 0.005 * energy
    got = np.array([i["reference_reward"] for i in infos])
    progress = np.array([i["forward_progress"] for i in infos])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose(progress, forward, rtol=0, atol=1e-6)
    assert abs(progress.sum() - obs[-1, 28]) < 1e-6


# --- check 6 ----------------------------------------------------------------------------------
def test_check_env_passes(env):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    messages = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert not [m for m in messages if "observation" in m.lower() or "bound" in m.lower()], messages


def test_gymnasium_make_registers_time_limit():
    e = gym.make("torchrl_recon/Minitaur-v0", self_collision=False)
    try:
        assert e.spec.max_episode_steps == 500
        assert isinstance(e.unwrapped, MinitaurEnv)
        assert e.action_space.shape == (8,) and e.observation_space.shape == (34,)
    finally:
        e.close()
    assert get_entry("minitaur").cost_fn() is minitaur_cost


# --- several clients in one process -------------------------------------------------------------
def test_two_envs_are_independent():
    a, b = MinitaurEnv(self_collision=False), MinitaurEnv(self_collision=False)
    try:
        assert a.client_id != b.client_id
        xs, ys = _random_actions(30, seed=4), _random_actions(30, seed=5)
        solo, _, _, _ = _rollout(a, xs)
        obs_a, _ = a.reset(seed=0)
        obs_b, _ = b.reset(seed=0)
        traj_a, traj_b = [obs_a], [obs_b]
        for x, y in zip(xs, ys, strict=True):  # interleave the two simulations
            traj_a.append(a.step(x)[0])
            traj_b.append(b.step(y)[0])
        assert np.array_equal(np.stack(traj_a), solo)
        assert not np.array_equal(np.stack(traj_b), solo)
    finally:
        a.close()
        b.close()


def test_close_disconnects_and_is_idempotent():
    e = MinitaurEnv(self_collision=False)
    e.reset(seed=0)
    client = e.client_id
    assert pybullet.isConnected(physicsClientId=client)
    e.close()
    assert not pybullet.isConnected(physicsClientId=client)
    e.close()  # harmless
    with pytest.raises(RuntimeError, match="closed"):
        e.step(np.zeros(8, dtype=np.float32))


# --- torch cost ---------------------------------------------------------------------------------
@pytest.mark.parametrize("cost", ["signed", "squared"])
def test_torch_cost_equals_minus_reward(cost):
    e = MinitaurEnv(cost=cost, self_collision=False)
    try:
        actions = _random_actions(40, seed=6)
        obs, rewards, _, _ = _rollout(e, actions)
    finally:
        e.close()
    n = len(rewards)
    c = minitaur_cost(
        torch.from_numpy(obs[:-1]),
        torch.from_numpy(actions[:n]),
        torch.from_numpy(obs[1:]),
        cost=cost,
    )
    assert c.shape == (n,)
    assert torch.equal(c.double(), -torch.from_numpy(rewards))


def test_torch_cost_batched_signed_and_differentiable():
    next_obs = torch.zeros(2, 3, 34)
    next_obs[..., 28] = torch.tensor([[0.5, -0.5, 0.0], [1.0, -2.0, 0.1]])
    next_obs.requires_grad_(True)
    signed = minitaur_cost(torch.zeros(2, 3, 34), torch.zeros(2, 3, 8), next_obs)
    squared = minitaur_cost(torch.zeros(2, 3, 34), torch.zeros(2, 3, 8), next_obs, cost="squared")
    assert signed.shape == (2, 3) and squared.shape == (2, 3)
    assert torch.allclose(signed, torch.tensor([[-0.25, 0.25, 0.0], [-1.0, 4.0, -0.01]]))
    assert torch.allclose(squared, torch.tensor([[-0.25, -0.25, 0.0], [-1.0, -4.0, -0.01]]))
    signed.sum().backward()
    grad = next_obs.grad[..., 28]
    assert torch.allclose(grad, -2 * next_obs.detach()[..., 28].abs())
    assert next_obs.grad[..., :28].abs().sum() == 0
    with pytest.raises(ValueError, match="cost"):
        minitaur_cost(torch.zeros(34), torch.zeros(8), torch.zeros(34), cost="abs")


# --- bad input ----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("action", "pattern"),
    [
        (np.zeros(7), r"shape \(7,\)"),
        (np.zeros((2, 8)), r"shape \(2, 8\)"),
        (np.array([0.0] * 7 + [np.nan]), "nan"),
        (np.array([np.inf] + [0.0] * 7), "inf"),
    ],
)
def test_bad_actions_raise(env, action, pattern):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=pattern):
        env.step(action)


def test_out_of_range_action_is_clipped(env):
    big = np.array([5.0, -3.0, 1.5, -1.2, 2.0, -9.0, 1.0, 0.0])
    clipped = np.clip(big, -1.0, 1.0)
    env.reset(seed=0)
    obs_big = env.step(big)[0]
    env.reset(seed=0)
    obs_clipped = env.step(clipped)[0]
    assert np.array_equal(obs_big, obs_clipped)


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"action_mode": "torque"}, "action_mode"),
        ({"cost": "abs"}, "cost"),
        ({"render_mode": "human"}, "render_mode"),
    ],
)
def test_bad_keywords_raise(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        MinitaurEnv(**kwargs)


# --- options ------------------------------------------------------------------------------------
def test_randomize_dynamics_uses_the_seed():
    e = MinitaurEnv(self_collision=False, randomize_dynamics=True)
    try:
        a, _ = e.reset(seed=1)
        b, _ = e.reset(seed=1)
        c, _ = e.reset(seed=2)
    finally:
        e.close()
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_default_start_does_not_depend_on_seed(env):
    a, _ = env.reset(seed=1)
    b, _ = env.reset(seed=2)
    assert np.array_equal(a, b)


def test_render_rgb_array():
    e = MinitaurEnv(self_collision=False, render_mode="rgb_array", render_size=(64, 48))
    try:
        e.reset(seed=0)
        frame = e.render()
    finally:
        e.close()
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
