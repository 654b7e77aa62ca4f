"""Monte Carlo dropout on a one-step dynamics model; u is the spread of S stochastic passes."""

from __future__ import annotations

import torch
from tensordict import NestedKey
from torch import nn
from torch.nn import functional as F

from torchrl_recon.estimators._one_step import blocked_scores, one_step_pairs, population_variance
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.activations import ACTIVATIONS
from torchrl_recon.modules.checks import check_activation, check_int
from torchrl_recon.modules.normalization import Normalizer


class MCDropoutUncertainty(UncertaintyEstimator):
    """Variance of S Monte Carlo dropout passes of a one-step dynamics MLP (Gal & Ghahramani 2016).

    One MLP (two hidden layers, dropout with rate p after each hidden activation) maps a
    standardised step x̃_t = ((s_t − μ_s)/σ_s, (a_t − μ_a)/σ_a) to the change of the
    standardised state s̃_{t+1} − s̃_t. It is trained with ordinary dropout; for scoring, S
    passes with S dropout masks approximate samples from the posterior over networks:

        d_t = (1/N) Σ_n Var_k[ f_k(x̃_t)_n ],        u_t = (1/T) Σ_{i=t-T+1..t} d_i

    (population variance over the S passes, mean over the N state features, mean over the
    T steps of the window ending at t). u is in units of squared standardised state change
    (σ_s²), like :class:`~torchrl_recon.estimators.EnsembleUncertainty`.

    The S passes run as one batched pass. Each call draws per-pass masks of shape
    ``[S, 1, hidden]`` (one per hidden layer) from the global RNG of the inputs' device,
    scaled by 1/(1 − p), and shares them across every row of the call: all candidates a
    planner scores in one call see the same S sub-networks (common random numbers), so their
    u differ only because their (s, a) differ, and mask noise does not reorder them.
    Successive calls draw new masks, so u is stochastic across calls; seed
    ``torch.manual_seed`` for reproducible scores.

    Args:
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        window: T, the number of steps per window.
        hidden_size: hidden units per layer.
        dropout: p, the drop probability, in (0, 1).
        samples: S, stochastic passes per score (at least 2).
        activation: ``"relu"``, ``"tanh"`` or ``"elu"``.
        obs_key, action_key, out_key: TensorDict keys used by ``forward``.

    Examples:
        >>> mc = MCDropoutUncertainty(6, 3, window=10, samples=8)
        >>> mc.score(torch.randn(4, 30, 6), torch.randn(4, 30, 3)).shape
        torch.Size([4, 21])
        >>> _ = torch.manual_seed(0); a = mc.score(torch.ones(1, 10, 6), torch.ones(1, 10, 3))
        >>> _ = torch.manual_seed(0); b = mc.score(torch.ones(1, 10, 6), torch.ones(1, 10, 3))
        >>> torch.equal(a, b)
        True
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        *,
        window: int = 10,
        hidden_size: int = 64,
        dropout: float = 0.1,
        samples: int = 10,
        activation: str = "relu",
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = "uncertainty",
    ) -> None:
        super().__init__(
            obs_dim, action_dim, window, obs_key=obs_key, action_key=action_key, out_key=out_key
        )
        check_int("hidden_size", hidden_size, 1)
        check_int("samples", samples, 2)
        check_activation(activation)
        if isinstance(dropout, bool) or not isinstance(dropout, (int, float)):
            raise ValueError(f"dropout must be a float in (0, 1), got {dropout!r}.")
        if not 0.0 < dropout < 1.0:
            raise ValueError(f"dropout must be in (0, 1), got {dropout!r}.")
        self.hidden_size, self.dropout, self.samples = hidden_size, float(dropout), samples
        self.activation = activation
        self.hidden1 = nn.Linear(self.feature_dim, hidden_size)
        self.hidden2 = nn.Linear(hidden_size, hidden_size)
        self.head = nn.Linear(hidden_size, obs_dim)
        self.input_norm = Normalizer(self.feature_dim)

    def config(self) -> dict:
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "window": self.window,
            "hidden_size": self.hidden_size,
            "dropout": self.dropout,
            "samples": self.samples,
            "activation": self.activation,
        }

    def score_sequence(self, x: torch.Tensor) -> torch.Tensor:
        keep = 1.0 - self.dropout
        shape = (2, self.samples, 1, self.hidden_size)  # one mask per hidden layer and pass
        masks = torch.bernoulli(torch.full(shape, keep, device=x.device)).to(x).div_(keep)
        needs_grad = torch.is_grad_enabled() and (
            x.requires_grad or self.hidden1.weight.requires_grad
        )
        return blocked_scores(lambda rows: self._score_rows(rows, masks), x, needs_grad)

    def _score_rows(self, x: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        rows, length, dim = x.shape
        steps = self.input_norm.normalize(x).reshape(rows * length, dim)
        act = ACTIVATIONS[self.activation]
        # A mask on a layer's input is a mask on the columns of its weight: pass k runs the
        # sub-network with weights W ⊙ m_k, so the S passes are one baddbmm per layer and no
        # masked [S, P, hidden] copy is made. The first layer has no dropout before it, so
        # its output is computed once and shared by the passes.
        h = act(self.hidden1(steps)).expand(self.samples, -1, -1)  # [S, P, H]
        w2 = self.hidden2.weight.t() * masks[0].transpose(1, 2)  # [S, H, H]
        h = act(torch.baddbmm(self.hidden2.bias, h, w2))
        w3 = self.head.weight.t() * masks[1].transpose(1, 2)  # [S, H, N]
        pred = torch.baddbmm(self.head.bias, h, w3)  # [S, P, N]
        spread = population_variance(pred).mean(-1).view(rows, length)
        return spread.unfold(1, self.window, 1).mean(-1)

    def loss(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """One-step MSE on the (s, a) pairs of ``[*B, L, N]``, ``[*B, L, M]``, with dropout on."""
        inputs, targets = one_step_pairs(self, obs, action)
        act = ACTIVATIONS[self.activation]
        h = F.dropout(act(self.hidden1(inputs)), self.dropout, training=True)
        h = F.dropout(act(self.hidden2(h)), self.dropout, training=True)
        return (self.head(h) - targets).pow(2).mean()
