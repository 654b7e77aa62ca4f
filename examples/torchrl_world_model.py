"""Reconstruction uncertainty for a TorchRL world model, end to end on Pendulum-v1.

1. Random data from Pendulum-v1 (TorchRL's collector, through ``collect_random``).
2. A TorchRL ``WorldModel`` as TorchRL's docs build one: MLP dynamics (in observation space, the
   encoder copies the observation into the latent) and an MLP reward head, trained with
   TorchRL's ``WorldModelLoss`` (reward and next-latent losses) on replay-buffer samples.
3. The library's reconstruction estimator (the paper's autoencoder), fitted on the same data.
4. Planning with u, two ways: TorchRL's ``MPPIPlanner`` over the model's ``WorldModelEnv`` with
   the ``UncertaintyPenalty`` transform, and the library's ``CEMPlanner`` over
   ``PlanningModel.from_torchrl`` (one batched rollout per iteration), each as the MPC policy
   of the real env. The last line prints their returns against a random policy's.

Run: python examples/torchrl_world_model.py  (a few minutes on one thread)
"""

from __future__ import annotations

import time

import torch

torch.set_num_threads(1)

from tensordict.nn import TensorDictModule, TensorDictSequential  # noqa: E402
from torch import nn  # noqa: E402
from torchrl.data import (  # noqa: E402
    Composite,
    LazyTensorStorage,
    TensorDictReplayBuffer,
    Unbounded,
)
from torchrl.envs import TransformedEnv  # noqa: E402
from torchrl.modules import MLP, MPPIPlanner, ValueOperator, WorldModel  # noqa: E402
from torchrl.objectives import WorldModelLoss  # noqa: E402
from torchrl.objectives.value import TDLambdaEstimator  # noqa: E402

from torchrl_recon.collectors import collect_random  # noqa: E402
from torchrl_recon.data import make_sequence_buffer  # noqa: E402
from torchrl_recon.envs import make_env  # noqa: E402
from torchrl_recon.estimators import ReconstructionUncertainty  # noqa: E402
from torchrl_recon.fitting import fit_uncertainty  # noqa: E402
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel, relative_beta  # noqa: E402
from torchrl_recon.planners.torchrl_models import BatchedWorldModelEnv  # noqa: E402
from torchrl_recon.policies import MPCPolicy  # noqa: E402
from torchrl_recon.transforms import UncertaintyPenalty  # noqa: E402

SEED, EPISODE, EPISODES = 0, 200, 2
HORIZON, BETA_RELATIVE = 15, 0.1


class Residual(nn.Module):
    """Dynamics ``s + MLP(s, a)``: the MLP predicts the change of the state."""

    def __init__(self) -> None:
        super().__init__()
        self.net = MLP(in_features=4, out_features=3, num_cells=[64, 64], activation_class=nn.SiLU)

    def forward(self, latent: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return latent + self.net(latent, action)


def make_world_model() -> WorldModel:
    encoder = TensorDictModule(nn.Identity(), in_keys=["observation"], out_keys=["latent"])
    dynamics = TensorDictModule(
        Residual(), in_keys=["latent", "action"], out_keys=[("next", "latent")]
    )
    reward_head = TensorDictModule(
        MLP(in_features=4, out_features=1, num_cells=[64, 64], activation_class=nn.SiLU),
        in_keys=["latent", "action"],  # Pendulum's reward is of the state the step starts from
        out_keys=[("next", "reward")],
    )
    return WorldModel(encoder, dynamics, reward_head)


def train_world_model(world_model: WorldModel, data, steps: int = 3000) -> None:
    """TorchRL's WorldModelLoss: the reward head's error and the next latent's (here the next
    observation), on batches of single transitions from a TorchRL replay buffer."""
    loss_module = WorldModelLoss(world_model, losses=["reward", "latent"])
    loss_module.set_keys(predicted_latent=("next", "latent"), target_latent=("next", "observation"))
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), batch_size=256)
    buffer.extend(data.select("observation", "action", ("next", "observation"), ("next", "reward")))
    optim = torch.optim.Adam(world_model.parameters(), lr=1e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optim, steps)
    for step in range(steps):
        losses = loss_module(buffer.sample())
        loss = losses["loss_reward"] + losses["loss_latent"]
        optim.zero_grad()
        loss.backward()
        optim.step()
        schedule.step()
        if step % 1000 == 0 or step == steps - 1:
            print(
                f"  step {step:4d}: reward loss {losses['loss_reward'].item():.4f}, "
                f"next-state loss {losses['loss_latent'].item():.4f}"
            )
    world_model.requires_grad_(False)


def evaluate(env, policy, name: str) -> float:
    """Mean return (and real u) of ``EPISODES`` episodes from the same starts for every policy."""
    returns, u = [], []
    start = time.perf_counter()
    for episode in range(EPISODES):
        env.set_seed(SEED + 100 + episode)
        torch.manual_seed(episode)
        with torch.no_grad():
            rollout = env.rollout(EPISODE, policy)
        returns.append(rollout["next", "reward"].sum().item())
        u.append(rollout["next", "uncertainty"].mean().item())
    seconds = (time.perf_counter() - start) / (EPISODES * EPISODE)
    mean = sum(returns) / len(returns)
    print(
        f"{name:34s} return {mean:8.1f} (episodes {[round(r) for r in returns]}), "
        f"real u {sum(u) / len(u):.3f}, {1e3 * seconds:.0f} ms a step"
    )
    return mean


def main() -> None:
    torch.manual_seed(SEED)
    t0 = time.perf_counter()
    env = make_env("Pendulum-v1", seed=SEED, max_episode_steps=EPISODE)
    data = collect_random(env, frames=10_000, seed=SEED)  # 50 random episodes
    print(f"{len(data)} random steps ({time.perf_counter() - t0:.0f} s)")

    world_model = make_world_model()
    print("world model (TorchRL's WorldModelLoss):")
    train_world_model(world_model, data)
    estimator = ReconstructionUncertainty(3, 1, window=4, hidden_size=32)
    buffer = make_sequence_buffer(len(data), slice_len=20, num_slices=32)
    buffer.extend(data)
    fit_uncertainty(estimator, buffer, steps=1000, lr=3e-3, eval_every=250, progress=False)
    estimator.requires_grad_(False)
    beta = relative_beta(BETA_RELATIVE, data, estimator)  # β in cost units: 0.1 of a step
    print(
        f"models fitted ({time.perf_counter() - t0:.0f} s); beta {BETA_RELATIVE} relative = {beta:.3f}"
    )

    # The real env keeps its own last T - 1 (s, a) pairs (and logs the real u): the imagined
    # rollouts of TorchRL's planner start from them.
    real = make_env("Pendulum-v1", seed=SEED, max_episode_steps=EPISODE).append_transform(
        UncertaintyPenalty(estimator)
    )

    # TorchRL's route: MPPIPlanner over the WorldModelEnv, u from the transform.
    model_env = TransformedEnv(
        BatchedWorldModelEnv(world_model, real, observation_spec=Composite(latent=Unbounded((3,)))),
        UncertaintyPenalty(estimator, beta=beta, obs_key="latent"),
    )
    value = ValueOperator(nn.Linear(3, 1), in_keys=["latent"])
    nn.init.zeros_(value.module.weight)  # no value function: the advantage is the return
    nn.init.zeros_(value.module.bias)
    mppi = MPPIPlanner(
        model_env,
        TDLambdaEstimator(gamma=1.0, lmbda=1.0, value_network=value),
        temperature=0.2,
        planning_horizon=HORIZON,
        optim_steps=2,
        num_candidates=64,
        top_k=8,
    )
    torchrl_policy = TensorDictSequential(world_model.encoder, mppi)  # observation → latent → plan

    # The library's route: one batched rollout of the same model for all candidates.
    model = PlanningModel.from_torchrl(world_model, env=real, uncertainty=estimator)
    cem = CEMPlanner(
        model,
        Objective(beta=beta),
        horizon=HORIZON,
        num_candidates=200,
        num_elites=20,
        iterations=4,
    )
    library_policy = MPCPolicy(cem)
    library_env = make_env("Pendulum-v1", seed=SEED, max_episode_steps=EPISODE)
    library_env.append_transform(UncertaintyPenalty(estimator))
    library_env.append_transform(library_policy.make_tensordict_primer())

    random = evaluate(real, None, "random actions")
    theirs = evaluate(real, torchrl_policy, "TorchRL MPPIPlanner + UncertaintyPenalty")
    ours = evaluate(library_env, library_policy, "library CEMPlanner (from_torchrl)")
    print(f"total {time.perf_counter() - t0:.0f} s")
    print(
        f"mean return over {EPISODES} episodes: library CEM {ours:.0f}, TorchRL MPPI {theirs:.0f}, "
        f"random {random:.0f}"
    )


if __name__ == "__main__":
    main()
