"""How well an uncertainty estimate tells familiar from unfamiliar, and ranks real prediction error."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from torchrl_recon.devices import module_device
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator


def _ranks(x: torch.Tensor) -> torch.Tensor:
    """Average ranks (ties share their mean rank), 1-based, as float64."""
    x = x.double().flatten()
    order = torch.argsort(x)
    ranks = torch.empty_like(x)
    ranks[order] = torch.arange(1, len(x) + 1, dtype=torch.float64, device=x.device)
    unique, inverse = torch.unique(x, return_inverse=True)
    if len(unique) < len(x):
        sums = x.new_zeros(len(unique)).index_add_(0, inverse, ranks)
        counts = x.new_zeros(len(unique)).index_add_(0, inverse, torch.ones_like(ranks))
        ranks = (sums / counts)[inverse]
    return ranks


def auroc(negatives: torch.Tensor, positives: torch.Tensor) -> float:
    """Probability that a random positive scores above a random negative (ties count half).

    Examples:
        >>> auroc(torch.tensor([0.1, 0.2]), torch.tensor([0.3, 0.15]))
        0.75
    """
    n_neg, n_pos = negatives.numel(), positives.numel()
    if n_neg == 0 or n_pos == 0:
        raise ValueError(f"auroc needs both classes, got {n_neg} negatives and {n_pos} positives.")
    ranks = _ranks(torch.cat([negatives.flatten(), positives.flatten()]))
    return float((ranks[n_neg:].sum() - n_pos * (n_pos + 1) / 2) / (n_neg * n_pos))


def spearman(x: torch.Tensor, y: torch.Tensor) -> float:
    """Spearman rank correlation of two equally long vectors.

    Examples:
        >>> round(spearman(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([10.0, 30.0, 20.0])), 6)
        0.5
    """
    if x.numel() != y.numel() or x.numel() < 3:
        raise ValueError(
            f"spearman needs two vectors of equal length >= 3, got {x.numel()} and {y.numel()}."
        )
    rx, ry = _ranks(x), _ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    return float((rx * ry).sum() / (rx.norm() * ry.norm()))


@torch.no_grad()
def imagined_uncertainty_and_error(
    world_model,
    estimator: UncertaintyEstimator,
    trajectories: TensorDictBase,
    *,
    window: int,
    scale: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cumulative u of each imagined trajectory and the world model's real error on it.

    For each real trajectory ``[V, window + H]``, the world model imagines the last ``H``
    states from the real actions after a real context of ``window`` steps; the estimator
    scores every window of (context + imagined states, actions) ending in the imagined part.
    The trajectories are moved to the world model's device, where the results are.

    Returns:
        ``(cumulative_u [V], mean_squared_error [V])``, the error in units of ``scale``.
    """
    if isinstance(world_model, nn.Module):
        trajectories = trajectories.to(module_device(world_model))
    obs, action = trajectories["observation"], trajectories["action"]
    next_obs = trajectories["next", "observation"]
    pred = world_model.imagine(
        obs[:, :window], action[:, :window], obs[:, window], action[:, None, window:]
    )[:, 0]
    t = estimator.window
    # States entering each step: real context, then the real s_window, then predictions.
    states = torch.cat([obs[:, window - t + 1 : window + 1], pred[:, :-1]], 1)
    u = estimator.score(states, action[:, window - t + 1 :])
    err = pred - next_obs[:, window:]
    if scale is not None:
        err = err / scale.to(err.device)
    return u.sum(-1), err.pow(2).mean((-1, -2))


def calibration_metrics(
    world_model,
    estimator: UncertaintyEstimator,
    trajectories: TensorDictBase,
    ood_windows: TensorDictBase,
    *,
    window: int,
    scale: torch.Tensor,
    state_shift: float,
    action_high: torch.Tensor,
) -> dict[str, float]:
    """How well ``estimator``'s u ranks real prediction error and flags out-of-distribution windows.

    ``trajectories`` ``[V, window + H]``: Σu of each imagined trajectory
    (:func:`imagined_uncertainty_and_error`) against its real MSE (units of ``scale``): Spearman
    correlation and AUROC for "MSE above its median". ``ood_windows`` ``[W, T]`` real windows:
    AUROC of u on them (negatives) against the same windows with the states moved by
    ``state_shift``·``scale`` and with the actions held at ``action_high`` (positives).

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
        >>> _ = torch.manual_seed(0)
        >>> world, est = LSTMWorldModel(3, 1, window=4), ReconstructionUncertainty(3, 1, window=4)
        >>> traj = TensorDict({"observation": torch.randn(5, 7, 3), "action": torch.randn(5, 7, 1),
        ...     ("next", "observation"): torch.randn(5, 7, 3)}, [5, 7])
        >>> m = calibration_metrics(world, est, traj, traj[:, :4], window=4, scale=torch.ones(3),
        ...     state_shift=3.0, action_high=torch.ones(1))
        >>> sorted(m), 0 <= m["ood_auroc_state_shift"] <= 1
        (['auroc_error_above_median', 'mean_trajectory_mse', 'ood_auroc_action_bound', 'ood_auroc_state_shift', 'spearman'], True)
    """
    with torch.no_grad():
        u_sum, mse = imagined_uncertainty_and_error(
            world_model, estimator, trajectories, window=window, scale=scale
        )
        above = mse > mse.median()
        device = module_device(estimator)
        obs, act = ood_windows["observation"].to(device), ood_windows["action"].to(device)
        scale, action_high = scale.to(device), action_high.to(device)
        u_in = estimator.score(obs, act)[:, 0]
        u_shift = estimator.score(obs + state_shift * scale, act)[:, 0]
        u_bound = estimator.score(obs, action_high.expand_as(act))[:, 0]
    return {
        "spearman": spearman(u_sum, mse),
        "auroc_error_above_median": auroc(u_sum[~above], u_sum[above]),
        "ood_auroc_state_shift": auroc(u_in, u_shift),
        "ood_auroc_action_bound": auroc(u_in, u_bound),
        "mean_trajectory_mse": float(mse.mean()),
    }
