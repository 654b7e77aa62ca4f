from __future__ import annotations

import pytest
import torch
from torch import nn
from torchrl.envs.utils import check_env_specs
from torchrl.modules import CEMPlanner as TorchRLCEMPlanner
from torchrl.modules import MPPIPlanner, ValueOperator
from torchrl.objectives.value import TDLambdaEstimator

from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import PlanningModel
from torchrl_recon.planners.model_env import WorldModelPlanningEnv


def _models():
    torch.manual_seed(0)
    world = LSTMWorldModel(12, 4, window=3, hidden_size=8, dense_size=8)
    world.fit_normalization(torch.randn(50, 12), torch.rand(50, 4) * 2 - 1, torch.randn(50, 12))
    estimator = ReconstructionUncertainty(12, 4, window=3, hidden_size=8)
    estimator.fit_normalization(torch.randn(50, 12), torch.rand(50, 4) * 2 - 1)
    return world, estimator


def _context():
    g = torch.Generator().manual_seed(1)
    return (
        torch.randn(3, 12, generator=g),
        torch.rand(3, 4, generator=g) * 2 - 1,
        torch.randn(12, generator=g),
    )


@pytest.mark.parametrize("with_u", [False, True])
def test_specs_and_rollout_match_the_planning_model(with_u):
    world, estimator = _models()
    env = WorldModelPlanningEnv(
        world, drone_cost, uncertainty=estimator if with_u else None, beta=0.3
    )
    check_env_specs(env)
    ctx = _context()
    rollout = env.rollout(6, auto_reset=False, tensordict=env.initial_state(*ctx))
    pred = PlanningModel(world, drone_cost, uncertainty=estimator if with_u else None)(
        *ctx, rollout["action"][None]
    )
    torch.testing.assert_close(rollout["next", "observation"], pred.states[0], atol=1e-5, rtol=1e-5)
    expected = -pred.cost[0] - (0.3 * pred.uncertainty[0] if with_u else 0.0)
    torch.testing.assert_close(
        rollout["next", "reward"].squeeze(-1), expected, atol=1e-5, rtol=1e-5
    )


def test_torchrl_cem_planner_plans_on_our_model():
    world, estimator = _models()
    env = WorldModelPlanningEnv(world, drone_cost, uncertainty=estimator, beta=0.1)
    planner = TorchRLCEMPlanner(env, planning_horizon=5, optim_steps=2, num_candidates=32, top_k=4)
    action = planner(env.initial_state(*_context()))["action"]
    assert action.shape == (4,) and torch.isfinite(action).all() and (action.abs() <= 1).all()


def test_torchrl_mppi_planner_plans_on_our_model():
    world, _ = _models()
    env = WorldModelPlanningEnv(world, drone_cost)
    value = ValueOperator(nn.Linear(12, 1), in_keys=["observation"])
    advantage = TDLambdaEstimator(gamma=0.99, lmbda=0.95, value_network=value)
    planner = MPPIPlanner(
        env,
        advantage,
        temperature=0.1,
        planning_horizon=5,
        optim_steps=2,
        num_candidates=32,
        top_k=4,
    )
    action = planner(env.initial_state(*_context()))["action"]
    assert action.shape == (4,) and torch.isfinite(action).all()
