"""Bootstrapped ensemble of one-step dynamics models; u is the members' disagreement."""

from __future__ import annotations

import math

import torch
from tensordict import NestedKey
from torch import nn

from torchrl_recon.estimators._one_step import blocked_scores, one_step_pairs, population_variance
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.activations import ACTIVATIONS
from torchrl_recon.modules.checks import check_activation, check_int
from torchrl_recon.modules.normalization import Normalizer


class EnsembleUncertainty(UncertaintyEstimator):
    """Disagreement of a bootstrapped ensemble of one-step dynamics MLPs (MAX / PETS style).

    E members f_e (two hidden layers each) map a standardised step
    x̃_t = ((s_t − μ_s)/σ_s, (a_t − μ_a)/σ_a) to the change of the standardised state
    s̃_{t+1} − s̃_t. Per step the disagreement is the population variance across members,
    averaged over the N state features, and the u of the window ending at t is its mean
    over the window's T steps:

        d_t = (1/N) Σ_n Var_e[ f_e(x̃_t)_n ],        u_t = (1/T) Σ_{i=t-T+1..t} d_i

    This is the model disagreement of MAX (Shyam et al. 2019) with the bootstrapped
    ensemble of PETS (Chua et al. 2018), scored along any given, e.g. imagined, trajectory:
    the members never roll out themselves, they only judge each (s, a) pair of it. u is in
    units of squared standardised state change (σ_s²); it is 0 where all members agree.

    The members are stacked parameters ``[E, in, out]`` evaluated as one batched model with
    ``torch.baddbmm``. Training (:meth:`loss`) uses a *bootstrap per minibatch*: each member
    fits its own resample, with replacement, of the minibatch's transitions, which keeps
    the members apart where the data do not pin them down.

    Args:
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        window: T, the number of steps per window.
        num_members: E, the ensemble size (at least 2).
        hidden_size: hidden units per layer of each member.
        activation: ``"relu"``, ``"tanh"`` or ``"elu"``.
        obs_key, action_key, out_key: TensorDict keys used by ``forward``.

    Examples:
        >>> ens = EnsembleUncertainty(6, 3, window=10, num_members=4)
        >>> ens.score(torch.randn(4, 30, 6), torch.randn(4, 30, 3)).shape
        torch.Size([4, 21])
        >>> ens.loss(torch.randn(8, 12, 6), torch.randn(8, 12, 3)).shape
        torch.Size([])
    """

    window_local = True  # u of a window depends on that window alone

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        *,
        window: int = 10,
        num_members: int = 5,
        hidden_size: int = 64,
        activation: str = "relu",
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = "uncertainty",
    ) -> None:
        super().__init__(
            obs_dim, action_dim, window, obs_key=obs_key, action_key=action_key, out_key=out_key
        )
        check_int("num_members", num_members, 2)
        check_int("hidden_size", hidden_size, 1)
        check_activation(activation)
        self.num_members, self.hidden_size, self.activation = num_members, hidden_size, activation
        sizes = [self.feature_dim, hidden_size, hidden_size, obs_dim]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
            # nn.Linear's default init, drawn independently for every member.
            bound = 1.0 / math.sqrt(fan_in)
            self.weights.append(nn.Parameter(torch.empty(num_members, fan_in, fan_out)))
            self.biases.append(nn.Parameter(torch.empty(num_members, 1, fan_out)))
            nn.init.uniform_(self.weights[-1], -bound, bound)
            nn.init.uniform_(self.biases[-1], -bound, bound)
        self.input_norm = Normalizer(self.feature_dim)

    def config(self) -> dict:
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "window": self.window,
            "num_members": self.num_members,
            "hidden_size": self.hidden_size,
            "activation": self.activation,
        }

    def predict_deltas(self, x: torch.Tensor) -> torch.Tensor:
        """Every member's predicted s̃_{t+1} − s̃_t for standardised steps.

        ``x`` is ``[P, N + M]`` (the same inputs for all members) or ``[E, P, N + M]``
        (one set per member); the result is ``[E, P, N]``.
        """
        if x.ndim == 2:
            x = x.expand(self.num_members, *x.shape)
        act = ACTIVATIONS[self.activation]
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = torch.baddbmm(bias, x, weight)
            if i < last:
                x = act(x)
        return x

    def score_sequence(self, x: torch.Tensor) -> torch.Tensor:
        needs_grad = torch.is_grad_enabled() and (x.requires_grad or self.weights[0].requires_grad)
        return blocked_scores(self._score_rows, x, needs_grad)

    def _score_rows(self, x: torch.Tensor) -> torch.Tensor:
        rows, length, dim = x.shape
        steps = self.input_norm.normalize(x).reshape(rows * length, dim)
        pred = self.predict_deltas(steps)  # [E, R·L, N]
        disagreement = population_variance(pred).mean(-1).view(rows, length)
        return disagreement.unfold(1, self.window, 1).mean(-1)

    def loss(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Mean over members of their one-step MSE, each on its own bootstrap resample.

        Bootstrap per minibatch: the P transitions inside the sequences ``[*B, L, N]``,
        ``[*B, L, M]`` are resampled with replacement once per member
        (``torch.randint(P, (E, P))`` from the global RNG of the inputs' device).
        """
        inputs, targets = one_step_pairs(self, obs, action)
        p = inputs.shape[0]
        index = torch.randint(p, (self.num_members, p), device=inputs.device)
        pred = self.predict_deltas(inputs[index])
        return (pred - targets[index]).pow(2).mean()
