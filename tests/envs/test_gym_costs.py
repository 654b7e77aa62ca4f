"""The shipped costs and terminations of standard gymnasium tasks, against the envs themselves."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from torchrl_recon.envs.gym_costs import (
    mountain_car,
    mountain_car_energy,
    mountain_car_termination,
    pendulum,
)


def _steps(gym_id: str, actions: np.ndarray, seed: int = 0, reset_state=None):
    env = gym.make(gym_id)
    obs, _ = env.reset(seed=seed)
    if reset_state is not None:
        env.unwrapped.state = np.array(reset_state, dtype=np.float64)
        obs = np.array(reset_state, dtype=np.float32)
    rows = []
    for a in actions:
        next_obs, reward, terminated, _, _ = env.step(a)
        rows.append((obs, a, next_obs, reward, terminated))
        obs = next_obs
        if terminated:
            break
    env.close()
    o, a, n, r, t = (
        torch.as_tensor(np.array(x), dtype=torch.float32) for x in zip(*rows, strict=True)
    )
    return o, a, n, r, t.bool()


def test_pendulum_cost_is_the_negative_reward():
    o, a, n, r, _ = _steps("Pendulum-v1", np.random.default_rng(0).uniform(-2, 2, (50, 1)))
    torch.testing.assert_close(pendulum(o, a, n), -r, rtol=1e-4, atol=1e-4)


def test_mountain_car_termination_matches_the_env():
    # full throttle from just below the goal, moving right: the env ends the episode
    o, a, n, _, t = _steps("MountainCarContinuous-v0", np.ones((30, 1)), reset_state=[0.4, 0.03])
    assert t[-1] and not t[:-1].any()
    assert torch.equal(mountain_car_termination(o, a, n), t)


def test_mountain_car_energy_is_what_the_engine_changes():
    span = 1.65e-3  # energy from the valley's bottom to the goal
    o, _, n, _, _ = _steps("MountainCarContinuous-v0", np.zeros((40, 1)), reset_state=[-0.3, 0.0])
    coasting = mountain_car_energy(torch.cat([o[:1], n]))
    assert (coasting - coasting[0]).abs().max() < 0.02 * span  # Euler steps: about conserved
    o, _, n, _, _ = _steps("MountainCarContinuous-v0", np.ones((40, 1)), reset_state=[-0.5, 0.0])
    pushed = mountain_car_energy(torch.cat([o[:1], n]))
    assert pushed[-1] - pushed[0] > 0.2 * span


def test_mountain_car_cost_falls_as_the_car_gains_energy():
    low, high = torch.tensor([[-0.5, 0.0]]), torch.tensor([[-0.5, 0.05]])
    assert mountain_car(low, torch.zeros(1, 1), high) < mountain_car(low, torch.zeros(1, 1), low)
    goal = torch.tensor([[0.45, 0.0]])
    assert mountain_car(goal, torch.zeros(1, 1), goal) == 0
