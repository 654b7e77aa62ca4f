"""UncertaintyPenalty: the estimators as a TorchRL transform on any model-based env."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import GymEnv, TransformedEnv
from torchrl.envs.model_based import DreamerEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import MLP, CEMPlanner, MPPIPlanner, ValueOperator, WorldModelWrapper
from torchrl.objectives.value import TDLambdaEstimator

from tests.normalized import fitted
from tests.torchrl_world import fitted_pendulum
from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.modules import (
    ESTIMATORS,
    LSTMWorldModel,
    ReconstructionUncertainty,
    make_estimator,
)
from torchrl_recon.planners import PlanningModel, UncertaintyBand
from torchrl_recon.planners.model_env import WorldModelPlanningEnv
from torchrl_recon.planners.torchrl_models import BatchedWorldModelEnv
from torchrl_recon.transforms import UncertaintyPenalty

SMALL = {
    "reconstruction": {"hidden_size": 8},
    "ensemble": {"hidden_size": 8, "num_members": 2},
    "mc_dropout": {"hidden_size": 8, "samples": 3},
    "rnd": {"hidden_size": 8, "embedding_size": 4},
    "world_model_ensemble": {"hidden_size": 4, "dense_size": 4, "num_members": 2},
}


class MeanSquare(ReconstructionUncertainty):
    """A user's own estimator: u is the mean square of the standardised window."""

    def score_sequence(self, x: torch.Tensor) -> torch.Tensor:
        z = self.input_norm.normalize(x).unfold(1, self.window, 1)  # [R, W, F, T]
        return z.pow(2).mean((-1, -2))


def _lstm_env(batch=()):
    """Our LSTM model env without an estimator, and a start after a real context."""
    torch.manual_seed(0)
    world = fitted(LSTMWorldModel(12, 4, window=3, hidden_size=8, dense_size=8))
    env = WorldModelPlanningEnv(world, drone_cost)
    g = torch.Generator().manual_seed(1)
    ctx_obs, ctx_act = (
        torch.randn(*batch, 5, 12, generator=g),
        torch.rand(*batch, 5, 4, generator=g),
    )
    obs = torch.randn(*batch, 12, generator=g)
    return world, env, (ctx_obs, ctx_act, obs)


@pytest.mark.parametrize("batch", [(), (2,), (2, 3)])
def test_u_and_reward_are_the_planning_models(batch):
    world, env, ctx = _lstm_env(batch)
    estimator = fitted(ReconstructionUncertainty(12, 4, window=4, hidden_size=8))
    penalty = UncertaintyPenalty(estimator, beta=0.3)
    env = TransformedEnv(env, penalty)
    start = env.base_env.initial_state(*ctx)
    start[penalty.history_key] = penalty.history(*ctx[:2])  # u's windows reach into the context
    start = env.reset(start)
    torch.manual_seed(2)
    with torch.no_grad():
        rollout = env.rollout(6, auto_reset=False, tensordict=start)
        pred = PlanningModel(world, drone_cost, uncertainty=estimator)(
            *ctx, rollout["action"].unsqueeze(-3)
        )
    u = rollout["next", "uncertainty"].squeeze(-1)
    torch.testing.assert_close(u, pred.uncertainty.squeeze(-2), atol=1e-5, rtol=1e-5)
    expected = -pred.cost.squeeze(-2) - 0.3 * pred.uncertainty.squeeze(-2)
    torch.testing.assert_close(
        rollout["next", "reward"].squeeze(-1), expected, atol=1e-5, rtol=1e-5
    )


def test_the_same_as_our_model_env_with_its_own_penalty():
    world, env, ctx = _lstm_env()
    estimator = fitted(ReconstructionUncertainty(12, 4, window=3, hidden_size=8))
    ours = WorldModelPlanningEnv(world, drone_cost, uncertainty=estimator, beta=0.7)
    theirs = TransformedEnv(env, UncertaintyPenalty(estimator, beta=0.7))
    start = theirs.reset(
        env.initial_state(*ctx).set("uncertainty_history", ours.initial_state(*ctx)["u_history"])
    )
    actions = torch.rand(5, 4) * 2 - 1
    rewards = []
    for model_env, td in ((ours, ours.initial_state(*ctx)), (theirs, start)):
        for t in range(5):
            td = model_env.step(td.set("action", actions[t]))
            rewards.append(td["next", "reward"])
            td = td["next"]
    torch.testing.assert_close(torch.stack(rewards[:5]), torch.stack(rewards[5:]))


@pytest.mark.parametrize("kind", [*sorted(ESTIMATORS), "yours"])
def test_every_estimator_scores_every_step_in_one_batch(kind):
    torch.manual_seed(0)
    if kind == "yours":
        estimator = fitted(MeanSquare(12, 4, window=3))
    else:
        estimator = fitted(make_estimator(kind, 12, 4, window=3, **SMALL[kind]))
    _, env, ctx = _lstm_env((2,))
    env = TransformedEnv(env, UncertaintyPenalty(estimator, beta=1.0))
    check_env_specs(env)
    start = env.reset(env.base_env.initial_state(*ctx))
    torch.manual_seed(3)
    rollout = env.rollout(4, auto_reset=False, tensordict=start)
    u = rollout["next", "uncertainty"]
    assert u.shape == (2, 4, 1) and torch.isfinite(u).all()
    if kind != "mc_dropout":  # (its masks are drawn per call)
        pairs = torch.cat([rollout["observation"], rollout["action"]], -1)
        at_rest = torch.cat([ctx[2], torch.zeros(2, 4)], -1)[:, None].expand(2, 2, 16)
        seq = torch.cat([at_rest, pairs], 1)
        with torch.no_grad():
            expected = estimator.score(seq[..., :12], seq[..., 12:])
        torch.testing.assert_close(u.squeeze(-1), expected, atol=1e-5, rtol=1e-5)


def test_history_starts_at_rest_and_resets_where_the_env_resets():
    estimator = fitted(ReconstructionUncertainty(3, 1, window=4, hidden_size=8))
    env = TransformedEnv(GymEnv("Pendulum-v1"), UncertaintyPenalty(estimator))
    env.set_seed(0)
    td = env.reset()
    history = td["uncertainty_history"]
    assert history.shape == (3, 4)
    torch.testing.assert_close(history[:, :3], td["observation"].expand(3, 3))
    assert (history[:, 3] == 0).all()
    rollout = env.rollout(5)
    assert rollout["next", "uncertainty"].shape == (5, 1)
    # the history rolls: step t's last pair is (s_{t-1}, a_{t-1})
    torch.testing.assert_close(
        rollout["uncertainty_history"][1:, -1],
        torch.cat([rollout["observation"], rollout["action"]], -1)[:-1],
    )
    # a partial reset of a batch: the env reset starts at rest, the other goes on
    model_env = _dreamer_env(estimator_obs=3)
    start = model_env.reset(
        TensorDict({"state": torch.randn(2, 3), "belief": torch.randn(2, 6)}, [2])
    )
    after = model_env.rollout(3, auto_reset=False, tensordict=start)[..., -1]["next"]
    after["_reset"] = torch.tensor([[True], [False]])
    reset = model_env.reset(after)
    torch.testing.assert_close(reset["uncertainty_history"][1], after["uncertainty_history"][1])
    assert (reset["uncertainty_history"][0, :, 3:] == 0).all()
    torch.testing.assert_close(
        reset["uncertainty_history"][0, :, :3], after["state"][0].expand(3, 3)
    )


def _dreamer_env(estimator_obs: int = 3, **penalty):
    """TorchRL's DreamerEnv over a small transition model of (state, belief), u on the state."""
    torch.manual_seed(0)
    transition = TensorDictModule(
        MLP(in_features=3 + 6 + 1, out_features=9, num_cells=[8]),
        in_keys=["state", "belief", "action"],
        out_keys=["state_belief"],
    )

    class Split(nn.Module):
        def forward(self, x):
            return x[..., :3], x[..., 3:]

    split = TensorDictModule(Split(), in_keys=["state_belief"], out_keys=["state", "belief"])
    reward = TensorDictModule(nn.Linear(3, 1), in_keys=["state"], out_keys=["reward"])
    world_model = WorldModelWrapper(TensorDictSequential(transition, split), reward)
    env = DreamerEnv(world_model, prior_shape=(3,), belief_shape=(6,))
    env.observation_spec = Composite(state=Unbounded((3,)), belief=Unbounded((6,)))
    env.state_spec = env.observation_spec.clone()
    env.action_spec = Bounded(-1.0, 1.0, (1,))
    env.reward_spec = Unbounded((1,))
    estimator = fitted(ReconstructionUncertainty(estimator_obs, 1, window=4, hidden_size=8))
    return TransformedEnv(env, UncertaintyPenalty(estimator, obs_key="state", **penalty))


def test_dreamer_env_and_torchrls_cem_with_u():
    env = _dreamer_env(beta=1.0)
    start = env.reset(TensorDict({"state": torch.randn(3), "belief": torch.randn(6)}, []))
    with torch.no_grad():
        rollout = env.rollout(4, auto_reset=False, tensordict=start)
        action = CEMPlanner(env, 4, 2, 16, 4)(start)["action"]
    assert rollout["next", "uncertainty"].shape == (4, 1) and action.shape == (1,)


def test_a_band_penalises_sum_u_outside_it_and_forward_scores_trajectories():
    estimator = fitted(ReconstructionUncertainty(3, 1, window=4, hidden_size=8))
    band = UncertaintyBand(low=None, high=1.0)
    penalty = UncertaintyPenalty(estimator, alpha=0.5, beta=0.2, band=band, band_weight=10.0)
    env = TransformedEnv(GymEnv("Pendulum-v1"), penalty)
    env.set_seed(0)
    torch.manual_seed(0)
    rollout = env.rollout(8)
    u = rollout["next", "uncertainty"].squeeze(-1)
    raw = GymEnv("Pendulum-v1")
    raw.set_seed(0)
    torch.manual_seed(0)
    reward = raw.rollout(8)["next", "reward"].squeeze(-1)
    total = 0.5 * reward.sum() - 0.2 * u.sum() - 10.0 * (u.sum() - 1.0).clamp_min(0)
    torch.testing.assert_close(rollout["next", "reward"].sum(), total, atol=1e-4, rtol=1e-5)
    # forward() on the same trajectory from its first tensordict's history gives the same
    offline = rollout.exclude("uncertainty_sum").clone()
    offline["next", "reward"] = reward.unsqueeze(-1)
    offline = penalty(offline)
    torch.testing.assert_close(offline["next", "uncertainty"], rollout["next", "uncertainty"])
    torch.testing.assert_close(offline["next", "reward"], rollout["next", "reward"])


def test_errors_say_what_to_do():
    estimator = ReconstructionUncertainty(3, 1, window=4)
    with pytest.raises(ValueError, match="absolute band only, got kind='quantile'"):
        UncertaintyPenalty(estimator, band=UncertaintyBand(high=0.9, kind="quantile"))
    with pytest.raises(TypeError, match="must be an UncertaintyEstimator"):
        UncertaintyPenalty(nn.Linear(3, 1))
    with pytest.raises(ValueError, match="normalisation"):  # never fitted
        TransformedEnv(GymEnv("Pendulum-v1"), UncertaintyPenalty(estimator)).rollout(2)
    fitted(estimator)
    with pytest.raises(KeyError, match="'latent'"):
        _ = TransformedEnv(
            GymEnv("Pendulum-v1"), UncertaintyPenalty(estimator, obs_key="latent")
        ).observation_spec
    env = TransformedEnv(GymEnv("Pendulum-v1"), UncertaintyPenalty(estimator))
    td = env.reset().exclude("uncertainty_history")
    with pytest.raises(KeyError, match="no 'uncertainty_history'.*env.reset"):
        env.step(env.rand_action(td))
    with pytest.raises(ValueError, match="needs the last 3"):
        UncertaintyPenalty(estimator).history(torch.zeros(2, 3), torch.zeros(2, 1))


def test_the_env_device_is_followed():
    """Every tensor the transform makes follows its inputs' device: made on the CPU, called
    under a meta default device, nothing lands on meta (a factory ignoring its inputs would)."""
    estimator = fitted(ReconstructionUncertainty(3, 1, window=4, hidden_size=8))
    env = TransformedEnv(GymEnv("Pendulum-v1"), UncertaintyPenalty(estimator, beta=1.0))
    td = env.reset().set("action", torch.zeros(1))
    penalty = env.transform
    nxt, empty, reset = TensorDict({"reward": torch.zeros(1)}, []), TensorDict({}, []), td.clone()
    with torch.device("meta"):
        out = penalty._step(td, nxt)
        again = penalty._reset(empty, reset)
    assert out["uncertainty"].device.type == "cpu"
    assert again["uncertainty_history"].device.type == "cpu"


@pytest.mark.parametrize("kind", ["cem", "mppi"])
def test_torchrls_planners_plan_lower_u_with_beta(kind):
    """On a fitted MLP world model (TorchRL's WorldModel, Pendulum-v1 data with actions in
    [-0.5, 0.5]) and an autoencoder fitted on the same data, TorchRL's own planner swings with
    big actions for Pendulum's reward at β = 0, and keeps to the familiar small ones (lower u
    along the whole MPC rollout) at β > 0."""
    fit = fitted_pendulum()
    means = []
    for beta in (0.0, 30.0):
        base = BatchedWorldModelEnv(
            fit["world_model"], fit["env"], observation_spec=Composite(latent=Unbounded((3,)))
        )
        penalty = UncertaintyPenalty(fit["estimator"], beta=beta, obs_key="latent")
        env = TransformedEnv(base, penalty)
        torch.manual_seed(0)
        if kind == "cem":
            planner = CEMPlanner(env, planning_horizon=6, optim_steps=2, num_candidates=32, top_k=6)
        else:
            value = ValueOperator(nn.Linear(3, 1), in_keys=["latent"])
            nn.init.zeros_(value.module.weight)
            nn.init.zeros_(value.module.bias)
            planner = MPPIPlanner(
                env,
                TDLambdaEstimator(gamma=1.0, lmbda=1.0, value_network=value),
                temperature=0.1,
                planning_horizon=6,
                optim_steps=2,
                num_candidates=32,
                top_k=6,
            )
        start = env.reset(TensorDict({"latent": fit["data"]["observation"][0]}, []))
        with torch.no_grad():
            rollout = env.rollout(4, planner, tensordict=start, auto_reset=False)
        means.append(rollout["next", "uncertainty"].mean().item())
    assert means[1] < 0.5 * means[0], means


def test_in_torchrls_config_store_beside_its_transforms():
    from hydra.core.config_store import ConfigStore
    from hydra.utils import instantiate

    from torchrl_recon.trainers import configs

    repo = ConfigStore.instance().repo["transform"]
    assert "uncertainty_penalty.yaml" in repo and "cat_frames.yaml" in repo
    estimator = ReconstructionUncertainty(3, 1, window=4)
    penalty = instantiate(configs.UncertaintyPenaltyConfig(beta=0.5, band_weight=3.0))(estimator)
    assert isinstance(penalty, UncertaintyPenalty) and (penalty.beta, penalty.band_weight) == (
        0.5,
        3.0,
    )


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
