from __future__ import annotations

import pytest
import torch

from torchrl_recon.modules import LinearDeltaModel

GAIN, ACTION_PENALTY, S0 = 1.0, 0.1, 0.5


def integrator_cost(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """Quadratic cost of the 1-D integrator s' = s + a."""
    return next_obs[..., 0] ** 2 + ACTION_PENALTY * action[..., 0] ** 2


def integrator_model(window: int = 1) -> LinearDeltaModel:
    model = LinearDeltaModel(1, 1, window=window)
    model.weight.zero_()
    model.weight[1, 0] = GAIN  # Δs = a
    return model


def optimal_cost(horizon: int) -> float:
    """Closed-form minimum of Σ s_{k+1}² + 0.1 a_k² for s_{k+1} = s_k + a_k from s_0 = 0.5."""
    lower = torch.tril(torch.ones(horizon, horizon, dtype=torch.float64)) * GAIN  # s = S0 + L a
    ones = torch.full((horizon,), S0, dtype=torch.float64)
    q = lower.T @ lower + ACTION_PENALTY * torch.eye(horizon, dtype=torch.float64)
    a = torch.linalg.solve(q, -lower.T @ ones)
    assert a.abs().max() <= 1.0  # the unconstrained optimum lies inside the action bounds
    s = ones + lower @ a
    return float((s**2).sum() + ACTION_PENALTY * (a**2).sum())


@pytest.fixture
def context():
    return torch.zeros(4, 1), torch.zeros(4, 1), torch.full((1,), S0)
