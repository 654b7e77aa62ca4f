"""A policy called before any data (TorchRL's Collector calls its policy once at construction):
the unfitted-normalisation error says what works there, and what it says works does."""

from __future__ import annotations

import logging

import pytest
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv

from tests.normalized import fitted
from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import ExplorationPolicy, MPCPolicy, exploration_objective
from torchrl_recon.trainers import TimedPolicy

logging.getLogger("torchrl").setLevel(logging.WARNING)


def _env():
    return make_env("Pendulum-v1", seed=0, max_episode_steps=20)


def _policy(env, warmup: str, world=None) -> MPCPolicy:
    world = world if world is not None else LSTMWorldModel(3, 1, window=4)
    model = PlanningModel.from_env(world, pendulum, env)
    planner = CEMPlanner(model, Objective(), horizon=4, num_candidates=16, num_elites=4)
    return MPCPolicy(planner, warmup=warmup)


def _collector(env, policy, **kwargs) -> Collector:
    return Collector(
        TransformedEnv(env, policy.make_tensordict_primer(), auto_unwrap=False),
        policy,
        frames_per_batch=20,
        total_frames=40,
        **kwargs,
    )


def _first_call(env, policy):
    """What a Collector without the policy's specs does at construction: one call on a reset."""
    return policy(TransformedEnv(env, policy.make_tensordict_primer(), auto_unwrap=False).reset())


def test_a_plan_at_the_first_step_before_data_says_what_works_before_any_data():
    env = _env()
    with pytest.raises(ValueError) as info:
        _first_call(env, _policy(env, "plan"))
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("the world model's normalisation (obs_norm, action_norm, delta_norm")
    for advice in (
        "fit the models on data before building the collector",
        "world_model.fit_normalization(obs, action, next_obs)",
        "MPCPolicy(warmup='random')",
        "Collector(..., use_buffers=False)",
    ):
        assert advice in message


def test_an_exploration_policy_is_named_and_an_unfitted_estimator_too():
    env = _env()
    model = PlanningModel.from_env(
        fitted(LSTMWorldModel(3, 1, window=4)),
        pendulum,
        env,
        uncertainty=ReconstructionUncertainty(3, 1, window=2),
    )
    explorer = ExplorationPolicy(
        CEMPlanner(model, exploration_objective(), horizon=4, num_candidates=16, num_elites=4),
        warmup="plan",
    )
    with pytest.raises(
        ValueError,
        match=r"^the uncertainty estimator's normalisation .*ExplorationPolicy\(warmup='random'\)",
    ):
        _first_call(env, explorer)


@pytest.mark.parametrize("wrap", [False, True], ids=["policy", "timed"])
def test_what_the_advice_says_works_does(wrap):
    """Collector(use_buffers=False), warmup='random' and models fitted first: each builds."""
    env = _env()
    wrapped = TimedPolicy if wrap else (lambda p: p)
    _collector(env, wrapped(_policy(env, "plan")), use_buffers=False).shutdown()
    _collector(env, wrapped(_policy(env, "random"))).shutdown()
    _collector(
        env, wrapped(_policy(env, "plan", fitted(LSTMWorldModel(3, 1, window=4))))
    ).shutdown()


def test_after_the_warm_up_the_advice_is_the_usual_one():
    """warmup='random' plans only after its context: an unfitted model then is a missing fit
    (the Trainer's FitNormalization hook is the advice), not a call before any data."""
    env = _env()
    policy = _policy(env, "random")
    with pytest.raises(ValueError, match="never fitted; fit it from data before planning") as info:
        TransformedEnv(env, policy.make_tensordict_primer(), auto_unwrap=False).rollout(8, policy)
    assert "FitNormalization" in str(info.value) and "use_buffers" not in str(info.value)
