"""The online loop (torchrl_recon.training.online) on a real gymnasium env, at smoke scale."""

from __future__ import annotations

import math

import pytest
import torch

from torchrl_recon.data import split_by_trajectory
from torchrl_recon.envs import make_env
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import exploration_objective
from torchrl_recon.training.online import FitSchedule, learn_online

SCHEDULE = FitSchedule(
    steps=6, refit_steps=3, eval_every=3, slice_len=8, num_slices=4, val_fraction=0.34
)


def pendulum_cost(obs, action, next_obs):
    theta = torch.atan2(next_obs[..., 1], next_obs[..., 0])
    return theta.pow(2) + 0.1 * next_obs[..., 2].pow(2)


def _learn(seed: int, with_u: bool = True):
    torch.manual_seed(seed)
    env = make_env("Pendulum-v1", seed=seed, max_episode_steps=15)
    world = LSTMWorldModel(3, 1, window=4)
    estimator = ReconstructionUncertainty(3, 1, window=4) if with_u else None
    model = PlanningModel.from_env(world, pendulum_cost, env, uncertainty=estimator)
    seen = []
    records, data = learn_online(
        env,
        world,
        estimator,
        lambda: CEMPlanner(
            model,
            Objective(beta=0.1 if with_u else 0.0),
            horizon=4,
            num_candidates=16,
            iterations=2,
            num_elites=4,
        ),
        iterations=2,
        steps_per_iteration=30,
        random_steps=45,
        schedule=SCHEDULE,
        seed=seed,
        on_iteration=seen.append,
    )
    return records, data, seen, world


def test_records_data_and_callbacks():
    records, data, seen, _ = _learn(0)
    assert seen == records
    assert [r.iteration for r in records] == [0, 1, 2]
    assert [r.env_steps for r in records] == [45, 75, 105]
    assert len(data) == 105
    # 15-step episodes: 3 random ones, then 2 per iteration, each with a return
    assert [len(r.episode_returns) for r in records] == [3, 2, 2]
    assert math.isnan(records[0].model_error)
    for r in records[1:]:
        assert math.isfinite(r.model_error) and r.model_error > 0
        assert math.isfinite(r.mean_uncertainty)
        assert 0 < r.replans <= 30  # every step re-plans, less the random warm-up steps
        assert r.plan_s > 0 and r.fit_s > 0
    ids = data["collector", "traj_ids"]
    assert torch.unique(ids).numel() == 7  # trajectory ids stay distinct across iterations


def test_same_seed_same_numbers():
    a, data_a, _, _ = _learn(1)
    b, data_b, _, _ = _learn(1)
    assert [r.episode_returns for r in a] == [r.episode_returns for r in b]
    assert [r.model_error for r in a[1:]] == [r.model_error for r in b[1:]]
    assert torch.equal(data_a["action"], data_b["action"])


def test_refits_keep_the_first_normalisation():
    torch.manual_seed(2)
    records, data, _, world = _learn(2, with_u=False)
    # the normalisation is fitted once, on the random data's training split (its first 45 steps)
    train, _ = split_by_trajectory(data[:45], SCHEDULE.val_fraction, seed=2)
    first = LSTMWorldModel(3, 1, window=4)
    first.fit_normalization(train["observation"], train["action"], train["next", "observation"])
    assert torch.equal(world.obs_norm.loc, first.obs_norm.loc)
    assert torch.equal(world.obs_norm.scale, first.obs_norm.scale)
    assert math.isnan(records[1].mean_uncertainty)  # no estimator


def test_exploration_phase_plays_the_first_rounds():
    torch.manual_seed(3)
    env = make_env("Pendulum-v1", seed=3, max_episode_steps=15)
    world = LSTMWorldModel(3, 1, window=4)
    estimator = ReconstructionUncertainty(3, 1, window=4)
    model = PlanningModel.from_env(world, pendulum_cost, env, uncertainty=estimator)

    def planner(objective):
        return lambda: CEMPlanner(
            model, objective, horizon=5, num_candidates=16, iterations=2, num_elites=4
        )

    records, data = learn_online(
        env,
        world,
        estimator,
        planner(Objective()),
        iterations=3,
        steps_per_iteration=30,
        random_steps=45,
        schedule=SCHEDULE,
        seed=3,
        explore_iterations=2,
        make_explorer=planner(exploration_objective(ratio=1.2, cap=2.0)),
    )
    assert [r.policy for r in records] == ["random", "explore", "explore", "mpc"]
    assert len(data) == 45 + 3 * 30
    # the explorer runs each 5-step plan open loop; the MPC policy re-plans at every step
    assert all(r.replans <= 30 // 5 + 1 for r in records[1:3])
    assert records[3].replans > 2 * max(r.replans for r in records[1:3])


def test_exploration_phase_needs_an_explorer_and_an_estimator():
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=15)
    world = LSTMWorldModel(3, 1, window=4)
    model = PlanningModel.from_env(world, pendulum_cost, env)
    make = lambda: CEMPlanner(model, Objective(), horizon=4, num_candidates=8)  # noqa: E731
    common = dict(iterations=1, steps_per_iteration=15, random_steps=30, schedule=SCHEDULE)
    with pytest.raises(ValueError, match="explore_iterations=1 needs make_explorer"):
        learn_online(env, world, None, make, explore_iterations=1, make_explorer=make, **common)
    with pytest.raises(ValueError, match="explore_iterations=2 must be between 0 and"):
        learn_online(env, world, None, make, explore_iterations=2, **common)


def test_a_world_model_of_members_is_fitted_and_planned_with():
    """learn_online with an ensemble (num_members=3): every member refitted from its own weights
    (they stay distinct), the model error the members' mean."""
    from torchrl_recon.training.online import model_error

    torch.manual_seed(5)
    env = make_env("Pendulum-v1", seed=5, max_episode_steps=15)
    world = LSTMWorldModel(3, 1, window=4, hidden_size=8, dense_size=8, num_members=3)
    model = PlanningModel.from_env(world, pendulum_cost, env)
    before = [m.head.weight.clone() for m in world.split()]
    records, data = learn_online(
        env,
        world,
        None,
        lambda: CEMPlanner(
            model, Objective(), horizon=4, num_candidates=16, iterations=2, num_elites=4
        ),
        iterations=1,
        steps_per_iteration=30,
        random_steps=45,
        schedule=SCHEDULE,
        seed=5,
    )
    members = world.split()
    assert all(not torch.equal(m.head.weight, b) for m, b in zip(members, before, strict=True))
    assert not torch.equal(members[0].head.weight, members[1].head.weight)
    assert bool(members[0].obs_norm.fitted)
    assert records[1].env_steps == 75 and math.isfinite(records[1].model_error)
    errors = [model_error(m, data, SCHEDULE.slice_len) for m in members]
    assert model_error(world, data, SCHEDULE.slice_len) == pytest.approx(sum(errors) / 3)
