"""One builder of the online Trainer: ``OnlineTrainer.from_env``, which ``learn_online`` and the
config store's ``make_online_trainer`` call; its checks come before any planner or env step."""

from __future__ import annotations

import functools

import pytest
from torchrl.trainers import TrainerHookBase

from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.fitting.online import FitSchedule
from torchrl_recon.modules import (
    LearnedCost,
    LSTMWorldModel,
    ReconstructionUncertainty,
    RewardModel,
)
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import ExplorationPolicy, MPCPolicy, exploration_objective
from torchrl_recon.trainers import OnlineTrainer, learn_online
from torchrl_recon.trainers.configs import make_online_trainer

SCHEDULE = FitSchedule(
    steps=4, refit_steps=2, eval_every=2, slice_len=8, num_slices=4, val_fraction=0.34
)
SIZES = dict(iterations=1, steps_per_iteration=20, random_steps=40)


class Built(Exception):
    """Raised by the spy in place of building, so no test here trains."""


@pytest.fixture
def calls(monkeypatch) -> list[dict]:
    """The keywords of every ``OnlineTrainer.from_env`` call (the call then raises Built)."""
    seen: list[dict] = []

    def spy(cls, env, world_model, estimator, make_planner, **kwargs):
        seen.append(kwargs | {"world_model": world_model, "make_planner": make_planner})
        raise Built

    monkeypatch.setattr(OnlineTrainer, "from_env", classmethod(spy))
    return seen


def _planner(env, world, cost=pendulum):
    model = PlanningModel.from_env(world, cost, env)
    return lambda: CEMPlanner(model, Objective(), horizon=4, num_candidates=8, num_elites=2)


def test_learn_online_and_the_config_builder_both_build_through_from_env(calls):
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world = LSTMWorldModel(3, 1, window=4)
    with pytest.raises(Built):
        learn_online(env, world, None, _planner(env, world), schedule=SCHEDULE, seed=4, **SIZES)
    with pytest.raises(Built):
        make_online_trainer(
            env=env,
            world_model=functools.partial(LSTMWorldModel, window=4),
            cost="torchrl_recon.envs.gym_costs:pendulum",
            planner=functools.partial(CEMPlanner, horizon=4, num_candidates=8, num_elites=2),
            objective=Objective(),
            policy=MPCPolicy,
            schedule=SCHEDULE,
            seed=4,
            **SIZES,
        )
    assert len(calls) == 2
    for call in calls:
        assert (call["seed"], call["schedule"], call["iterations"]) == (4, SCHEDULE, 1)
        assert type(call["make_planner"]()) is CEMPlanner
    assert calls[0]["world_model"] is world and calls[1]["world_model"].window == 4


def test_from_env_builds_the_collector_policies_and_learned_reward_from_the_planners():
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world, rewards = LSTMWorldModel(3, 1, window=4), RewardModel(3, 1)
    hook = TrainerHookBase.__new__(TrainerHookBase)
    registered = []
    hook.register = registered.append
    trainer = OnlineTrainer.from_env(
        env,
        world,
        None,
        _planner(env, world, LearnedCost(rewards)),
        make_policy=functools.partial(MPCPolicy, replan="every_n", replan_every=2),
        schedule=SCHEDULE,
        progress=False,
        hooks=[hook],
        **SIZES,
    )
    policy = trainer.collector.policies["mpc"]
    assert type(policy) is MPCPolicy and policy.replan_every == 2
    assert trainer.collector.total_frames == 60 and trainer.buffer is not None
    assert trainer.log_iteration.slice_len == SCHEDULE.slice_len
    assert trainer._modules["reward_model"] is rewards and registered == [trainer]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"iterations": -1}, "iterations must be an int >= 0, got -1."),
        ({"schedule": {"steps": 2}}, "schedule must be a FitSchedule or None, got dict."),
        ({"explore_iterations": 1}, "explore_iterations=1 needs make_explorer and an estimator"),
        ({"make_planner": None}, "the MPC iterations need make_planner."),
        ({"hooks": ["log"]}, "hooks must be TrainerHookBase instances, got str."),
    ],
)
def test_from_env_refuses_bad_arguments_before_the_env_is_touched(kwargs, message):
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world = LSTMWorldModel(3, 1, window=4)
    made = []
    planner = _planner(env, world)
    env.step = env.reset = None  # the env is never touched
    arguments = dict(SIZES, make_planner=lambda: made.append(1) or planner()) | kwargs
    with pytest.raises((ValueError, TypeError), match=message.replace("(", r"\(")):
        OnlineTrainer.from_env(env, world, None, progress=False, **arguments)
    assert not world.obs_norm.fitted
    assert made == [] or "hooks" in kwargs  # a hook is checked once the Trainer is wired


def test_the_config_builder_explores_with_the_exploration_objective():
    trainer = make_online_trainer(
        env=make_env("Pendulum-v1", seed=0, max_episode_steps=20),
        world_model=functools.partial(LSTMWorldModel, window=4),
        estimator=functools.partial(ReconstructionUncertainty, window=4),
        cost="torchrl_recon.envs.gym_costs:pendulum",
        planner=functools.partial(CEMPlanner, horizon=4, num_candidates=8, num_elites=2),
        objective=Objective(),
        policy=MPCPolicy,
        schedule=SCHEDULE,
        explore_iterations=1,
        progress=False,
        **SIZES,
    )
    explorer = trainer.collector.policies["explore"]
    assert type(explorer) is ExplorationPolicy and trainer.collector.policies["mpc"] is None
    assert explorer.planner.objective == exploration_objective()
