"""β in cost units: scale the uncertainty penalty of J = Σ(α·r − β·u) to the task's cost.

u (reconstruction error of a normalised window) and the cost (whatever the env's units are)
live on unrelated scales, so an absolute β means nothing across tasks: ``beta=0.1`` changes
plans on one env and is a no-op on another. A *relative* β is measured in "mean cost per step
per mean u per window" on data (usually the random data the models were fitted on): with
``relative_beta(1.0, ...)`` a window of average u costs as much as an average step.
"""

from __future__ import annotations

import math

import torch
from tensordict import NestedKey, TensorDictBase

from torchrl_recon.data.buffers import MASK_KEY, TRAJ_KEY, cut_sequences
from torchrl_recon.devices import module_device
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.checks import check_int, check_keys, check_real, check_type
from torchrl_recon.modules.padding import windows_at_rest

__all__ = ["cost_to_u_ratio", "relative_beta", "window_uncertainty"]


def cost_to_u_ratio(data: TensorDictBase, per_window_u: torch.Tensor) -> float:
    """Mean ``|cost|`` per step over mean u per window: the unit of a relative β (``beta_relative``).

    The cost is read as ``-("next", "reward")`` of ``data``.

    Examples:
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"next": {"reward": -torch.full((4, 1), 6.0)}}, [4])
        >>> cost_to_u_ratio(data, torch.tensor([0.5, 1.5]))
        6.0
    """
    check_keys("data", data, [("next", "reward")])
    check_type("per_window_u", per_window_u, torch.Tensor, "a tensor of u per window")
    cost = float(data["next", "reward"].abs().mean())
    u = float(per_window_u.mean())
    if not (math.isfinite(cost) and math.isfinite(u) and cost > 0 and u > 0):
        raise ValueError(
            f"a relative beta needs a positive finite mean |cost| and mean u on the random data, "
            f"got mean |cost| = {cost} and mean u = {u}."
        )
    return cost / u


@torch.no_grad()
def window_uncertainty(
    data: TensorDictBase,
    estimator: UncertaintyEstimator,
    *,
    sequence_length: int | None = None,
    obs_key: NestedKey = "observation",
    action_key: NestedKey = "action",
    traj_key: NestedKey = TRAJ_KEY,
) -> torch.Tensor:
    """u of every T-window of ``data``'s trajectories (flat, on the CPU), in one batched call.

    ``data`` is cut into non-overlapping sequences of ``sequence_length`` steps (default: the
    estimator's window T) inside each trajectory (``traj_key``, written by TorchRL collectors);
    every T-window of each sequence is scored on the estimator's device. When no trajectory has
    ``sequence_length`` steps (an env whose episodes end early), each trajectory is one padded
    sequence and its windows are those the estimator trains on in padded slices
    (``torchrl_recon.modules.padding.windows_at_rest``): every window that ends at a real
    step, an episode shorter than T started at rest.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> est = ReconstructionUncertainty(3, 1, window=4)
        >>> data = TensorDict({"observation": torch.randn(40, 3), "action": torch.rand(40, 1),
        ...                    ("collector", "traj_ids"): torch.arange(40) // 20}, [40])
        >>> window_uncertainty(data, est).shape, window_uncertainty(data, est, sequence_length=10).shape
        (torch.Size([10]), torch.Size([28]))
        >>> short = data.clone().set(("collector", "traj_ids"), torch.arange(40) // 2)  # 20 episodes of 2 steps
        >>> window_uncertainty(short, est, sequence_length=10).shape  # one window (at rest) each
        torch.Size([20])
    """
    check_type("estimator", estimator, UncertaintyEstimator, "an UncertaintyEstimator")
    if sequence_length is not None:
        check_int("sequence_length", sequence_length)
    check_keys("data", data, [obs_key, action_key, traj_key])
    length = estimator.window if sequence_length is None else sequence_length
    if length < estimator.window:
        raise ValueError(
            f"sequence_length={length} is shorter than the estimator's window ({estimator.window})."
        )
    keys = (obs_key, action_key, traj_key)
    seqs = cut_sequences(data.select(*keys), length, traj_key=traj_key, pad_short=True)
    device = module_device(estimator) if isinstance(estimator, torch.nn.Module) else None
    obs, action = seqs.get(obs_key), seqs.get(action_key)
    if device is not None:
        obs, action = obs.to(device), action.to(device)
    mask = seqs.get(MASK_KEY, None)
    if mask is None:
        return estimator.score(obs, action).flatten().cpu()
    obs, action, valid = windows_at_rest(obs, action, mask.to(obs.device), estimator.window)
    return estimator.score(obs, action)[valid].cpu()


def relative_beta(
    beta: float,
    data: TensorDictBase,
    estimator: UncertaintyEstimator,
    *,
    sequence_length: int | None = None,
    traj_key: NestedKey = TRAJ_KEY,
) -> float:
    """The absolute β for ``Objective(beta=...)`` of a β given in cost units on ``data``.

    ``beta`` × mean ``|cost|`` per step / mean u per window, both measured on ``data`` (flat
    transitions with ``observation``, ``action``, ``("next", "reward")`` and trajectory ids;
    usually the random data the models were fitted on): ``relative_beta(1.0, ...)`` makes a
    window of average u cost as much as an average step. Negative ``beta`` (exploration) keeps
    its sign.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> est = ReconstructionUncertainty(3, 1, window=4)
        >>> data = TensorDict({"observation": torch.randn(40, 3), "action": torch.rand(40, 1),
        ...                    ("next", "reward"): -torch.full((40, 1), 6.0),
        ...                    ("collector", "traj_ids"): torch.arange(40) // 20}, [40])
        >>> u = window_uncertainty(data, est)
        >>> abs(relative_beta(0.5, data, est) - 0.5 * 6.0 / float(u.mean())) < 1e-4
        True
    """
    check_real("beta", beta)
    u = window_uncertainty(data, estimator, sequence_length=sequence_length, traj_key=traj_key)
    return beta * cost_to_u_ratio(data, u)
