"""A learned reward and termination: what a task's cost and end are when nobody wrote them.

PETS (mbrl-lib's ``learned_rewards``), TD-MPC2, Dreamer and TorchRL's ``WorldModel`` (a reward
head) learn the reward from the data instead of asking for a cost function. :class:`RewardModel`
does that beside the world model: a small MLP over a standardised transition (s, a, s') that
predicts the env's reward r and, optionally, the probability that s' ends the episode. The
planners read it as any given cost and termination, through :class:`LearnedCost` (−r) and
:class:`LearnedTermination` (p > threshold), which :class:`~torchrl_recon.planners.PlanningModel`
takes as its ``cost_fn`` and ``termination_fn``; the fits train it with the world model from the
buffer's ``("next", "reward")`` and ``("next", "terminated")``
(:class:`~torchrl_recon.objectives.RewardLoss`).
"""

from __future__ import annotations

import math

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.nn import functional as F

from torchrl_recon.modules.activations import ACTIVATIONS
from torchrl_recon.modules.checks import check_activation, check_features, check_finite, check_int
from torchrl_recon.modules.normalization import Normalizer, refit_inputs, refit_outputs

REWARD_KEY: tuple[str, str] = ("next", "reward")
TERMINATED_KEY: tuple[str, str] = ("next", "terminated")
LEARNED_REWARD = "reward model"
"""The role a planning model's fitted check names (:class:`~torchrl_recon.modules.FittedCheck`)."""


class RewardModel(TensorDictModuleBase):
    """MLP predicting a transition's reward r(s, a, s') and the probability that s' is terminal.

    The input is the standardised (s, a, s') (statistics fitted by :meth:`fit_normalization`
    and kept as buffers, so a checkpoint is self-contained); ``layers`` hidden layers of
    ``hidden_size`` units; one output for the standardised reward (``reward=True``) and one
    logit for the termination (``termination=True``). Batched over any leading dims and
    differentiable in every input (the gradient planner ascends through it).

    Args:
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        reward: learn the reward (False: only the termination, beside a given cost).
        termination: learn the termination probability too.
        hidden_size, layers, activation: the MLP's hidden layers.
        obs_key, action_key, next_obs_key: where ``forward`` reads a transition.
        reward_key, terminated_key: the targets the loss reads.

    Examples:
        >>> model = RewardModel(3, 1, termination=True)
        >>> s, a = torch.randn(50, 3), torch.randn(50, 1)
        >>> model.fit_normalization(s, a, s + 0.1, s[:, 0])
        >>> model.reward(s, a, s + 0.1).shape, model.termination_probability(s, a, s).shape
        (torch.Size([50]), torch.Size([50]))
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        *,
        reward: bool = True,
        termination: bool = False,
        hidden_size: int = 64,
        layers: int = 2,
        activation: str = "relu",
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        next_obs_key: NestedKey = ("next", "observation"),
        reward_key: NestedKey = REWARD_KEY,
        terminated_key: NestedKey = TERMINATED_KEY,
    ) -> None:
        super().__init__()
        for name, value in (
            ("obs_dim", obs_dim),
            ("action_dim", action_dim),
            ("hidden_size", hidden_size),
            ("layers", layers),
        ):
            check_int(name, value)
        check_activation(activation)
        if not (reward or termination):
            raise ValueError(
                "RewardModel needs reward=True or termination=True (it would learn nothing)."
            )
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.learns_reward, self.learns_termination = bool(reward), bool(termination)
        self.hidden_size, self.layers, self.activation = hidden_size, layers, activation
        self.in_keys = [obs_key, action_key, next_obs_key]
        self.out_keys = [("next", "predicted_reward"), ("next", "termination_probability")]
        self.target_keys = (reward_key, terminated_key)
        sizes = [2 * obs_dim + action_dim] + [hidden_size] * layers
        self.hidden = nn.ModuleList(
            nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)
        )
        self.out = nn.Linear(hidden_size, self.learns_reward + self.learns_termination)
        self.obs_norm = Normalizer(obs_dim)
        self.action_norm = Normalizer(action_dim)
        self.reward_norm = Normalizer(1)

    def config(self) -> dict:
        """Constructor arguments, stored in checkpoints and checked on load."""
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "reward": self.learns_reward,
            "termination": self.learns_termination,
            "hidden_size": self.hidden_size,
            "layers": self.layers,
            "activation": self.activation,
        }

    @torch.no_grad()
    def fit_normalization(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        reward: torch.Tensor,
    ) -> None:
        """Fit the input and reward statistics on real transitions ``[..., N]``, ``[..., M]``,
        ``[..., N]`` and rewards ``[...]`` (or ``[..., 1]``); every value must be finite."""
        check_features("obs", obs, self.obs_dim)
        check_features("action", action, self.action_dim)
        check_features("next_obs", next_obs, self.obs_dim)
        for name, x in (("obs", obs), ("action", action), ("next_obs", next_obs)):
            check_finite(name, x)
        check_finite("reward", reward)
        self.obs_norm.fit(
            torch.cat([obs.reshape(-1, self.obs_dim), next_obs.reshape(-1, self.obs_dim)])
        )
        self.action_norm.fit(action)
        self.reward_norm.fit(reward.reshape(-1, 1))

    @torch.no_grad()
    def refit_normalization(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        reward: torch.Tensor,
    ) -> None:
        """Refit the statistics on (more) data keeping the model's function, as
        :meth:`~torchrl_recon.modules.LSTMWorldModel.refit_normalization` does: the first
        layer and the reward output are rewritten so every prediction stays what it was.

        Examples:
            >>> model = RewardModel(2, 1)
            >>> s, a = torch.randn(30, 2), torch.randn(30, 1)
            >>> model.fit_normalization(s, a, s, s[:, 0])
            >>> before = model.reward(s, a, s)
            >>> model.refit_normalization(2 * s, a - 1, 2 * s, 5 * s[:, 0])
            >>> torch.allclose(model.reward(s, a, s), before, atol=1e-5)
            True
        """
        for name, x in (("obs", obs), ("action", action), ("next_obs", next_obs)):
            check_finite(name, x)
        check_finite("reward", reward)
        n = self.obs_dim
        states = torch.cat([obs.reshape(-1, n), next_obs.reshape(-1, n)])
        norms = (self.obs_norm, self.action_norm, self.reward_norm)
        old = [(m.loc.clone(), m.scale.clone()) for m in norms]
        new = [
            m.statistics(x)
            for m, x in zip(norms, (states, action, reward.reshape(-1, 1)), strict=True)
        ]
        old_in, new_in = (
            tuple(torch.cat([o[i], a[i], o[i]]) for i in (0, 1))
            for o, a in ((old[0], old[1]), (new[0], new[1]))
        )
        refit_inputs(self.hidden[0].weight, self.hidden[0].bias, old_in, new_in)
        if self.learns_reward:
            refit_outputs(self.out.weight[:1], self.out.bias[:1], old[2], new[2])
        for m, (loc, scale) in zip(norms, new, strict=True):
            m.loc.copy_(loc)
            m.scale.copy_(scale)
            m.fitted.fill_(True)

    def _outputs(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """The MLP's raw outputs ``[..., reward + termination]`` (standardised reward, logit)."""
        check_features("obs", obs, self.obs_dim)
        check_features("action", action, self.action_dim)
        check_features("next_obs", next_obs, self.obs_dim)
        norm = self.obs_norm.normalize
        x = torch.cat([norm(obs), self.action_norm.normalize(action), norm(next_obs)], -1)
        act = ACTIVATIONS[self.activation]
        for layer in self.hidden:
            x = act(layer(x))
        return self.out(x)

    def reward(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """The predicted reward ``[...]`` of transitions ``[..., N]``, ``[..., M]``, ``[..., N]``."""
        if not self.learns_reward:
            raise ValueError("this RewardModel learns only the termination (reward=False).")
        std = self._outputs(obs, action, next_obs)[..., 0]
        return std * self.reward_norm.scale[0] + self.reward_norm.loc[0]

    def termination_logit(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """The logit ``[...]`` of the probability that ``next_obs`` ends the episode."""
        if not self.learns_termination:
            raise ValueError("this RewardModel does not learn the termination (termination=False).")
        return self._outputs(obs, action, next_obs)[..., -1]

    def termination_probability(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """The probability ``[...]`` that ``next_obs`` ends the episode."""
        return torch.sigmoid(self.termination_logit(obs, action, next_obs))

    def loss(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        reward: torch.Tensor,
        terminated: torch.Tensor,
        *,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The mean square error of the standardised reward plus the termination's binary cross
        entropy, over the steps ``mask`` marks real (all when None); ``reward`` and
        ``terminated`` ``[...]`` (or ``[..., 1]``)."""
        out = self._outputs(obs, action, next_obs)
        shape = out.shape[:-1]
        weight = (
            torch.ones(shape, dtype=out.dtype, device=out.device)
            if mask is None
            else mask.to(out.dtype)
        )
        count = weight.sum().clamp(min=1)
        total = out.new_zeros(())
        if self.learns_reward:
            target = self.reward_norm.normalize(reward.reshape(*shape, 1).to(out.dtype))[..., 0]
            total = total + ((out[..., 0] - target).pow(2) * weight).sum() / count
        if self.learns_termination:
            labels = terminated.reshape(shape).to(out.dtype)
            bce = F.binary_cross_entropy_with_logits(out[..., -1], labels, reduction="none")
            total = total + (bce * weight).sum() / count
        return total

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the predicted reward and termination probability of the transitions in
        ``tensordict`` (each head it learns) under ``out_keys``."""
        obs, action, next_obs = (tensordict.get(k) for k in self.in_keys)
        out = self._outputs(obs, action, next_obs)
        if self.learns_reward:
            reward = out[..., :1] * self.reward_norm.scale + self.reward_norm.loc
            tensordict.set(self.out_keys[0], reward)
        if self.learns_termination:
            tensordict.set(self.out_keys[1], torch.sigmoid(out[..., -1:]))
        return tensordict


class LearnedCost(nn.Module):
    """A :class:`RewardModel`'s reward as a planner's cost: ``cost(obs, action, next_obs) = −r``.

    A module (not a function), so a :class:`~torchrl_recon.planners.PlanningModel` holding it
    moves it with ``.to(device)`` and saves it in its ``state_dict``.

    Examples:
        >>> rewards = RewardModel(3, 1)
        >>> LearnedCost(rewards)(torch.zeros(5, 3), torch.zeros(5, 1), torch.zeros(5, 3)).shape
        torch.Size([5])
    """

    def __init__(self, reward_model: RewardModel) -> None:
        super().__init__()
        if not isinstance(reward_model, RewardModel) or not reward_model.learns_reward:
            raise TypeError("LearnedCost needs a RewardModel that learns the reward (reward=True).")
        self.reward_model = reward_model

    def forward(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        return -self.reward_model.reward(obs, action, next_obs)


class LearnedTermination(nn.Module):
    """A :class:`RewardModel`'s termination as a planner's rule: ``next_obs`` ends the episode
    where its predicted probability exceeds ``threshold`` (bool ``[...]``).

    Examples:
        >>> rewards = RewardModel(3, 1, reward=False, termination=True)
        >>> LearnedTermination(rewards)(torch.zeros(5, 3), torch.zeros(5, 1), torch.zeros(5, 3)).dtype
        torch.bool
    """

    def __init__(self, reward_model: RewardModel, *, threshold: float = 0.5) -> None:
        super().__init__()
        if not isinstance(reward_model, RewardModel) or not reward_model.learns_termination:
            raise TypeError(
                "LearnedTermination needs a RewardModel that learns the termination "
                "(termination=True)."
            )
        if not 0.0 < float(threshold) < 1.0:
            raise ValueError(f"threshold must be in (0, 1), got {threshold!r}.")
        self.reward_model, self.threshold = reward_model, float(threshold)
        self.logit_threshold = math.log(self.threshold / (1 - self.threshold))

    def forward(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        return self.reward_model.termination_logit(obs, action, next_obs) > self.logit_threshold
