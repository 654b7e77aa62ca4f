"""The online loop (torchrl_recon.fitting.online) on a real gymnasium env, at smoke scale."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import pytest
import torch
from tensordict import TensorDict

import torchrl_recon.fitting.online as online
from torchrl_recon.collectors import collect_random
from torchrl_recon.data import make_sequence_buffer, split_by_trajectory
from torchrl_recon.data.buffers import TRAJ_KEY
from torchrl_recon.envs import make_env
from torchrl_recon.fitting.fit import FitResult
from torchrl_recon.fitting.online import (
    FitSchedule,
    fit_models,
    recent_and_sampled,
)
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import exploration_objective
from torchrl_recon.trainers import ModelFitStepper, learn_online

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


@pytest.mark.parametrize(
    ("bad", "error", "message"),
    [
        ({"random_steps": 0}, ValueError, "random_steps must be an int >= 1, got 0."),
        ({"steps_per_iteration": 0}, ValueError, "steps_per_iteration must be an int >= 1, got 0."),
        ({"iterations": -1}, ValueError, "iterations must be an int >= 0, got -1."),
        (
            {"schedule": {"steps": 2}},
            TypeError,
            "schedule must be a FitSchedule or None, got dict.",
        ),
        (
            {"policy_kwargs": {"replan_evry": 3}},
            TypeError,
            "policy_kwargs: got an unexpected keyword argument 'replan_evry' (they are MPCPolicy's keywords).",
        ),
    ],
)
def test_learn_online_refuses_bad_arguments_before_any_env_step(bad, error, message):
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=15)
    world = LSTMWorldModel(3, 1, window=4)
    model = PlanningModel.from_env(world, pendulum_cost, env)
    make = lambda: CEMPlanner(model, Objective(), horizon=4, num_candidates=8)  # noqa: E731
    kwargs = dict(iterations=1, steps_per_iteration=15, random_steps=30, schedule=SCHEDULE) | bad
    env.step = env.reset = None  # the env is never touched
    with pytest.raises(error, match=f"^{re.escape(message)}$"):
        learn_online(env, world, None, make, **kwargs)
    assert not world.obs_norm.fitted


def test_a_world_model_of_members_is_fitted_and_planned_with():
    """learn_online with an ensemble (num_members=3): every member refitted from its own weights
    (they stay distinct), the model error the members' mean."""
    from torchrl_recon.fitting.online import model_error

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


TINY_FIT = FitSchedule(steps=2, refit_steps=2, eval_every=1, slice_len=6, num_slices=2)


def _eight_step_episodes(frames: int):
    """``frames`` random Pendulum-v1 steps in episodes of 8 (trajectory ids 0, 1, ...)."""
    return collect_random(
        make_env("Pendulum-v1", seed=0, max_episode_steps=8), frames=frames, seed=0
    )


def test_recent_and_sampled_keeps_the_new_trajectories_and_draws_whole_old_ones():
    ids = torch.arange(96) // 8  # 10 old trajectories of 8 steps (ids 0..9), 2 new (10, 11)
    data = TensorDict({TRAJ_KEY: ids, "t": torch.arange(96)}, [96])
    mixed = recent_and_sampled(data, 10, 20, seed=0)
    kept = torch.unique(mixed[TRAJ_KEY]).tolist()
    assert kept[-2:] == [10, 11] and len(kept) == 5  # 3 old ones: 24 steps, the first >= 20
    assert all((ids == i).sum() == (mixed[TRAJ_KEY] == i).sum() for i in kept)  # whole ones
    assert mixed["t"].tolist() == recent_and_sampled(data, 10, 20, seed=0)["t"].tolist()
    draws = {
        tuple(torch.unique(recent_and_sampled(data, 10, 20, seed=s)[TRAJ_KEY]).tolist())
        for s in range(5)
    }
    assert len(draws) > 1  # the seed draws the old ones
    assert len(recent_and_sampled(data, 10, 0, seed=0)) == 16  # the new steps only
    assert len(recent_and_sampled(data, 10, 10**6, seed=0)) == 96  # every old one


def test_a_refit_with_refit_old_steps_trains_on_the_new_steps_and_a_sample(monkeypatch):
    data = _eight_step_episodes(96)  # trajectories 0..11, the last two new
    schedule = replace(TINY_FIT, val_fraction=0.2, refit_old_steps=8)
    world = LSTMWorldModel(3, 1, window=4)
    fit_models(world, None, data, schedule, seed=0, warm=False)
    seen = {}

    def spy(model, buffer, **kwargs):
        seen["train"] = torch.unique(buffer[:][TRAJ_KEY]).tolist()
        seen["val"] = torch.unique(kwargs["val_buffer"][:][TRAJ_KEY]).tolist()
        return FitResult(0, 0.0)

    monkeypatch.setattr(online, "world_model_fit", lambda model: spy)
    fit_models(world, None, data, schedule, seed=3, warm=True, new_steps=16)
    train, val = split_by_trajectory(data, 0.2, seed=3)
    new = [i for i in torch.unique(train[TRAJ_KEY]).tolist() if i >= 10]
    assert seen["train"][len(seen["train"]) - len(new) :] == new
    assert len(seen["train"]) == len(new) + 1  # one old trajectory of 8 steps
    assert seen["val"] == torch.unique(val[TRAJ_KEY]).tolist()  # drawn from all data
    with pytest.raises(ValueError, match="needs new_steps"):
        fit_models(world, None, data, schedule, seed=3, warm=True)


def test_a_refit_without_refit_uncertainty_leaves_the_estimator_as_it_was():
    data = _eight_step_episodes(48)
    schedule = replace(TINY_FIT, val_fraction=0.34, refit_uncertainty=False)
    world, estimator = LSTMWorldModel(3, 1, window=4), ReconstructionUncertainty(3, 1, window=4)
    assert set(fit_models(world, estimator, data, schedule, seed=0, warm=False)) == {
        "world_model",
        "uncertainty",
    }  # the first fit fits both
    before = {k: v.clone() for k, v in estimator.state_dict().items()}
    assert set(fit_models(world, estimator, data, schedule, seed=1, warm=True)) == {"world_model"}
    assert all(torch.equal(v, estimator.state_dict()[k]) for k, v in before.items())


def test_each_network_is_fitted_with_its_own_settings(monkeypatch):
    """``FitSchedule.uncertainty`` sets the estimator's fits apart from the world model's (the
    online recipe's ``training.uncertainty`` block); refits take ``refit_steps`` for both."""
    data = _eight_step_episodes(48)
    schedule = replace(
        TINY_FIT, val_fraction=0.34, lr=3e-3, uncertainty={"lr": 1e-3, "steps": 7, "patience": 1}
    )
    seen = {}

    def spy(name):
        def fit(model, buffer, **kwargs):
            seen[name] = {
                k: kwargs[k] for k in ("steps", "lr", "eval_every", "patience", "compile")
            }
            return FitResult(0, 0.0)

        return fit

    monkeypatch.setattr(online, "world_model_fit", lambda model: spy("world_model"))
    monkeypatch.setattr(online, "fit_uncertainty", spy("uncertainty"))
    world, estimator = LSTMWorldModel(3, 1, window=4), ReconstructionUncertainty(3, 1, window=4)
    fit_models(world, estimator, data, schedule, seed=0, warm=False)
    base = {"eval_every": 1, "compile": False}
    assert seen["world_model"] == base | {"steps": 2, "lr": 3e-3, "patience": 10}
    assert seen["uncertainty"] == base | {"steps": 7, "lr": 1e-3, "patience": 1}
    fit_models(world, estimator, data, schedule, seed=1, warm=True)
    assert seen["world_model"]["steps"] == seen["uncertainty"]["steps"] == 2  # refit_steps
    assert seen["uncertainty"]["lr"] == 1e-3
    compiled_world = replace(TINY_FIT, compile=True)  # the world model's only, as documented
    assert compiled_world.estimator_settings()["compile"] is False
    assert replace(compiled_world, uncertainty={"compile": True}).estimator_settings()["compile"]
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['hidden'\]"):
        replace(TINY_FIT, uncertainty={"hidden": 4})
    with pytest.raises(TypeError, match="must be a mapping of fit settings, got NoneType"):
        replace(TINY_FIT, uncertainty=None)


@pytest.mark.parametrize(
    ("settings", "error", "message"),
    [
        ({"steps": 0}, ValueError, "steps must be an int >= 1, got 0."),
        ({"refit_steps": -5}, ValueError, "refit_steps must be an int >= 1, got -5."),
        ({"refit_old_steps": -1}, ValueError, "refit_old_steps must be an int >= 0, got -1."),
        ({"lr": float("nan")}, ValueError, "lr must be a finite number > 0, got nan."),
        ({"patience": 0}, ValueError, "patience must be an int >= 1, got 0."),
        ({"val_fraction": 1.0}, ValueError, "val_fraction must be in (0, 1), got 1.0."),
        (
            {"mode": "two_step"},
            ValueError,
            "mode must be 'multi_step' or 'one_step', got 'two_step'.",
        ),
        ({"uncertainty": {"lr": -1e-3}}, ValueError, "uncertainty.lr must be a finite number > 0"),
        ({"uncertainty": {"steps": 2.5}}, ValueError, "uncertainty.steps must be an int >= 1"),
        (
            {"uncertainty": {"compile": "yes"}},
            TypeError,
            "uncertainty.compile must be True or False",
        ),
    ],
)
def test_a_schedule_out_of_range_is_refused_when_made(settings, error, message):
    """Before any env step: the first fit comes only after the random data are collected."""
    with pytest.raises(error, match=f"^{re.escape(message)}"):
        FitSchedule(**settings)


def test_a_schedule_may_stop_early_never_and_refit_on_new_data_only():
    schedule = FitSchedule(patience=None, refit_old_steps=0, uncertainty={"patience": None})
    assert schedule.world_model_settings()["patience"] is None
    assert schedule.estimator_settings()["patience"] is None


def test_a_schedule_with_cuda_graph_fits_the_world_models_members_with_it(monkeypatch):
    """``FitSchedule(cuda_graph=True)``: the world model's (members') fits and refits take
    ``cuda_graph=True``, the estimator's not; a world model without members or off CUDA is
    refused before any fit (a ``ModelFitStepper``: when it is built), and so is a value that is
    not a bool."""
    import torchrl_recon.fitting.fit as fit_module

    data = _eight_step_episodes(48)
    schedule = replace(TINY_FIT, val_fraction=0.34, cuda_graph=True)
    for module in (fit_module, online):  # a CPU run
        monkeypatch.setattr(module, "check_cuda_graph", lambda *args: None)
    built = []
    monkeypatch.setattr(
        fit_module, "CapturedStep", lambda *args: built.append(args) or args[0]
    )  # the step, uncaptured
    members = LSTMWorldModel(3, 1, window=4, num_members=2)
    estimator = ReconstructionUncertainty(3, 1, window=4)
    fit_models(members, estimator, data, schedule, seed=0, warm=False)
    fit_models(members, estimator, data, schedule, seed=1, warm=True)
    assert len(built) == 2  # the world model's fit and refit; not the estimator's
    with pytest.raises(ValueError, match=r"must hold members \(num_members=R\)"):
        fit_models(LSTMWorldModel(3, 1, window=4), None, data, schedule, seed=0, warm=False)
    monkeypatch.undo()  # the device check back
    with pytest.raises(ValueError, match="must be on a CUDA device, got cpu"):
        schedule.check_world_model(members)
    with pytest.raises(ValueError, match="must be on a CUDA device, got cpu"):
        ModelFitStepper(
            members,
            estimator,
            make_sequence_buffer(10, slice_len=8, num_slices=4),
            schedule=schedule,
        )
    with pytest.raises(TypeError, match="cuda_graph must be True or False, got 1"):
        replace(TINY_FIT, cuda_graph=1)
