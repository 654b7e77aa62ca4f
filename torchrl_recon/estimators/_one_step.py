"""Helpers shared by the one-step-model estimators (ensemble, MC dropout)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.checks import check_features, check_finite

_BLOCK = 2048  # steps per block in the no-grad path


def population_variance(pred: torch.Tensor) -> torch.Tensor:
    """Variance over dim 0 with divisor n (``correction=0``), as ``((p - mean) ** 2).mean(0)``.

    Written out because ``Tensor.var`` over a leading dim is ~30x slower on CPU.
    """
    return (pred - pred.mean(0)).square().mean(0)


def blocked_scores(
    score: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, needs_grad: bool
) -> torch.Tensor:
    """``score`` on all rows of ``x`` ``[R, L, D]`` at once, or without autograd in row blocks.

    Blocks of about ``_BLOCK`` steps keep the ``[E or S, steps, hidden]`` intermediates in
    cache instead of page-faulting hundreds of MB; per-row results are the same.
    """
    if needs_grad:
        return score(x)
    with torch.no_grad():
        rows_per_block = max(1, _BLOCK // x.shape[1])
        return torch.cat([score(block) for block in x.split(rows_per_block)])


def one_step_pairs(
    estimator: UncertaintyEstimator, obs: torch.Tensor, action: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Standardised one-step transitions inside sequences ``[*B, L, N]``, ``[*B, L, M]``.

    Returns the inputs x̃_t ``[P, N + M]`` and the targets s̃_{t+1} − s̃_t ``[P, N]`` for every
    consecutive pair of steps, P = B·(L − 1). Sequences need at least 2 steps.
    """
    check_features("obs", obs, estimator.obs_dim, min_ndim=2)
    check_features("action", action, estimator.action_dim, min_ndim=2)
    if obs.shape[:-1] != action.shape[:-1]:
        raise ValueError(
            f"obs {tuple(obs.shape)} and action {tuple(action.shape)} disagree on batch/time dims."
        )
    if obs.shape[-2] < 2:
        raise ValueError(
            f"obs has shape {tuple(obs.shape)}; expected a time dimension (-2) of at least 2 steps "
            "(one transition)."
        )
    check_finite("obs", obs.detach())
    check_finite("action", action.detach())
    n, dim = estimator.obs_dim, estimator.feature_dim
    x = estimator.input_norm.normalize(torch.cat([obs, action], -1))
    x = x.reshape(-1, obs.shape[-2], dim)
    inputs = x[:, :-1].reshape(-1, dim)
    targets = (x[:, 1:, :n] - x[:, :-1, :n]).reshape(-1, n)
    return inputs, targets
