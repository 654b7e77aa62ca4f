"""What the steps before the first plan do: random (the paper's), the rest action, or a plan."""

from __future__ import annotations

import pytest
import torch

from tests.normalized import fitted
from torchrl_recon.envs import make_env
from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import MPCPolicy


def _policy(low=-1.0, high=1.0, **kwargs) -> MPCPolicy:
    torch.manual_seed(0)
    model = PlanningModel(
        fitted(LSTMWorldModel(12, 4, window=3)), drone_cost, action_low=low, action_high=high
    )
    planner = CEMPlanner(
        model, Objective(), horizon=5, num_candidates=16, num_elites=4, iterations=2
    )
    return MPCPolicy(planner, **kwargs)


def _rollout(policy: MPCPolicy, steps: int = 6):
    env = make_env("drone", seed=0).append_transform(policy.make_tensordict_primer())
    torch.manual_seed(1)
    return env.rollout(steps, policy)


def test_zeros_holds_the_rest_action_until_the_first_plan():
    td = _rollout(_policy(warmup="zeros", warmup_steps=4))
    replanned = td["mpc_replanned"].squeeze(-1).tolist()
    assert replanned == [False] * 4 + [True, True]
    assert (td["action"][:4] == 0).all()


def test_random_is_the_default_and_draws_uniform_actions():
    default, random = _rollout(_policy()), _rollout(_policy(warmup="random"))
    assert torch.equal(default["action"], random["action"])
    assert (default["action"][:3] != 0).all()


def test_plan_plans_from_the_first_step_with_a_padded_context():
    policy = _policy(warmup="plan")
    td = _rollout(policy)
    assert td["mpc_replanned"].squeeze(-1).tolist() == [True] * 6
    assert not td["mpc_predicted_cost"].isnan().any()  # every action is planned
    # The context after two steps: the episode's first observation and the rest action
    # stand in for the step before the episode's start.
    state = td[2].select("mpc_obs_history", "mpc_action_history", "mpc_steps_seen")[None]
    obs_h, act_h = policy._context(state, td[2]["observation"][None], torch.tensor([2]))
    first = td[0]["observation"]
    assert torch.equal(obs_h[0, 0], first) and torch.equal(obs_h[0, 1], first)
    assert torch.equal(obs_h[0, 2], td[1]["observation"])
    assert (act_h[0, 0] == 0).all() and torch.equal(act_h[0, 2], td[1]["action"])


def test_the_rest_action_is_clamped_into_the_bounds():
    assert _policy(low=0.5, high=1.0, warmup="zeros")._rest_action().tolist() == [0.5] * 4
    assert _policy(low=-1.0, high=-0.25, warmup="zeros")._rest_action().tolist() == [-0.25] * 4


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"warmup": "noise"}, r"warmup must be one of \['random', 'zeros', 'plan'\], got 'noise'"),
        ({"warmup": "plan", "warmup_steps": 5}, r"warmup='plan' plans from the first step"),
        ({"warmup": "zeros", "warmup_steps": 1}, r"warmup_steps=1 is shorter than the context"),
    ],
)
def test_bad_warmup_arguments_are_one_clear_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        _policy(**kwargs)
