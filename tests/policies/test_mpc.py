from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector, MultiSyncCollector

from torchrl_recon.envs import get_entry, make_env
from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel, RandomShootingPlanner
from torchrl_recon.policies import MPCPolicy


def _small_drone_policy(**kwargs) -> MPCPolicy:
    torch.manual_seed(0)
    model = PlanningModel(
        LSTMWorldModel(12, 4, window=3, hidden_size=8, dense_size=8),
        drone_cost,
        uncertainty=ReconstructionUncertainty(12, 4, window=3, hidden_size=8),
    )
    planner = RandomShootingPlanner(model, Objective(beta=0.1), horizon=6, num_candidates=16)
    return MPCPolicy(planner, **kwargs)


def _make_drone(policy: MPCPolicy, **kwargs):
    return make_env("drone", seed=0, **kwargs).append_transform(policy.make_tensordict_primer())


def test_state_is_carried_and_reset_at_episode_start():
    policy = _small_drone_policy(replan="every_n", replan_every=4)
    env = _make_drone(policy, max_episode_steps=10)
    td = env.rollout(20, policy, break_when_any_done=False)
    replanned = td["mpc_replanned"].squeeze(-1).tolist()
    # context of 3 random actions, then a plan every 4 steps; the episode restarts at step 10.
    assert replanned == [False] * 3 + [True, False, False, False, True, False, False] + [
        False
    ] * 3 + [True, False, False, False, True, False, False]
    assert td["mpc_steps_seen"][:, 0].tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9] * 2
    # Between episode ends the carried history is the previous step's next-history.
    same = td["next", "mpc_obs_history"][:9] == td["mpc_obs_history"][1:10]
    assert same.all()
    # The predicted next observation is the plan's, and NaN during the random warm-up.
    assert torch.isnan(td["mpc_predicted_next_observation"][:3]).all()
    assert torch.isfinite(td["mpc_predicted_next_observation"][3:10]).all()


def test_every_step_replans_at_every_step_after_warm_up():
    policy = _small_drone_policy(replan="every_step")
    td = _make_drone(policy).rollout(8, policy)
    assert td["mpc_replanned"].squeeze(-1).tolist() == [False] * 3 + [True] * 5


def _replans_and_drift(error_threshold: float | None) -> tuple[list[bool], torch.Tensor]:
    """One 10-step rollout with plans of 6 steps; the RMS drift of each step from its plan."""
    policy = _small_drone_policy(
        replan="every_n", replan_every=100, error_threshold=error_threshold
    )
    torch.manual_seed(1)
    td = _make_drone(policy).rollout(10, policy)
    scale = policy.planner.model.world_model.obs_norm.scale
    predicted = td["mpc_predicted_next_observation"][:-1]  # prediction of the next step's obs
    drift = ((td["observation"][1:] - predicted) / scale).pow(2).mean(-1).sqrt()
    return td["mpc_replanned"].squeeze(-1).tolist(), drift


def test_error_threshold_replans_where_the_state_leaves_the_plan():
    replanned, drift = _replans_and_drift(None)
    # warm-up of 3 steps, one 6-step plan (steps 3-8), then the plan runs out.
    assert replanned == [False] * 3 + [True] + [False] * 5 + [True]
    on_plan = drift[3:8]  # drift at steps 4..8, each against the plan made at step 3
    first = next(i for i in range(1, 5) if on_plan[i] > on_plan[:i].max())
    threshold = float(on_plan[:first].max() + on_plan[first]) / 2
    replanned, _ = _replans_and_drift(threshold)
    # identical up to the first step whose drift crosses the threshold, which re-plans
    assert replanned[: 4 + first + 1] == [False] * 3 + [True] + [False] * first + [True]
    # a tiny threshold re-plans at every step after the first plan; a huge one never adds one
    assert _replans_and_drift(1e-9)[0] == [False] * 3 + [True] * 7
    assert _replans_and_drift(1e9)[0] == _replans_and_drift(None)[0]


@pytest.fixture(scope="module")
def ib_policy_factory(trained_models):
    trained = trained_models("industrial_benchmark")
    model = PlanningModel(
        trained["model"],
        get_entry("industrial_benchmark").cost_fn(),
        uncertainty=trained["estimator"],
    )

    def build(threshold: float) -> MPCPolicy:
        planner = CEMPlanner(
            model, Objective(beta=0.1), horizon=30, num_candidates=200, num_elites=20, iterations=3
        )
        return MPCPolicy(planner, replan="uncertainty", threshold=threshold)

    return trained, build


def test_uncertainty_triggered_replanning_on_a_trained_model(ib_policy_factory):
    trained, build = ib_policy_factory
    held_out = trained["held_out"]
    with torch.no_grad():
        in_dist_u = float(
            trained["estimator"]
            .score(held_out["observation"][None, :200], held_out["action"][None, :200])
            .median()
        )
    counts = {}
    for factor in (0.5, 1.0, 2.0, 4.0):
        torch.manual_seed(0)
        policy = build(threshold=factor * in_dist_u)
        env = make_env("industrial_benchmark", seed=3).append_transform(
            policy.make_tensordict_primer()
        )
        td = env.rollout(60, policy)
        counts[factor] = int(td["mpc_replanned"].sum())
        assert torch.isfinite(td["action"]).all()
    print("re-plans in 50 planned steps by threshold factor:", counts)
    assert counts[4.0] < 50  # fewer re-plans than classic every-step MPC
    assert counts[0.5] >= counts[1.0] >= counts[2.0] >= counts[4.0]
    assert counts[0.5] > counts[4.0]


def test_policy_in_a_collector_with_two_parallel_envs():
    policy = _small_drone_policy(replan="every_n", replan_every=3)
    primer = policy.make_tensordict_primer()
    collector = Collector(
        lambda: make_env("drone", seed=0, num_envs=2).append_transform(primer.clone()),
        policy=policy,
        frames_per_batch=20,
        total_frames=40,
    )
    batches = [b for b in collector]
    collector.shutdown()
    batch = batches[-1]
    assert batch.batch_size == (2, 10)
    assert torch.isfinite(batch["action"]).all()
    assert batch["mpc_replanned"].any()
    planned = ~torch.isnan(batch["mpc_predicted_next_observation"][..., 0])
    assert torch.isfinite(batch["mpc_predicted_next_observation"][planned]).all()


def test_policy_in_a_multisync_collector():
    policy = _small_drone_policy(replan="every_n", replan_every=3)
    primer = policy.make_tensordict_primer()
    collector = MultiSyncCollector(
        [lambda: make_env("drone", seed=0).append_transform(primer.clone())] * 2,
        policy=policy,
        frames_per_batch=16,
        total_frames=32,
    )
    total = sum(b.numel() for b in collector)
    collector.shutdown()
    assert total == 32


def test_bad_input_and_missing_primer():
    policy = _small_drone_policy()
    env = make_env("drone", seed=0)
    with pytest.raises(KeyError, match="make_tensordict_primer"):
        env.rollout(2, policy)
    env = _make_drone(policy)
    td = env.reset()
    td["observation"][0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        policy(td)
    with pytest.raises(ValueError, match="threshold"):
        _small_drone_policy(replan="uncertainty")
    with pytest.raises(ValueError, match="replan"):
        _small_drone_policy(replan="sometimes")
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="error_threshold"):
            _small_drone_policy(error_threshold=bad)


if __name__ == "__main__":
    pytest.main([__file__, "-q", "-s"])
