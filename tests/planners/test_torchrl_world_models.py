"""The library's planners over TorchRL world models, and our LSTM inside TorchRL's types."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import (
    Composite,
    LazyTensorStorage,
    SliceSampler,
    TensorDictReplayBuffer,
    Unbounded,
)
from torchrl.envs import GymEnv, TransformedEnv
from torchrl.envs.model_based import WorldModelEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import CEMPlanner as TorchRLCEMPlanner
from torchrl.modules import MPPIPlanner as TorchRLMPPIPlanner
from torchrl.modules import ValueOperator, WorldModel
from torchrl.objectives import WorldModelLoss
from torchrl.objectives.value import TDLambdaEstimator

from tests.normalized import fitted
from tests.torchrl_world import fitted_pendulum, latent_world_model, mlp_world_model
from torchrl_recon.collectors import collect_random
from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.objectives import WorldModelPredictionLoss
from torchrl_recon.planners import Objective, PlanningModel, make_planner
from torchrl_recon.planners.registry import PLANNERS
from torchrl_recon.planners.torchrl_models import (
    BatchedWorldModelEnv,
    LSTMWorldModelModule,
    TorchRLWorldModelAdapter,
)
from torchrl_recon.transforms import UncertaintyPenalty

PENDULUM = GymEnv("Pendulum-v1")
SMALL = {
    "shooting": {"num_candidates": 48},
    "cem": {"num_candidates": 32, "num_elites": 6, "iterations": 3},
    "mppi": {"num_candidates": 32, "iterations": 3},
    "icem": {"num_candidates": 32, "num_elites": 6, "iterations": 3},
    "gradient": {"restarts": 4, "steps": 10},
}


def _model(kind: str) -> WorldModel:
    torch.manual_seed(0)
    return mlp_world_model() if kind == "mlp" else latent_world_model()


def _latents_env(world_model: WorldModel) -> BatchedWorldModelEnv:
    spec = world_model.encode(TensorDict({"observation": torch.zeros(3)}, []))["latent"].shape
    return BatchedWorldModelEnv(
        world_model, PENDULUM, observation_spec=Composite(latent=Unbounded(spec))
    )


@pytest.mark.parametrize("kind", ["mlp", "latent"])
@pytest.mark.parametrize("batch", [(), (2,)])
def test_the_adapter_rolls_out_every_candidate_at_once_as_the_env_does(kind, batch):
    world_model = _model(kind)
    adapter = TorchRLWorldModelAdapter(world_model, env=PENDULUM)
    calls = []
    world_model.dynamics.module.register_forward_hook(lambda *a: calls.append(1))
    obs, actions = torch.randn(*batch, 3), torch.rand(*batch, 5, 4, 1) * 4 - 2
    ctx = torch.zeros(*batch, 1, 3), torch.zeros(*batch, 1, 1)
    with torch.no_grad():
        states = adapter.imagine(*ctx, obs, actions)
        cost = adapter.cost(None, None, states)
    assert states.shape == (*batch, 5, 4, 3) and len(calls) == 4  # one call per step, all K
    # the same steps through TorchRL's rollout of the same model, one env per candidate
    env = _latents_env(world_model)
    start = world_model.encode(
        TensorDict({"observation": obs.unsqueeze(-2).expand(*batch, 5, 3)}, [*batch, 5])
    )
    setter = iter(actions.unbind(-2))
    with torch.no_grad():
        rollout = env.rollout(
            4,
            lambda td: td.set("action", next(setter)),
            tensordict=start.exclude("observation"),
            auto_reset=False,
        )
        decoded = adapter.decode(rollout["next", "latent"])
    torch.testing.assert_close(states, decoded, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(-cost, rollout["next", "reward"].squeeze(-1), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("planner", sorted(PLANNERS))
@pytest.mark.parametrize("kind", ["mlp", "latent"])
def test_every_planner_plans_on_a_torchrl_world_model(planner, kind):
    world_model = _model(kind)
    estimator = fitted(ReconstructionUncertainty(3, 1, window=3, hidden_size=8))
    model = PlanningModel.from_torchrl(world_model, env=PENDULUM, uncertainty=estimator)
    assert model.context_length == 2 and model.action_high.tolist() == [2.0]
    objective = Objective(alpha=1.0, beta=0.1)
    torch.manual_seed(1)
    ctx = torch.randn(2, 4, 3), torch.rand(2, 4, 1) * 4 - 2, torch.randn(2, 3)
    result = make_planner(planner, model, objective, horizon=5, **SMALL[planner]).plan(*ctx)
    assert result.actions.shape == (2, 5, 1) and result.uncertainty.shape == (2, 5)
    assert (result.actions.abs() <= 2).all() and torch.isfinite(result.objective).all()
    with torch.no_grad():  # better than a random candidate, on the model
        random = model(*ctx, torch.rand(2, 48, 5, 1) * 4 - 2)
    assert (result.objective >= objective.score(random).median(-1).values).all()


def test_a_given_cost_a_done_head_and_a_world_model_env():
    torch.manual_seed(0)
    world_model = mlp_world_model()
    done = TensorDictModule(
        lambda z: z[..., 2:] > 0.0, in_keys=[("next", "latent")], out_keys=[("next", "done")]
    )
    with_done = WorldModel(
        world_model.encoder, world_model.dynamics, world_model.reward_head, done_head=done
    )
    env = _latents_env(with_done)
    model = PlanningModel.from_torchrl(env, cost_fn=pendulum, obs_dim=3)  # bounds from the env
    assert (
        isinstance(model.world_model, TorchRLWorldModelAdapter) and model.termination_fn is not None
    )
    obs, actions = torch.tensor([0.4, 0.0, 0.0]), torch.rand(16, 6, 1) * 4 - 2
    with torch.no_grad():
        pred = model(torch.zeros(1, 3), torch.zeros(1, 1), obs, actions)
    states = pred.states
    ended = (states[..., 2] > 0.0).cumsum(-1) > 0  # the done head's rule
    ended_before = torch.cat([torch.zeros_like(ended[..., :1]), ended[..., :-1]], -1)
    assert ended_before.any() and not ended_before.all()
    entering = torch.cat([obs.expand(16, 1, 3), states[:, :-1]], 1)
    expected = pendulum(entering, actions, states).masked_fill(ended_before, 0.0)
    torch.testing.assert_close(pred.cost, expected)  # the given cost, nothing after the end
    # TorchRL's own WorldModelEnv (batch [1], a 1-dim action: what its constructor allows)
    plain = WorldModelEnv(
        world_model,
        PENDULUM,
        observation_spec=Composite(latent=Unbounded((1, 3)), shape=(1,)),
    )
    assert PlanningModel.from_torchrl(plain, obs_dim=3).action_low.tolist() == [-2.0]
    with pytest.raises(ValueError, match="has 5 features but the observation has 3.*decoder"):
        TorchRLWorldModelAdapter(
            WorldModel(*(latent_world_model()._full_seq.module[:3])), obs_dim=3, action_dim=1
        )
    with pytest.raises(ValueError, match="pass obs_dim= and action_dim="):
        TorchRLWorldModelAdapter(world_model)


def test_the_library_plans_lower_u_with_beta_on_a_fitted_torchrl_model():
    fit = fitted_pendulum()
    model = PlanningModel.from_torchrl(
        fit["world_model"], env=PENDULUM, uncertainty=fit["estimator"]
    )
    data = fit["data"]
    ctx = data["observation"][:2][None], data["action"][:2][None], data["observation"][2][None]
    u = []
    for beta in (0.0, 30.0):
        torch.manual_seed(0)
        planner = make_planner("cem", model, Objective(beta=beta), horizon=8, **SMALL["cem"])
        u.append(planner.plan(*ctx).uncertainty.sum().item())
    assert u[1] < 0.5 * u[0], u


@pytest.mark.parametrize("batch", [(), (2,)])
def test_the_lstm_world_model_in_torchrls_types_predicts_what_imagine_does(batch):
    torch.manual_seed(0)
    lstm = fitted(LSTMWorldModel(3, 1, window=4, hidden_size=8, dense_size=8))
    estimator = fitted(ReconstructionUncertainty(3, 1, window=4, hidden_size=8))
    world_model = LSTMWorldModelModule(lstm, pendulum)
    base = world_model.make_env(PENDULUM)
    penalty = UncertaintyPenalty(estimator, beta=0.5)
    env = TransformedEnv(base, penalty)
    g = torch.Generator().manual_seed(1)
    ctx = (
        torch.randn(*batch, 6, 3, generator=g),
        torch.rand(*batch, 6, 1, generator=g),
        torch.randn(*batch, 3, generator=g),
    )
    start = world_model.start(*ctx).set(penalty.history_key, penalty.history(*ctx[:2]))
    start = env.reset(start)
    check_env_specs(env, tensordict=start.exclude("context"))
    torch.manual_seed(2)
    with torch.no_grad():
        rollout = env.rollout(7, auto_reset=False, tensordict=start)
        pred = PlanningModel(
            lstm, pendulum, uncertainty=estimator, action_low=-2.0, action_high=2.0
        )(*ctx, rollout["action"].unsqueeze(-3))
    # tolerance: nn.LSTM one step at a time against the fused rollout, float32
    torch.testing.assert_close(
        rollout["next", "observation"], pred.states.squeeze(-3), atol=1e-5, rtol=1e-5
    )
    u = pred.uncertainty.squeeze(-2)
    torch.testing.assert_close(rollout["next", "uncertainty"].squeeze(-1), u, atol=1e-5, rtol=1e-5)
    expected = -pred.cost.squeeze(-2) - 0.5 * u
    torch.testing.assert_close(
        rollout["next", "reward"].squeeze(-1), expected, atol=1e-5, rtol=1e-5
    )
    # and TorchRL's own planners plan on it
    value = ValueOperator(nn.Linear(3, 1), in_keys=["observation"])
    mppi = TorchRLMPPIPlanner(
        env,
        TDLambdaEstimator(gamma=0.9, lmbda=0.9, value_network=value),
        temperature=0.1,
        planning_horizon=4,
        optim_steps=2,
        num_candidates=16,
        top_k=4,
    )
    with torch.no_grad():
        for planner in (TorchRLCEMPlanner(env, 4, 2, 16, 4), mppi):
            action = planner(start.clone())["action"]
            assert action.shape == (*batch, 1) and (action.abs() <= 2).all()


def test_world_model_prediction_loss_takes_torchrls_batch_layout():
    data = collect_random(make_env("Pendulum-v1", seed=0, max_episode_steps=40), frames=160, seed=0)
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(160),
        sampler=SliceSampler(slice_len=8, traj_key=("collector", "traj_ids")),
        batch_size=32,
    )
    buffer.extend(data)
    torch.manual_seed(0)
    batch = buffer.sample()  # flat [4 * 8], as TorchRL's WorldModelLoss takes it
    lstm = fitted(LSTMWorldModel(3, 1, window=4, hidden_size=8, dense_size=8))
    ours = WorldModelPredictionLoss(lstm)(batch)["loss_world_model"]
    torch.testing.assert_close(
        ours, WorldModelPredictionLoss(lstm, slice_len=8)(batch)["loss_world_model"]
    )
    world_model = mlp_world_model()
    keys = {"predicted_latent": ("next", "latent"), "target_latent": ("next", "observation")}
    theirs = WorldModelLoss(world_model, losses=["reward", "latent"])
    theirs.set_keys(**keys)
    assert set(theirs(batch).keys()) == {"loss_reward", "loss_latent"}
    with pytest.raises(ValueError, match="pass slice_len="):
        WorldModelPredictionLoss(lstm)(batch.exclude(("next", "truncated"), "is_init"))


def test_the_adapters_in_torchrls_config_store():
    from hydra.core.config_store import ConfigStore
    from hydra.utils import instantiate

    from torchrl_recon.trainers import configs

    repo = ConfigStore.instance().repo["model"]
    assert {"torchrl_world_model_adapter.yaml", "lstm_world_model_module.yaml"} <= set(repo)
    adapter = instantiate(configs.TorchRLWorldModelAdapterConfig(obs_dim=3, action_dim=1))(
        mlp_world_model()
    )
    assert isinstance(adapter, TorchRLWorldModelAdapter) and adapter.window == 1
    module = instantiate(configs.LSTMWorldModelModuleConfig())(LSTMWorldModel(3, 1), pendulum)
    assert isinstance(module, LSTMWorldModelModule)


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
