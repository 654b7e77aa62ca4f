"""TorchRL world models for the tests of the transform and the adapters: TorchRL ``WorldModel``s
as its docs build them (an MLP over the observation; a latent one with an encoder and a
decoder), and one fitted on Pendulum-v1 data whose actions stayed in [-0.5, 0.5] (a quarter of
the range), with an autoencoder fitted on the same data: big actions are unfamiliar to it."""

from __future__ import annotations

import functools

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.modules import MLP, WorldModel

from torchrl_recon.collectors import collect
from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.modules import ReconstructionUncertainty

SMALL_ACTION = 0.5


class Residual(nn.Module):
    """``z + MLP(z, a)``: dynamics that predict the change of the latent."""

    def __init__(self, latent: int, action: int, hidden: int = 32) -> None:
        super().__init__()
        self.net = MLP(in_features=latent + action, out_features=latent, num_cells=[hidden])

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return z + self.net(z, action)


class PendulumReward(nn.Module):
    """Pendulum-v1's reward of the state a step starts from, as a reward head."""

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return -pendulum(obs, action, obs).unsqueeze(-1)


def mlp_world_model(
    obs_dim: int = 3, action_dim: int = 1, *, exact_reward: bool = False
) -> WorldModel:
    """The MLP example of TorchRL's ``WorldModel`` docs, in observation space (the encoder copies
    the observation into the latent): dynamics ``(latent, action) → ("next", latent)``, a reward
    head on the latent and action (Pendulum's own reward with ``exact_reward``)."""
    encoder = TensorDictModule(nn.Identity(), in_keys=["observation"], out_keys=["latent"])
    dynamics = TensorDictModule(
        Residual(obs_dim, action_dim), in_keys=["latent", "action"], out_keys=[("next", "latent")]
    )
    head = (
        PendulumReward()
        if exact_reward
        else MLP(in_features=obs_dim + action_dim, out_features=1, num_cells=[16])
    )
    reward = TensorDictModule(head, in_keys=["latent", "action"], out_keys=[("next", "reward")])
    return WorldModel(encoder, dynamics, reward)


def latent_world_model(obs_dim: int = 3, action_dim: int = 1, latent: int = 5) -> WorldModel:
    """A latent ``WorldModel``: an encoder into 5 features, dynamics and reward there, a decoder
    back (``latent → reconstructed_observation``, WorldModelLoss's key)."""
    encoder = TensorDictModule(
        MLP(in_features=obs_dim, out_features=latent, num_cells=[16]),
        in_keys=["observation"],
        out_keys=["latent"],
    )
    dynamics = TensorDictModule(
        Residual(latent, action_dim), in_keys=["latent", "action"], out_keys=[("next", "latent")]
    )
    reward = TensorDictModule(
        nn.Linear(latent, 1), in_keys=[("next", "latent")], out_keys=[("next", "reward")]
    )
    decoder = TensorDictModule(
        MLP(in_features=latent, out_features=obs_dim, num_cells=[16]),
        in_keys=["latent"],
        out_keys=["reconstructed_observation"],
    )
    return WorldModel(encoder, dynamics, reward, decoder=decoder)


class SmallRandomActions(TensorDictModuleBase):
    """Uniform actions in [-0.5, 0.5] from its own generator."""

    in_keys: list = []
    out_keys = ["action"]

    def __init__(self, seed: int) -> None:
        super().__init__()
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, td):
        shape = (*td.batch_size, 1)
        td["action"] = (torch.rand(shape, generator=self.generator) * 2 - 1) * SMALL_ACTION
        return td


@functools.cache
def fitted_pendulum(seed: int = 0) -> dict:
    """Data (600 steps, episodes of 50, small actions), the MLP world model with Pendulum's reward
    fitted on it (200 Adam steps), and an autoencoder (window 3) fitted on the same windows."""
    torch.manual_seed(seed)
    env = make_env("Pendulum-v1", seed=seed, max_episode_steps=50)
    data = collect(env, SmallRandomActions(seed), frames=600, seed=seed)
    world_model = mlp_world_model(exact_reward=True)
    obs, action, next_obs = data["observation"], data["action"], data["next", "observation"]
    optim = torch.optim.Adam(world_model.parameters(), lr=3e-3)
    for _ in range(200):
        td = world_model(TensorDict({"observation": obs, "action": action}, obs.shape[:1]))
        loss = (td["next", "latent"] - next_obs).pow(2).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    estimator = ReconstructionUncertainty(3, 1, window=3, hidden_size=16)
    estimator.fit_normalization(obs, action)
    seq_obs, seq_action = obs.reshape(-1, 50, 3), action.reshape(-1, 50, 1)
    optim = torch.optim.Adam(estimator.parameters(), lr=3e-3)
    for _ in range(150):
        loss = estimator.loss(seq_obs, seq_action)
        optim.zero_grad()
        loss.backward()
        optim.step()
    world_model.requires_grad_(False)
    estimator.requires_grad_(False)
    return {"data": data, "world_model": world_model, "estimator": estimator, "env": env}
