"""TorchRL's ``Collector`` at its default arguments with an MPC policy that plans from the first
step (``warmup="plan"``): at construction it reads the policy's ``spec`` instead of calling the
policy (which would plan with models not fitted yet), then collects as usual."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModuleBase
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


class _OnAnotherDevice(TensorDictModuleBase):
    """``policy`` as TorchRL's Collector runs it when the env and the policy are on different
    devices (``env_device="cpu", policy_device="cuda"``), emulated on the CPU: the policy gets a
    copy of the collector's tensordict, and the collector takes back the keys it learnt."""

    def __init__(self, policy: MPCPolicy):
        super().__init__()
        self.policy = policy
        self.in_keys, self.out_keys = policy.in_keys, policy.out_keys

    @property
    def spec(self):
        return self.policy.spec

    def forward(self, tensordict):
        return self.policy(tensordict.clone())


def _pendulum_policy(warmup: str) -> tuple[MPCPolicy, object]:
    """An MPC policy on Pendulum-v1 whose world model's normalisation is fitted, and its env."""
    torch.manual_seed(0)
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world = LSTMWorldModel(3, 1, window=4)
    obs = torch.randn(64, 3)
    world.fit_normalization(obs, torch.rand(64, 1) * 4 - 2, obs + 0.1 * torch.randn(64, 3))
    model = PlanningModel.from_env(world, pendulum, env)
    planner = CEMPlanner(
        model, Objective(), horizon=5, num_candidates=16, iterations=2, num_elites=4
    )
    policy = MPCPolicy(planner, warmup=warmup)
    env.append_transform(policy.make_tensordict_primer())
    return policy, env


def test_a_collector_takes_back_every_output_when_the_policy_runs_on_a_copy():
    """The default warm-up (random steps first) has no spec: the Collector learns the policy's
    outputs from one call, the path TorchRL 0.14 gets right across devices (with a spec its
    update stops on a set of keys); every step's plan state comes back to the env (four random context steps, then a plan
    each step)."""
    policy, env = _pendulum_policy("random")
    assert policy.spec is None
    collector = Collector(env, _OnAnotherDevice(policy), frames_per_batch=8, total_frames=8)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch["mpc_replanned"].squeeze(-1).tolist() == [False] * 4 + [True] * 4
    assert batch["next", "mpc_steps_seen"].squeeze(-1).tolist() == list(range(1, 9))
    assert torch.isfinite(batch["action"]).all()


def test_plan_from_the_first_step_on_a_copy_with_use_buffers_off():
    """``warmup="plan"`` with the env on another device: ``use_buffers=False`` (the remedy the
    spec's docstring gives) collects, planning from the first step."""
    policy, env = _pendulum_policy("plan")
    collector = Collector(
        env, _OnAnotherDevice(policy), frames_per_batch=4, total_frames=4, use_buffers=False
    )
    batch = next(iter(collector))
    collector.shutdown()
    assert batch["mpc_replanned"].squeeze(-1).tolist() == [True] * 4
    assert torch.isfinite(batch["action"]).all()
