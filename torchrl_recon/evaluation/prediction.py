"""Multi-step prediction error of a dynamics model on real trajectories."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from torchrl_recon.devices import module_device


def multi_step_errors(
    model,
    trajectories: TensorDictBase,
    *,
    window: int,
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """Squared prediction error per trajectory and step, ``[V, H]``, averaged over state dims.

    Each trajectory ``[V, window + H]`` gives the model a real context of ``window`` steps
    (moved to the model's device, where the result is);
    the model then predicts the next ``H`` states open loop from the real actions (as a planner
    would), and the predictions are compared with the real next states. Errors are in units of
    ``scale`` (per state dim; e.g. the standard deviation of a fixed reference dataset), raw
    units when ``scale`` is None.

    Args:
        model: anything with ``imagine(context_obs, context_action, observation, actions)``.
        trajectories: TensorDict ``[V, L]`` with ``observation``, ``action`` and ``("next", "observation")``.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.modules import LinearDeltaModel
        >>> td = TensorDict({"observation": torch.zeros(2, 15, 3), "action": torch.zeros(2, 15, 1),
        ...                  ("next", "observation"): torch.ones(2, 15, 3)}, [2, 15])
        >>> multi_step_errors(LinearDeltaModel(3, 1), td, window=5).shape
        torch.Size([2, 10])
    """
    if isinstance(model, nn.Module):
        trajectories = trajectories.to(module_device(model))
    obs, action, next_obs = _parts(trajectories, window)
    with torch.no_grad():
        pred = model.imagine(
            obs[:, :window], action[:, :window], obs[:, window], action[:, None, window:]
        )[:, 0]
    return _squared_errors(pred, next_obs[:, window:], scale)


def _parts(
    trajectories: TensorDictBase, window: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Observations, actions and next observations of ``[V, L]`` trajectories with L > window."""
    obs, action = trajectories["observation"], trajectories["action"]
    if obs.ndim != 3 or obs.shape[1] <= window:
        raise ValueError(
            f"trajectories must be [V, L] with L > window={window}, got observation {tuple(obs.shape)}."
        )
    return obs, action, trajectories["next", "observation"]


def _squared_errors(
    pred: torch.Tensor, real: torch.Tensor, scale: torch.Tensor | None
) -> torch.Tensor:
    """Squared error averaged over state dims, in units of ``scale`` when given."""
    err = pred - real
    if scale is not None:
        err = err / scale.to(err.device)
    return err.pow(2).mean(-1)


def population_multi_step_errors(
    population,
    trajectories: TensorDictBase,
    *,
    window: int,
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`multi_step_errors` of every member of a population, in one batched rollout:
    ``[R, V, H]``, member r's errors as ``multi_step_errors(population.member(r), ...)``.

    Args:
        population: a :class:`~torchrl_recon.modules.WorldModelPopulation` (R members).
        trajectories: TensorDict ``[V, L]`` as for :func:`multi_step_errors`, shared by all members.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.modules import WorldModelPopulation
        >>> td = TensorDict({"observation": torch.zeros(2, 15, 3), "action": torch.zeros(2, 15, 1),
        ...                  ("next", "observation"): torch.ones(2, 15, 3)}, [2, 15])
        >>> population_multi_step_errors(WorldModelPopulation(3, 1, num_members=4, window=5), td,
        ...                              window=5).shape
        torch.Size([4, 2, 10])
    """
    trajectories = trajectories.to(module_device(population))
    obs, action, next_obs = _parts(trajectories, window)
    members = population.num_members

    def each(x: torch.Tensor) -> torch.Tensor:
        return x.expand(members, *x.shape)

    with torch.no_grad():
        pred = population.imagine(
            each(obs[:, :window]),
            each(action[:, :window]),
            each(obs[:, window]),
            each(action[:, None, window:]),
        )[:, :, 0]
    return _squared_errors(pred, next_obs[:, window:], scale)
