"""TorchRL's ``Collector`` at its default arguments with an MPC policy that plans from the first
step (``warmup="plan"``): at construction it reads the policy's ``spec`` instead of calling the
policy (which would plan with models not fitted yet), then collects as usual."""

from __future__ import annotations

import torch
from torchrl.collectors import Collector

from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import MPCPolicy


def test_a_collector_at_its_defaults_builds_before_the_models_are_fitted():
    torch.manual_seed(0)
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world = LSTMWorldModel(3, 1, window=4)
    planner = CEMPlanner(
        PlanningModel.from_env(world, pendulum, env),
        Objective(),
        horizon=5,
        num_candidates=16,
        iterations=2,
        num_elites=4,
    )
    policy = MPCPolicy(planner, warmup="plan")
    env.append_transform(policy.make_tensordict_primer())
    collector = Collector(env, policy, frames_per_batch=20, total_frames=40, init_random_frames=20)
    batches = []
    for batch in collector:
        if not batches:  # the random batch: fit the normalisation from it, then plan
            flat = batch.reshape(-1)
            world.fit_normalization(
                flat["observation"], flat["action"], flat["next", "observation"]
            )
        batches.append(batch)
    collector.shutdown()
    assert [b.numel() for b in batches] == [20, 20]
    planned = batches[1]["mpc_replanned"]
    assert planned.all()  # warmup="plan": every step of the second batch was planned
    assert set(policy.spec.keys(True, True)) == set(policy.out_keys)
