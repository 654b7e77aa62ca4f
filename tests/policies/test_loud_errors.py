"""A policy in an env without an InitTracker raises instead of running a stale plan."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import DoubleToFloat, GymEnv, InitTracker, TransformedEnv

from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import PlanningModel, RandomShootingPlanner
from torchrl_recon.planners.objective import Objective
from torchrl_recon.policies import ExplorationPolicy, MPCPolicy, exploration_objective


def pendulum_cost(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    return torch.atan2(obs[..., 1], obs[..., 0]).pow(2) + 0.1 * obs[..., 2].pow(2)


def _model() -> PlanningModel:
    return PlanningModel(
        fitted(LSTMWorldModel(3, 1, window=2, hidden_size=8, dense_size=8)),
        pendulum_cost,
        uncertainty=fitted(ReconstructionUncertainty(3, 1, window=2, hidden_size=8)),
        action_low=-2.0,
        action_high=2.0,
    )


def _policies() -> dict[str, MPCPolicy]:
    model = _model()
    return {
        "mpc_uncertainty": MPCPolicy(
            RandomShootingPlanner(model, Objective(), horizon=4, num_candidates=8),
            replan="uncertainty",
            threshold=1e6,  # never re-plans on u: the case that ran an all-zero plan silently
        ),
        "mpc_every_step": MPCPolicy(
            RandomShootingPlanner(model, Objective(), horizon=4, num_candidates=8)
        ),
        "exploration": ExplorationPolicy(
            RandomShootingPlanner(model, exploration_objective(), horizon=4, num_candidates=8)
        ),
    }


@pytest.mark.parametrize("name", sorted(_policies()))
def test_missing_init_tracker_is_an_error_naming_what_to_add(name):
    policy = _policies()[name]
    env = TransformedEnv(GymEnv("Pendulum-v1"), DoubleToFloat())
    env.append_transform(policy.make_tensordict_primer())  # primer, but no InitTracker
    with pytest.raises(KeyError, match=r"env\.append_transform\(InitTracker\(\)\)"):
        env.rollout(5, policy)
    with pytest.raises(KeyError, match="InitTracker"):
        policy.check_env(env)


@pytest.mark.parametrize("name", sorted(_policies()))
def test_with_an_init_tracker_the_policy_plans_after_the_warmup(name):
    policy = _policies()[name]
    env = TransformedEnv(GymEnv("Pendulum-v1"), InitTracker())
    env.append_transform(policy.make_tensordict_primer())
    policy.check_env(env)
    torch.manual_seed(0)
    td = env.rollout(5, policy)
    replanned = td["mpc_replanned"].squeeze(-1).tolist()
    assert replanned[:2] == [False, False] and replanned[2]  # context 2, then a first plan
    assert td["action"][2:].abs().sum() > 0  # a plan, not the primer's zeros


def test_check_env_names_a_missing_primer():
    policy = _policies()["mpc_every_step"]
    env = TransformedEnv(GymEnv("Pendulum-v1"), InitTracker())
    with pytest.raises(KeyError, match=r"policy\.make_tensordict_primer\(\)"):
        policy.check_env(env)
