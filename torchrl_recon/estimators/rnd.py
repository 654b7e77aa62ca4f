"""Random network distillation over T-step (s, a) windows; u is the distillation error."""

from __future__ import annotations

import math

import torch
from tensordict import NestedKey
from torch import nn

from torchrl_recon.estimators.uncertainty import UncertaintyEstimator, window_view
from torchrl_recon.modules.checks import check_activation, check_int
from torchrl_recon.modules.normalization import Normalizer
from torchrl_recon.modules.padding import masked_mean, windows_at_rest

_ACTIVATION_MODULES = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU}


class RNDUncertainty(UncertaintyEstimator):
    """Random network distillation (Burda et al. 2019) over flattened T-step windows.

    A fixed, randomly initialised target MLP g (one hidden layer) embeds the flattened
    window of T standardised (s, a) pairs, size T·(N + M); a predictor MLP f (two hidden
    layers) is trained to reproduce that embedding on real windows. Where it has seen data
    the predictor matches the target; elsewhere it does not. For the window w ending at t,

        u_t = ‖f(w) − g(w)‖ / sqrt(embedding_size)

    the root-mean-square distillation error per embedding coordinate, in the units of the
    target's embedding (whose coordinates are O(0.1–1) at nn.Linear's default init).
    :meth:`loss` is the mean of u², the MSE of the distillation.

    The target is drawn from the global RNG when the estimator is built and frozen with
    ``requires_grad_(False)``: it is saved in ``state_dict`` (a checkpoint reproduces it)
    and an optimizer given ``parameters()`` never changes it (it never gets a gradient).

    Args:
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        window: T, the number of steps per window.
        hidden_size: hidden units per layer of both networks.
        embedding_size: size of the embedding the predictor distils.
        activation: ``"relu"``, ``"tanh"`` or ``"elu"``.
        obs_key, action_key, out_key: TensorDict keys used by ``forward``.

    Examples:
        >>> rnd = RNDUncertainty(6, 3, window=10)
        >>> rnd.score(torch.randn(4, 30, 6), torch.randn(4, 30, 3)).shape
        torch.Size([4, 21])
        >>> any(p.requires_grad for p in rnd.target.parameters())
        False
    """

    window_local = True  # u of a window depends on that window alone

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        *,
        window: int = 10,
        hidden_size: int = 64,
        embedding_size: int = 32,
        activation: str = "relu",
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = "uncertainty",
    ) -> None:
        super().__init__(
            obs_dim, action_dim, window, obs_key=obs_key, action_key=action_key, out_key=out_key
        )
        check_int("hidden_size", hidden_size, 1)
        check_int("embedding_size", embedding_size, 1)
        check_activation(activation)
        self.hidden_size, self.embedding_size = hidden_size, embedding_size
        self.activation = activation
        act = _ACTIVATION_MODULES[activation]
        size = window * self.feature_dim
        self.target = nn.Sequential(
            nn.Linear(size, hidden_size), act(), nn.Linear(hidden_size, embedding_size)
        ).requires_grad_(False)
        self.predictor = nn.Sequential(
            nn.Linear(size, hidden_size),
            act(),
            nn.Linear(hidden_size, hidden_size),
            act(),
            nn.Linear(hidden_size, embedding_size),
        )
        self.input_norm = Normalizer(self.feature_dim)

    def config(self) -> dict:
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "window": self.window,
            "hidden_size": self.hidden_size,
            "embedding_size": self.embedding_size,
            "activation": self.activation,
        }

    def score_sequence(self, x: torch.Tensor) -> torch.Tensor:
        rows, length, dim = x.shape
        x = self.input_norm.normalize(x).contiguous()
        num_windows, size = length - self.window + 1, self.window * dim
        windows = window_view(x, self.window).reshape(rows * num_windows, size)
        error = self.predictor(windows) - self.target(windows)
        u = torch.linalg.vector_norm(error, dim=-1) / math.sqrt(self.embedding_size)
        return u.view(rows, num_windows)

    def loss(
        self, obs: torch.Tensor, action: torch.Tensor, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Distillation MSE: the mean of u² over every window of ``[*B, L, N]``, ``[*B, L, M]``
        (with ``mask`` ``[*B, L]``, over the windows of real steps, as the base class's)."""
        if mask is None:
            return self.score(obs, action).pow(2).mean()
        obs, action, valid = windows_at_rest(obs, action, mask, self.window)
        return masked_mean(self.score(obs, action).pow(2), valid, valid.dim())
