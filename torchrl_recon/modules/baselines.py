"""Reference dynamics models to compare the world model with: "no change" and linear least squares."""

from __future__ import annotations

import torch
from torch import nn

from torchrl_recon.modules.checks import check_features, check_int


class LinearDeltaModel(nn.Module):
    """Δs_{t+1} = W [s_t, a_t, 1], fitted by least squares; same ``imagine`` signature as the world model.

    With ``fitted=False`` (never call :meth:`fit`) it is the "no change" model Δs = 0.

    Examples:
        >>> model = LinearDeltaModel(2, 1)
        >>> s = torch.randn(100, 2); a = torch.randn(100, 1)
        >>> model.fit(s, a, s + 0.5 * a)
        >>> model.imagine(s[None, :3], a[None, :3], s[:1], torch.ones(1, 4, 5, 1)).shape
        torch.Size([1, 4, 5, 2])
    """

    weight: torch.Tensor

    def __init__(self, obs_dim: int, action_dim: int, *, window: int = 1) -> None:
        super().__init__()
        for name, value in (("obs_dim", obs_dim), ("action_dim", action_dim), ("window", window)):
            check_int(name, value)
        self.obs_dim, self.action_dim, self.window = obs_dim, action_dim, window
        self.register_buffer("weight", torch.zeros(obs_dim + action_dim + 1, obs_dim))

    @torch.no_grad()
    def fit(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> None:
        """Least-squares fit (float64, small ridge term) on transitions ``[..., N]``, ``[..., M]``, ``[..., N]``."""
        check_features("obs", obs, self.obs_dim)
        check_features("action", action, self.action_dim)
        x = (
            torch.cat([obs, action, torch.ones_like(obs[..., :1])], -1)
            .reshape(-1, self.weight.shape[0])
            .double()
        )
        y = (next_obs - obs).reshape(-1, self.obs_dim).double()
        gram = x.T @ x + 1e-6 * torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
        self.weight.copy_(torch.linalg.solve(gram, x.T @ y).to(self.weight.dtype))

    def imagine(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        actions: torch.Tensor,
    ) -> torch.Tensor:
        """Roll out ``actions`` ``[*B, K, H, M]`` from ``observation`` ``[*B, N]``; the context is unused."""
        k, horizon = actions.shape[-3], actions.shape[-2]
        s = observation.unsqueeze(-2).expand(*observation.shape[:-1], k, self.obs_dim)
        w_s, w_a, b = self.weight[: self.obs_dim], self.weight[self.obs_dim : -1], self.weight[-1]
        states = []
        for t in range(horizon):
            s = s + s @ w_s + actions[..., t, :] @ w_a + b
            states.append(s)
        return torch.stack(states, -2)
