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
