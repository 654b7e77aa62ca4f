"""PlanningModel with a world model of R members (an ensemble, PETS's): each candidate imagined
by every member, its cost the members' mean."""

from __future__ import annotations

import torch

from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel


def _cost(obs, action, next_obs):
    return next_obs.pow(2).sum(-1) + 0.1 * action.pow(2).sum(-1)


def _members(r: int = 3) -> LSTMWorldModel:
    torch.manual_seed(0)
    members = [LSTMWorldModel(3, 1, window=4, hidden_size=8, dense_size=8) for _ in range(r)]
    for m in members:
        m.fit_normalization(torch.randn(50, 3), torch.rand(50, 1), torch.randn(50, 3))
    return LSTMWorldModel.from_members(members)


def test_cost_is_the_members_mean_and_states_their_mean():
    stacked = _members()
    ctx = torch.randn(2, 6, 3), torch.rand(2, 6, 1), torch.randn(2, 3)
    actions = torch.rand(2, 5, 7, 1) * 2 - 1
    pred = PlanningModel(stacked, _cost)(*ctx, actions)
    singles = [PlanningModel(m, _cost)(*ctx, actions) for m in stacked.split()]
    assert pred.states.shape == (2, 5, 7, 3) and pred.cost.shape == (2, 5, 7)
    torch.testing.assert_close(pred.cost, torch.stack([p.cost for p in singles]).mean(0))
    torch.testing.assert_close(pred.states, torch.stack([p.states for p in singles]).mean(0))
    # the cost of the mean trajectory is not the mean cost: the members disagree
    assert not torch.allclose(pred.cost, _cost(ctx[2][:, None, None], actions, pred.states))


def test_warmup_state_and_blocks_give_the_same_prediction():
    model = PlanningModel(_members(2), _cost)
    ctx = torch.randn(3, 4, 3), torch.rand(3, 4, 1), torch.randn(3, 3)
    actions = torch.rand(3, 10, 6, 1)
    plain = model(*ctx, actions)
    state = model.warmup(*ctx[:2])
    assert state[0].shape == (2, 3, 8)  # [R, *B, hidden]
    blocked = model(*ctx, actions, state=state, block_rows=9)
    torch.testing.assert_close(blocked.cost, plain.cost)
    torch.testing.assert_close(blocked.states, plain.states)


def test_cem_plans_on_members():
    model = PlanningModel(_members(), _cost)
    planner = CEMPlanner(model, Objective(), horizon=6, num_candidates=40, num_elites=5)
    ctx = torch.randn(4, 3), torch.rand(4, 1), torch.randn(3)
    torch.manual_seed(1)
    result = planner.plan(*ctx)
    assert result.actions.shape == (6, 1) and result.states.shape == (6, 3)
    again = model(*ctx, result.actions[None])
    torch.testing.assert_close(result.cost, again.cost[0])
    torch.testing.assert_close(result.objective, -again.cost[0].sum())
