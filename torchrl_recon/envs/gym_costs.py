"""Batched torch costs of standard gymnasium tasks, for ``env.cost`` in recipes.

Each is the negative of the env's own reward, so predicted and real costs compare:
``env.id=Pendulum-v1 env.cost=torchrl_recon.envs.gym_costs:pendulum``.
"""

from __future__ import annotations

import torch


def pendulum(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """Pendulum-v1's cost θ² + 0.1·θ̇² + 0.001·u² of the state a step starts from (θ from
    cos θ, sin θ), ``[..., 3]``, ``[..., 1]`` → ``[...]``.

    Examples:
        >>> pendulum(torch.tensor([[1.0, 0.0, 2.0]]), torch.tensor([[1.0]]), torch.zeros(1, 3))
        tensor([0.4010])
    """
    theta = torch.atan2(obs[..., 1], obs[..., 0])
    return theta.pow(2) + 0.1 * obs[..., 2].pow(2) + 0.001 * action[..., 0].pow(2)


def inverted_pendulum_fallen(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """InvertedPendulum-v5's termination: the state a step reaches is not finite or its pole
    angle (``obs[1]``) is past 0.2 rad, ``[..., 4]`` → bool ``[...]``.

    Examples:
        >>> inverted_pendulum_fallen(None, None, torch.tensor([[0.0, 0.1, 0, 0], [0.0, -0.3, 0, 0]]))
        tensor([False,  True])
    """
    return ~torch.isfinite(next_obs).all(-1) | (next_obs[..., 1].abs() > 0.2)


def inverted_pendulum(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """InvertedPendulum-v5's cost: −1 for a step that keeps the pole up, 0 for the step it falls
    (the env's reward is 1 while not terminated). Give the planner
    :func:`inverted_pendulum_fallen` as ``env.termination`` too, so that nothing accrues after
    a predicted fall and plans that stay up win: ``env.id=InvertedPendulum-v5
    env.cost=torchrl_recon.envs.gym_costs:inverted_pendulum
    env.termination=torchrl_recon.envs.gym_costs:inverted_pendulum_fallen`` (needs
    ``pip install "torchrl-recon[mujoco]"``).

    Examples:
        >>> inverted_pendulum(None, None, torch.tensor([[0.0, 0.1, 0, 0], [0.0, -0.3, 0, 0]]))
        tensor([-1., -0.])
    """
    return -(~inverted_pendulum_fallen(obs, action, next_obs)).to(next_obs.dtype)
