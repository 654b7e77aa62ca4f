"""Planning with the task's termination function: a toy task where the unaware plan fails.

State x, action a in [-1, 1], x' = x + a (an exact linear model). The reward is x' (it grows
towards the limit) and the episode ends once x' > 1. Unaware of the end, the best plan drives
x up as fast as it can (and the real episode ends at the second step); aware of it, the
planner stays at the limit and collects ~1 per step for the whole horizon.
"""

from __future__ import annotations

import pytest
import torch
from torchrl.modules import CEMPlanner as TorchRLCEMPlanner

from tests.normalized import fitted
from torchrl_recon.modules import LinearDeltaModel, LSTMWorldModel
from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
)
from torchrl_recon.planners.model_env import WorldModelPlanningEnv

LIMIT, HORIZON = 1.0, 8


def reward_cost(obs, action, next_obs):
    return -next_obs[..., 0]


def past_limit(obs, action, next_obs):
    return next_obs[..., 0] > LIMIT


def toy_model(termination: bool) -> PlanningModel:
    world = LinearDeltaModel(1, 1)
    world.weight[1, 0] = 1.0  # Δx = a
    return PlanningModel(world, reward_cost, termination_fn=past_limit if termination else None)


PLANNERS = {
    "shooting": lambda m: RandomShootingPlanner(
        m, Objective(), horizon=HORIZON, num_candidates=2000
    ),
    "cem": lambda m: CEMPlanner(
        m, Objective(), horizon=HORIZON, num_candidates=400, iterations=6, num_elites=40
    ),
    "mppi": lambda m: MPPIPlanner(
        m, Objective(), horizon=HORIZON, num_candidates=400, iterations=6, temperature=0.01
    ),
    "icem": lambda m: ICEMPlanner(
        m, Objective(), horizon=HORIZON, num_candidates=400, iterations=6, num_elites=40
    ),
}


def real_return(actions: torch.Tensor, x0: float = 0.0) -> tuple[float, int]:
    """The toy env's return and length when the plan is executed open loop."""
    x, total = x0, 0.0
    for t, a in enumerate(actions.flatten().tolist()):
        x += a
        total += x
        if x > LIMIT:
            return total, t + 1
    return total, len(actions)


@pytest.mark.parametrize("kind", sorted(PLANNERS))
def test_the_aware_plan_stays_alive_where_the_unaware_one_ends(kind):
    context = torch.zeros(1, 1), torch.zeros(1, 1)
    plans = {}
    for aware in (False, True):
        torch.manual_seed(0)
        planner = PLANNERS[kind](toy_model(aware))
        plans[aware] = planner.plan(*context, torch.zeros(1)).actions
    unaware_return, unaware_steps = real_return(plans[False])
    aware_return, aware_steps = real_return(plans[True])
    assert unaware_steps <= 2  # drives over the limit at once
    assert aware_steps >= HORIZON - 1  # passes it at the last step at most (that step still counts)
    assert aware_return > 2 * unaware_return


def test_costs_and_u_stop_after_the_predicted_end():
    model = toy_model(True)
    actions = torch.tensor([0.6, 0.6, 0.6, -1.0]).view(1, 4, 1)  # ends at the 2nd step
    pred = model(torch.zeros(1, 1), torch.zeros(1, 1), torch.zeros(1), actions)
    assert pred.cost.flatten().tolist() == pytest.approx([-0.6, -1.2, 0.0, 0.0])


def test_the_torchrl_adapter_stops_the_reward_after_the_end():
    world = fitted(LSTMWorldModel(1, 1, window=2))
    env = WorldModelPlanningEnv(
        world, reward_cost, termination_fn=lambda s, a, s1: s1[..., 0] > -1e9
    )
    td = env.initial_state(torch.zeros(2, 1), torch.zeros(2, 1), torch.zeros(1))
    rollout = env.rollout(3, auto_reset=False, tensordict=td)
    reward = rollout["next", "reward"].flatten()
    assert reward[0] != 0 and (reward[1:] == 0).all()  # every step ends: only the first counts
    assert TorchRLCEMPlanner(env, planning_horizon=3, optim_steps=1, num_candidates=4, top_k=2)(td)[
        "action"
    ].shape == (1,)


@pytest.mark.parametrize(
    "fn, message",
    [
        (
            lambda s, a, s1: s1,
            r"must return one value per step, a tensor \[2, 3\], got \[2, 3, 1\]",
        ),
        (lambda s, a, s1: s1[..., 0], r"must return bools"),
        (lambda s, a: s, r"termination_fn\(obs .*\) failed: TypeError"),
    ],
)
def test_a_wrong_termination_function_is_one_clear_error(fn, message):
    world = LinearDeltaModel(1, 1)
    with pytest.raises(ValueError, match=message):
        PlanningModel(world, reward_cost, termination_fn=fn)


def test_a_cost_of_the_wrong_shape_is_refused_when_the_model_is_built():
    with pytest.raises(ValueError, match=r"cost_fn\(obs \[2, 3, 1\].*got \[2, 3, 1\]"):
        PlanningModel(LinearDeltaModel(1, 1), lambda s, a, s1: s1)


def test_gradient_planner_takes_the_termination_too():
    torch.manual_seed(0)
    planner = GradientPlanner(toy_model(True), Objective(), horizon=HORIZON, restarts=8, steps=30)
    plan = planner.plan(torch.zeros(1, 1), torch.zeros(1, 1), torch.zeros(1))
    assert torch.isfinite(plan.actions).all()
