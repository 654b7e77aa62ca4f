"""A learned reward and termination (RewardModel): it learns a task's reward and end from
transitions, the planners read it as a given cost, it is refused unfitted, and its (and the world
model's) statistics refit on more data without changing what they predict."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_recon.data import TRAJ_KEY
from torchrl_recon.fitting import load_checkpoint, save_checkpoint
from torchrl_recon.fitting.online import FitSchedule, fit_models
from torchrl_recon.modules import (
    LearnedCost,
    LearnedTermination,
    LSTMWorldModel,
    RewardModel,
)
from torchrl_recon.objectives import RewardLoss
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel


def transitions(n: int, seed: int = 0) -> TensorDict:
    """Trajectories of 20 steps of s' = s + 0.1 a in 2-D; reward −|s'|², terminated |s'_0| > 1."""
    g = torch.Generator().manual_seed(seed)
    s = torch.rand(n, 2, generator=g) * 3 - 1.5
    a = torch.rand(n, 1, generator=g) * 2 - 1
    s1 = s + 0.1 * a
    return TensorDict(
        {
            "observation": s,
            "action": a,
            ("next", "observation"): s1,
            ("next", "reward"): -s1.pow(2).sum(-1, keepdim=True),
            ("next", "terminated"): s1[:, :1].abs() > 1,
            ("next", "done"): s1[:, :1].abs() > 1,
            TRAJ_KEY: torch.arange(n) // 20,
        },
        [n],
    )


SCHEDULE = FitSchedule(
    steps=400, refit_steps=50, eval_every=50, slice_len=10, num_slices=16, val_fraction=0.2
)


def test_it_learns_a_reward_and_a_termination_the_planner_reads():
    torch.manual_seed(0)
    data, test = transitions(1000), transitions(400, seed=1)
    world, rewards = LSTMWorldModel(2, 1, window=3), RewardModel(2, 1, termination=True)
    losses = fit_models(world, None, data, SCHEDULE, seed=0, warm=False, reward_model=rewards)
    assert set(losses) == {"world_model", "reward_model"}
    args = test["observation"], test["action"], test["next", "observation"]
    with torch.no_grad():
        error = (rewards.reward(*args) - test["next", "reward"][:, 0]).abs().mean()
        ends = LearnedTermination(rewards)(*args) == test["next", "terminated"][:, 0]
    spread = test["next", "reward"].std()
    assert error < 0.15 * spread, (error, spread)
    assert ends.float().mean() > 0.95
    model = PlanningModel(world, LearnedCost(rewards), termination_fn=LearnedTermination(rewards))
    assert model.reward_model is rewards
    plan = CEMPlanner(model, Objective(), horizon=5, num_candidates=64, iterations=3, num_elites=8)
    result = plan.plan(test["observation"][:3], test["action"][:3], torch.tensor([0.8, 0.8]))
    # the learned reward −|s|² is raised by moving s towards 0: the first action is negative
    assert result.actions[0, 0] < 0


def test_an_unfitted_reward_model_is_refused_before_planning():
    world, rewards = LSTMWorldModel(2, 1, window=3), RewardModel(2, 1)
    data = transitions(100)
    world.fit_normalization(data["observation"], data["action"], data["next", "observation"])
    model = PlanningModel(world, LearnedCost(rewards))
    with pytest.raises(ValueError, match="reward model's normalisation .* never fitted"):
        model(torch.zeros(3, 2), torch.zeros(3, 1), torch.zeros(2), torch.zeros(4, 5, 1))


def test_the_wrappers_and_the_model_refuse_what_they_cannot_do():
    with pytest.raises(ValueError, match="reward=True or termination=True"):
        RewardModel(2, 1, reward=False)
    with pytest.raises(TypeError, match="learns the termination"):
        LearnedTermination(RewardModel(2, 1))
    with pytest.raises(TypeError, match="learns the reward"):
        LearnedCost(RewardModel(2, 1, reward=False, termination=True))
    with pytest.raises(ValueError, match=r"threshold must be in \(0, 1\)"):
        LearnedTermination(RewardModel(2, 1, termination=True), threshold=1.0)


def test_a_nan_reward_is_refused_naming_the_key_and_index():
    data = transitions(100)
    data["next", "reward"][7, 0] = float("nan")
    with pytest.raises(ValueError, match=r"\('next', 'reward'\) contains NaN .* \[7, 0\]"):
        fit_models(
            LSTMWorldModel(2, 1, window=3),
            None,
            data,
            SCHEDULE,
            seed=0,
            warm=False,
            reward_model=RewardModel(2, 1),
        )
    rewards = RewardModel(2, 1)
    rewards.fit_normalization(
        *(transitions(50)[k] for k in ("observation", "action")),
        transitions(50)["next", "observation"],
        transitions(50)["next", "reward"],
    )
    with pytest.raises(ValueError, match=r"\('next', 'reward'\) contains NaN"):
        RewardLoss(rewards)(data[:10])


def test_data_without_the_termination_is_refused_in_one_line():
    data = transitions(100).exclude(("next", "terminated"))
    with pytest.raises(ValueError, match=r"no \('next', 'terminated'\) to fit"):
        fit_models(
            LSTMWorldModel(2, 1, window=3),
            None,
            data,
            SCHEDULE,
            seed=0,
            warm=False,
            reward_model=RewardModel(2, 1, termination=True),
        )


def test_a_checkpoint_holds_the_reward_model(tmp_path):
    rewards = RewardModel(2, 1, termination=True, hidden_size=16)
    data = transitions(50)
    rewards.fit_normalization(
        data["observation"], data["action"], data["next", "observation"], data["next", "reward"]
    )
    save_checkpoint(tmp_path / "m.pt", {"reward_model": rewards})
    loaded = RewardModel(2, 1, termination=True, hidden_size=16)
    load_checkpoint(tmp_path / "m.pt", {"reward_model": loaded})
    args = data["observation"], data["action"], data["next", "observation"]
    assert torch.equal(loaded.reward(*args), rewards.reward(*args))


@pytest.mark.parametrize("members", [None, 3])
def test_renormalizing_keeps_the_world_models_predictions(members):
    torch.manual_seed(0)
    data = transitions(200)
    obs, action, next_obs = data["observation"], data["action"], data["next", "observation"]
    singles = [LSTMWorldModel(2, 1, window=3) for _ in range(members or 1)]
    for m in singles:
        m.fit_normalization(obs, action, next_obs)
    world = singles[0] if members is None else LSTMWorldModel.from_members(singles)
    lead = () if members is None else (members,)
    ctx_s, ctx_a = torch.randn(*lead, 3, 2), torch.randn(*lead, 3, 1)
    plans = torch.rand(*lead, 6, 4, 1)
    start = obs[0].expand(*lead, 2)
    before = world.imagine(ctx_s, ctx_a, start, plans)
    world.refit_normalization(3 * obs + 1, action - 0.5, 3 * next_obs + 1.2)
    after = world.imagine(ctx_s, ctx_a, start, plans)
    torch.testing.assert_close(after, before, atol=1e-5, rtol=1e-5)
    assert torch.allclose(
        world.obs_norm.scale, (3 * obs).std(0).expand_as(world.obs_norm.scale), atol=1e-4
    )


def test_a_feature_constant_so_far_starts_with_zero_weight_when_it_moves():
    data = transitions(200)
    obs = torch.cat([data["observation"], torch.zeros(200, 1)], -1)  # a force, 0 so far
    next_obs = torch.cat([data["next", "observation"], torch.zeros(200, 1)], -1)
    world = LSTMWorldModel(3, 1, window=3)
    world.fit_normalization(obs, data["action"], next_obs)
    assert world.obs_norm.scale[2] == 1  # the normaliser's scale for a constant feature
    ctx = obs[:3], data["action"][:3]
    plans = torch.rand(6, 4, 1)
    moved = torch.cat([obs[:, :2], 10 * torch.randn(200, 1)], -1)  # it jumps to ~10 at a rail
    world.refit_normalization(moved, data["action"], moved)
    assert world.lstm.weight_ih_l0[:, 2].abs().max() == 0  # it cannot swamp the gates
    assert world.obs_norm.scale[2] > 5
    # the model's predictions on the data so far (the force at 0) are unchanged
    before = world.imagine(*ctx, obs[3], plans)
    assert torch.isfinite(before).all()


@pytest.mark.slow  # 8 s; the reward model's fit and use stay
def test_a_warm_refit_renormalizes_on_all_data_when_asked():
    torch.manual_seed(0)
    data = transitions(600)
    world, rewards = LSTMWorldModel(2, 1, window=3), RewardModel(2, 1)
    first = data[:300]
    fit_models(world, None, first, SCHEDULE, seed=0, warm=False, reward_model=rewards)
    fitted = world.obs_norm.scale.clone()
    bigger = data.clone()
    bigger["observation"][300:] *= 4
    bigger["next", "observation"][300:] *= 4
    schedule = FitSchedule(**{**SCHEDULE.__dict__, "renormalize": True})
    fit_models(world, None, bigger, schedule, seed=1, warm=True, reward_model=rewards)
    assert (world.obs_norm.scale > 1.5 * fitted).all()
    assert torch.allclose(
        rewards.obs_norm.scale,
        torch.cat([bigger["observation"], bigger["next", "observation"]]).std(0),
        rtol=1e-4,
    )
    fit_models(world, None, bigger, SCHEDULE, seed=1, warm=True, reward_model=rewards)  # off: kept
    assert (world.obs_norm.scale > 1.5 * fitted).all()


def test_the_trainer_hook_fits_a_reward_models_statistics_from_the_first_batch():
    from torchrl_recon.trainers import FitNormalization

    world, rewards = LSTMWorldModel(2, 1, window=3), RewardModel(2, 1, termination=True)
    batch = transitions(60)
    FitNormalization(world, reward_model=rewards)(batch)
    torch.testing.assert_close(rewards.reward_norm.loc, batch["next", "reward"].mean(0))
    batch["next", "reward"][3] = float("inf")
    with pytest.raises(ValueError, match=r"\('next', 'reward'\).*first at row 3"):
        FitNormalization(world, reward_model=RewardModel(2, 1))(batch)
