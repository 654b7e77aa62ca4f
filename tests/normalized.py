"""Fit a test's world model or estimator normalisation on a little random data: planning refuses
a model whose normalisation was never fitted (``PlanningModel.check_fitted``)."""

from __future__ import annotations

import torch
from torch import nn

from torchrl_recon.modules import LSTMWorldModel, UncertaintyEstimator


def _data(n: int, m: int, like: torch.Tensor, seed: int) -> tuple[torch.Tensor, ...]:
    """Standard normal obs, action and Δs ``[256, .]`` (statistics near the identity's), drawn
    from their own generator: the global RNG a test seeded is left as it was."""
    g = torch.Generator().manual_seed(seed)
    obs, action, delta = (torch.randn(256, d, generator=g) for d in (n, m, n))
    return tuple(x.to(like.device, like.dtype) for x in (obs, action, obs + delta))


def fitted(module: nn.Module, *, seed: int = 0) -> nn.Module:
    """``module`` (an ``LSTMWorldModel``, one or of members, or an ``UncertaintyEstimator``)
    with its normalisation fitted on random data; returns it."""
    like = next(module.buffers())
    obs, action, next_obs = _data(module.obs_dim, module.action_dim, like, seed)
    if isinstance(module, UncertaintyEstimator):
        module.fit_normalization(obs, action)
    elif isinstance(module, LSTMWorldModel) and module.num_members is not None:
        for r, member in enumerate(module.split()):
            member.fit_normalization(obs, action, next_obs)
            module.load_member(r, member)
    else:
        module.fit_normalization(obs, action, next_obs)
    return module
