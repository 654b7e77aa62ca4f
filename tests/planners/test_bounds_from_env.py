"""Action bounds come from the env's action spec; a policy refuses an env with other bounds."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import Bounded, Categorical, OneHot, Unbounded
from torchrl.envs import GymEnv, InitTracker, TransformedEnv

from tests.normalized import fitted
from torchrl_recon.envs import make_env
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import (
    CEMPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
)
from torchrl_recon.planners.bounds import bounds_from_spec
from torchrl_recon.planners.model_env import WorldModelPlanningEnv
from torchrl_recon.policies import ExplorationPolicy, MPCPolicy, exploration_objective


def pendulum_cost(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    theta = torch.atan2(obs[..., 1], obs[..., 0])
    return theta.pow(2) + 0.1 * obs[..., 2].pow(2) + 0.001 * action[..., 0].pow(2)


def _world(window: int = 2) -> LSTMWorldModel:
    return fitted(LSTMWorldModel(3, 1, window=window, hidden_size=8, dense_size=8))


def _policy(model: PlanningModel) -> MPCPolicy:
    return MPCPolicy(RandomShootingPlanner(model, Objective(), horizon=3, num_candidates=8))


@pytest.mark.parametrize(
    "spec, low, high",
    [
        (Bounded(-2.0, 2.0, shape=(1,)), [-2.0], [2.0]),
        (
            Bounded(torch.tensor([-1.0, 0.0]), torch.tensor([1.0, 3.0]), shape=(2,)),
            [-1.0, 0.0],
            [1.0, 3.0],
        ),
        (Bounded(-0.5, 0.5, shape=(4, 3)), [-0.5] * 3, [0.5] * 3),  # a batch of 4 envs
    ],
)
def test_bounds_from_spec(spec, low, high):
    got_low, got_high = bounds_from_spec(spec)
    assert got_low.tolist() == low and got_high.tolist() == high


@pytest.mark.parametrize(
    "spec, match",
    [
        (Unbounded(shape=(2,)), r"Unbounded.*pass action_low= / action_high="),
        (Bounded(-float("inf"), float("inf"), shape=(2,)), r"unbounded.*pass action_low="),
        (Categorical(3), r"discrete action space \(Categorical.*need a bounded continuous vector"),
        (OneHot(2), r"discrete action space \(OneHot of shape \[2\]\); the planners need"),
        (
            Bounded(torch.tensor([[-1.0], [-2.0]]), torch.tensor([[1.0], [2.0]]), shape=(2, 1)),
            "differ between the envs of its batch",
        ),
    ],
)
def test_unusable_specs_are_refused(spec, match):
    with pytest.raises(ValueError, match=match):
        bounds_from_spec(spec)


def test_from_env_reads_pendulum_bounds_on_the_models_device_and_dtype():
    torch.manual_seed(0)  # the models' weights: unseeded, the test failed ~1 run in 10
    env = GymEnv("Pendulum-v1")
    pm = PlanningModel.from_env(
        _world(), pendulum_cost, env, uncertainty=fitted(ReconstructionUncertainty(3, 1, window=2))
    )
    assert pm.action_low.tolist() == [-2.0] and pm.action_high.tolist() == [2.0]
    on_meta = PlanningModel.from_env(_world().to("meta"), pendulum_cost, env)
    assert on_meta.action_low.device.type == "meta"
    in_double = PlanningModel.from_env(_world().double(), pendulum_cost, env)
    assert in_double.action_high.dtype == torch.float64
    # Candidates are drawn in the env's box.
    planner = RandomShootingPlanner(pm, Objective(), horizon=4, num_candidates=64)
    g = torch.Generator().manual_seed(0)
    context = (
        torch.randn(2, 3, generator=g),
        torch.rand(2, 1, generator=g),
        torch.randn(3, generator=g),
    )
    result = planner.plan(*context, generator=g)
    assert result.actions.abs().max() <= 2.0 and result.actions.abs().max() > 1.0


def test_a_discrete_env_says_the_planners_need_continuous_actions_not_action_low():
    """TorchRL's own GymEnv of CartPole: no bounds can make a discrete action space plannable,
    so neither from_env nor the policy's primer advises passing action_low= / action_high=."""
    env = GymEnv("CartPole-v1")
    with pytest.raises(ValueError, match="discrete action space") as info:
        PlanningModel.from_env(LSTMWorldModel(4, 1), pendulum_cost, env)
    assert "action_low" not in str(info.value)
    policy = _policy(PlanningModel(fitted(LSTMWorldModel(4, 1)), pendulum_cost))
    with pytest.raises(ValueError, match="continuous vector of floats") as info:
        TransformedEnv(env, policy.make_tensordict_primer())
    assert "action_low" not in str(info.value)


@pytest.mark.parametrize(
    "low, high, error, match",
    [
        (
            torch.tensor([-1.0, -1.0]),
            1.0,
            ValueError,
            r"^action_low has shape \[2\]; expected a float or a tensor of 1 value, shape \[1\]\.$",
        ),
        (torch.tensor([[-1.0]]), 1.0, ValueError, r"^action_low has shape \[1, 1\]; expected"),
        (-1.0, [[1.0], [1.0]], ValueError, r"^action_high has shape \[2, 1\]; expected"),
        ("low", 1.0, TypeError, r"^action_low must be a float or a tensor of 1 value"),
        (-1.0, None, TypeError, r"^action_high must be a float or a tensor"),
        (torch.tensor([True]), 1.0, TypeError, r"^action_low must be .*dtype torch.bool"),
        (float("nan"), 1.0, ValueError, r"^action bounds must be finite"),
        (1.0, 1.0, ValueError, r"^action_low must be below action_high"),
    ],
)
def test_bounds_of_a_wrong_shape_or_value_are_one_line_naming_the_argument(low, high, error, match):
    for make in (
        lambda: PlanningModel(_world(), pendulum_cost, action_low=low, action_high=high),
        lambda: WorldModelPlanningEnv(_world(), pendulum_cost, action_low=low, action_high=high),
    ):
        with pytest.raises(error, match=match) as info:
            make()
        assert "\n" not in str(info.value)


def test_from_env_refuses_a_world_model_of_another_action_size():
    with pytest.raises(ValueError, match="4 dims but the world model's action_dim is 1"):
        PlanningModel.from_env(_world(), pendulum_cost, make_env("drone", seed=0))


def test_the_primer_refuses_an_env_with_other_bounds_naming_both_ranges():
    policy = _policy(PlanningModel(_world(), pendulum_cost))  # default bounds [-1, 1]
    env = make_env("Pendulum-v1", seed=0)
    with pytest.raises(ValueError) as info:
        env.append_transform(policy.make_tensordict_primer())
    message = str(info.value)
    assert "[-1, 1]" in message and "[-2, 2]" in message and "from_env" in message


@pytest.mark.parametrize("num_envs", [1, 2])
def test_a_policy_with_the_envs_bounds_is_accepted_and_acts_in_the_whole_box(num_envs):
    env = make_env("Pendulum-v1", seed=0, num_envs=num_envs, parallel=False)
    model = PlanningModel.from_env(_world(), pendulum_cost, env)
    policy = _policy(model)
    env.append_transform(policy.make_tensordict_primer())
    policy.check_env(env)
    td = env.rollout(40, policy)
    actions = td["action"]
    assert actions.abs().max() <= 2.0 and actions.abs().max() > 1.0


def test_check_env_refuses_other_bounds_and_an_exploration_policy_too():
    env = make_env("Pendulum-v1", seed=0)
    model = PlanningModel(
        _world(), pendulum_cost, uncertainty=fitted(ReconstructionUncertainty(3, 1, window=2))
    )
    explorer = ExplorationPolicy(
        RandomShootingPlanner(model, exploration_objective(), horizon=3, num_candidates=8)
    )
    with pytest.raises(ValueError, match=r"ExplorationPolicy's planner's action range \[-1, 1\]"):
        explorer.check_env(env)
    with pytest.raises(ValueError, match=r"\[-2, 2\]"):
        env.append_transform(explorer.make_tensordict_primer())


def test_the_primer_checks_when_its_compose_joins_an_env():
    policy = _policy(PlanningModel(_world(), pendulum_cost, action_low=-2.0, action_high=2.0))
    TransformedEnv(GymEnv("Pendulum-v1"), InitTracker()).append_transform(
        policy.make_tensordict_primer()
    )
    policy = _policy(PlanningModel(_world(), pendulum_cost, action_low=-2.0, action_high=1.0))
    with pytest.raises(ValueError, match=r"\[-2, 1\] differs from the env's action spec \[-2, 2\]"):
        TransformedEnv(GymEnv("Pendulum-v1"), policy.make_tensordict_primer())


@pytest.mark.parametrize(
    "planner_cls, kwargs",
    [(CEMPlanner, {"num_elites": 4}), (MPPIPlanner, {}), (ICEMPlanner, {"num_elites": 4})],
    ids=["cem", "mppi", "icem"],
)
def test_cem_on_pendulum_bounds(planner_cls, kwargs):
    env = GymEnv("Pendulum-v1")
    pm = PlanningModel.from_env(_world(), pendulum_cost, env)
    planner = planner_cls(pm, Objective(), horizon=4, num_candidates=32, iterations=2, **kwargs)
    for init in (None, torch.full((4, 1), 1.9)):
        result = planner.plan(torch.randn(2, 3), torch.rand(2, 1), torch.randn(3), init=init)
        assert result.actions.abs().max() <= 2.0
