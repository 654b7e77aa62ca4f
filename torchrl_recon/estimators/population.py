"""Populations of autoencoders: R :class:`ReconstructionUncertainty` with weights ``[R, ...]``.

World models carry their member dim themselves (``LSTMWorldModel(..., num_members=R)``);
``WorldModelPopulation``, that class's former name, is in ``torchrl_recon.modules.world_model``
(and here, for imports from this module's old path ``torchrl_recon.modules.population``). An
autoencoder population is its own class because the estimator interface
(:class:`~torchrl_recon.estimators.UncertaintyEstimator`: ``score_sequence`` ``[R, L, D]`` →
``[R, W]``, what planners call) has no member dim; it is used to fit R autoencoders as one
batch (:func:`~torchrl_recon.fitting.fit_population`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_recon.estimators.reconstruction import (
    ReconstructionUncertainty,
    window_errors,
    window_errors_blocked,
)
from torchrl_recon.modules.checks import check_finite, check_int, check_window_pair
from torchrl_recon.modules.members import StackedMembers
from torchrl_recon.modules.padding import masked_mean, windows_at_rest
from torchrl_recon.modules.world_model import WorldModelPopulation  # noqa: F401  (old path's name)


class ReconstructionPopulation(StackedMembers, TensorDictModuleBase):
    """R :class:`ReconstructionUncertainty` autoencoders, weights ``[R, ...]``.

    Inputs carry the member dim first (``[R, *B, L, N]``); :meth:`score` gives ``[R, *B, W]``
    and :meth:`loss` one mean u per member ``[R]``. The weights keep the autoencoder's names
    (``encoder.weight`` ``[R, hidden, T·(N + M)]``); :meth:`from_members`, :meth:`member`,
    :meth:`split` and :meth:`load_member` move members in and out. A population of one runs
    the single autoencoder's own ops.

    Args:
        obs_dim, action_dim: as :class:`~torchrl_recon.estimators.ReconstructionUncertainty`.

    Keyword Args:
        num_members: R, the members, initialised one after the other from the global RNG.
        **kwargs: the members' keyword arguments (``window``, ``hidden_size``, ...).

    Examples:
        >>> pop = ReconstructionPopulation(6, 3, num_members=4, window=10)
        >>> pop.score(torch.randn(4, 2, 30, 6), torch.randn(4, 2, 30, 3)).shape
        torch.Size([4, 2, 21])
        >>> pop.loss(torch.randn(4, 2, 30, 6), torch.randn(4, 2, 30, 3)).shape
        torch.Size([4])
    """

    member_type = ReconstructionUncertainty

    def __init__(self, obs_dim: int, action_dim: int, *, num_members: int, **kwargs) -> None:
        super().__init__()
        check_int("num_members", num_members)
        self._register_member_hooks()
        members = [
            ReconstructionUncertainty(obs_dim, action_dim, **kwargs) for _ in range(num_members)
        ]
        template = members[0]
        self.obs_dim, self.action_dim = template.obs_dim, template.action_dim
        self.window, self.activation = template.window, template.activation
        self.hidden_size = template.hidden_size
        self._hold(members)

    def config(self) -> dict:
        """The members' constructor arguments and ``num_members`` (checkpoints rebuild from it)."""
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "window": self.window,
            "hidden_size": self.hidden_size,
            "activation": self.activation,
            "num_members": self.num_members,
        }

    def score(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each member's u for every window of ``[R, *B, L, N]``, ``[R, *B, L, M]`` → ``[R, *B, L - T + 1]``."""
        self._members_first("obs", obs, 3)
        check_window_pair(
            obs,
            action,
            obs_dim=self.obs_dim,
            action_dim=self.action_dim,
            window=self.window,
            min_ndim=3,
        )
        check_finite("obs", obs.detach())
        check_finite("action", action.detach())
        length, members = obs.shape[-2], self.num_members
        x = torch.cat([obs, action], -1).reshape(
            members, -1, length, obs.shape[-1] + action.shape[-1]
        )
        loc = self._bcast(self.input_norm.loc, 4)
        x = ((x - loc) / self._bcast(self.input_norm.scale, 4)).contiguous()
        enc, dec = self.encoder, self.decoder
        weights = (enc.weight, enc.bias, dec.weight, dec.bias)
        needs_grad = torch.is_grad_enabled() and (x.requires_grad or weights[0].requires_grad)
        if members == 1:  # one member: the single autoencoder's own ops
            weights = tuple(w[0] for w in weights)
            fn = window_errors if needs_grad else window_errors_blocked
            u = fn(x[0], self.window, self.activation, *weights)[None]
        else:
            u = window_errors(x, self.window, self.activation, *weights)
        return u.reshape(*obs.shape[:-2], length - self.window + 1)

    def loss(
        self, obs: torch.Tensor, action: torch.Tensor, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Each member's training loss, the mean u over its windows (paper eq. 1), ``[R]``; with
        ``mask`` ``[R, *B, L]`` over the windows of real steps (as ``UncertaintyEstimator.loss``)."""
        if mask is None:
            return self.score(obs, action).reshape(self.num_members, -1).mean(1)
        obs, action, valid = windows_at_rest(obs, action, mask, self.window)
        return masked_mean(self.score(obs, action), valid, valid.dim() - 1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action = tensordict.get(self.in_keys[0]), tensordict.get(self.in_keys[1])
        u = self.score(obs, action)
        pad = u.new_full((*u.shape[:-1], self.window - 1), float("nan"))
        tensordict.set(self.out_keys[0], torch.cat([pad, u], -1))
        return tensordict
