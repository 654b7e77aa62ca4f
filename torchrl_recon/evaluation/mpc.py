"""How an MPC episode's predictions compare with what happened: the planned steps of a rollout
of :class:`~torchrl_recon.policies.MPCPolicy` (its predicted next state, u and cost per step)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torchrl_recon.policies.mpc import FEASIBLE, PRED_COST, PRED_NEXT, PRED_U, REPLANNED

METRICS = ("env_return", "prediction_mse", "cost_error", "real_cost", "predicted_cost")
METRICS += ("replans", "mean_u", "feasible_fraction")
"""The metrics of :func:`episode_metrics` (besides ``steps``)."""


def episode_metrics(td: TensorDictBase, scale: torch.Tensor) -> dict[str, float]:
    """Predicted-vs-real metrics of one MPC episode ``[T]`` over its planned steps
    (``prediction_mse`` in units of ``scale`` per state dim, costs summed), its ``env_return``
    over every step and its ``steps``; NaN but those for an episode that ended before its first plan.

    Examples:
        >>> from tensordict import TensorDict
        >>> cost = torch.tensor([[float("nan")], [1.0], [2.0]])
        >>> td = TensorDict({PRED_COST: cost, PRED_U: cost, PRED_NEXT: torch.ones(3, 2),
        ...     REPLANNED: torch.tensor([[False], [True], [False]]), FEASIBLE: torch.ones(3, 1).bool(),
        ...     ("next", "observation"): torch.zeros(3, 2), ("next", "reward"): -torch.ones(3, 1)}, [3])
        >>> m = episode_metrics(td, torch.ones(2))
        >>> m["env_return"], m["real_cost"], m["predicted_cost"], m["prediction_mse"], m["replans"]
        (-3.0, 2.0, 3.0, 1.0, 1)
    """
    planned = ~torch.isnan(td[PRED_COST].squeeze(-1))
    replanned = td[REPLANNED].squeeze(-1)
    env_return, steps = float(td["next", "reward"].double().sum()), int(td.shape[0])
    if not planned.any():
        nan = dict.fromkeys(METRICS, float("nan"))
        return nan | {"env_return": env_return, "replans": 0, "steps": steps}
    err = (td[PRED_NEXT][planned] - td["next", "observation"][planned]) / scale
    predicted_cost = float(td[PRED_COST].squeeze(-1)[planned].sum())
    real_cost = float(-td["next", "reward"].squeeze(-1)[planned].sum())
    feasible = td[FEASIBLE].squeeze(-1)[replanned]
    return {
        "env_return": env_return,
        "prediction_mse": float(err.pow(2).mean()),
        "cost_error": abs(predicted_cost - real_cost),
        "real_cost": real_cost,
        "predicted_cost": predicted_cost,
        "replans": int(replanned.sum()),
        "mean_u": float(td[PRED_U].squeeze(-1)[planned].mean()),
        "feasible_fraction": float(feasible.float().mean()) if feasible.numel() else float("nan"),
        "steps": steps,
    }


def planned_trajectory(td: TensorDictBase) -> dict[str, list]:
    """The real and predicted next states, u and re-plans of one MPC episode's planned steps,
    as lists (e.g. for a plot of predicted against real states).

    Examples:
        >>> from tensordict import TensorDict
        >>> cost = torch.tensor([[float("nan")], [1.0]])
        >>> td = TensorDict({PRED_COST: cost, PRED_U: cost, PRED_NEXT: torch.ones(2, 1),
        ...     REPLANNED: torch.ones(2, 1).bool(), ("next", "observation"): torch.zeros(2, 1)}, [2])
        >>> planned_trajectory(td)
        {'real': [[0.0]], 'predicted': [[1.0]], 'uncertainty': [1.0], 'replanned': [True]}
    """
    planned = ~torch.isnan(td[PRED_COST].squeeze(-1))
    return {
        "real": td["next", "observation"][planned].tolist(),
        "predicted": td[PRED_NEXT][planned].tolist(),
        "uncertainty": td[PRED_U].squeeze(-1)[planned].tolist(),
        "replanned": td[REPLANNED].squeeze(-1)[planned].tolist(),
    }
