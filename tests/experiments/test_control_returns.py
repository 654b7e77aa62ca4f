"""The control table's env return, its random policy, and episodes that end in the warm-up."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from torchrl_recon.evaluation import episode_metrics
from torchrl_recon.policies.mpc import FEASIBLE, PRED_COST, PRED_NEXT, PRED_U, REPLANNED
from torchrl_recon.reports.control import settings_table


def _episode(steps: int, planned_from: int) -> TensorDict:
    cost = torch.full((steps, 1), float("nan"))
    cost[planned_from:] = 1.0
    return TensorDict(
        {
            PRED_COST: cost,
            PRED_U: cost.clone(),
            PRED_NEXT: torch.zeros(steps, 2),
            REPLANNED: torch.zeros(steps, 1, dtype=torch.bool),
            FEASIBLE: torch.ones(steps, 1, dtype=torch.bool),
            ("next", "observation"): torch.zeros(steps, 2),
            ("next", "reward"): -torch.ones(steps, 1),
        },
        [steps],
    )


def test_an_episode_that_ends_in_the_warmup_keeps_its_env_return():
    metrics = episode_metrics(_episode(3, planned_from=5), torch.ones(2))
    assert metrics["env_return"] == -3.0 and metrics["steps"] == 3
    assert math.isnan(metrics["real_cost"]) and metrics["replans"] == 0
    planned = episode_metrics(_episode(6, planned_from=2), torch.ones(2))
    assert planned["env_return"] == -6.0 and planned["real_cost"] == 4.0  # planned steps only


def test_the_table_counts_episodes_that_ended_in_the_warmup():
    settings = {
        "baseline": {
            "mean": {"env_return": -3.0},
            "std": {"env_return": 0.0},
            "n_episodes": 5,
            "ended_in_warmup": 2,
        }
    }
    assert "5 (2 in warm-up)" in settings_table("t", settings)


# The control smoke's env return and random policy: test_recipes' control smoke checks them
# on its run (_check_env_returns), not on a second run of the same recipe.
