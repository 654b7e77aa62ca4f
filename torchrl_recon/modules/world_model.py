"""The paper's recurrent world model: an LSTM that predicts state changes Δs."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from torchrl_recon.modules._lstm_rollout import (
    LSTMRollout,
    fold_weights,
    recorded_rollout,
    rollout_inplace,
)
from torchrl_recon.modules.activations import ACTIVATIONS
from torchrl_recon.modules.checks import (
    check_activation,
    check_features,
    check_finite,
    check_int,
    check_window,
)
from torchrl_recon.modules.normalization import Normalizer


class LSTMWorldModel(TensorDictModuleBase):
    """LSTM → dense → linear world model predicting Δs_{t+1} from past (s, a) (paper §2.1).

    Inputs and targets are standardised with statistics fitted by :meth:`fit_normalization`
    and stored as buffers, so ``state_dict`` is self-contained.

    Two uses, both batched:

    * ``forward(td)``: teacher-forced one-step predictions along the time dim of
      ``td[obs_key]`` ``[*B, L, N]`` and ``td[action_key]`` ``[*B, L, M]``; writes the
      predicted next observations ``[*B, L, N]`` to ``out_key``.
    * :meth:`imagine`: warm up on a real context of ``window`` (s, a) pairs, then roll out
      ``[*B, K, H, M]`` candidate action sequences autoregressively, all candidates at once,
      differentiably with respect to the actions.

    Their parts are public too: :meth:`warmup` (the LSTM state after a context), :meth:`step`
    (one autoregressive step) and :meth:`rollout` (many steps from a warmed-up state).
    Every output is made on the device and dtype of the model and its inputs.

    Args:
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        hidden_size: LSTM units (paper: 32).
        dense_size: units of the dense hidden layer.
        window: context length T used to warm the LSTM up (paper: 10).
        activation: ``"relu"``, ``"tanh"`` or ``"elu"`` after the dense layer.
        obs_key, action_key: input keys.
        out_key: where ``forward`` writes predicted next observations.

    Examples:
        >>> model = LSTMWorldModel(6, 3)
        >>> ctx_s, ctx_a, s0 = torch.randn(2, 10, 6), torch.randn(2, 10, 3), torch.randn(2, 6)
        >>> model.imagine(ctx_s, ctx_a, s0, torch.rand(2, 100, 30, 3)).shape
        torch.Size([2, 100, 30, 6])
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        *,
        hidden_size: int = 32,
        dense_size: int = 32,
        window: int = 10,
        activation: str = "relu",
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = ("next", "predicted_observation"),
    ) -> None:
        super().__init__()
        check_activation(activation)
        for name, value in (
            ("obs_dim", obs_dim),
            ("action_dim", action_dim),
            ("hidden_size", hidden_size),
            ("dense_size", dense_size),
            ("window", window),
        ):
            check_int(name, value)
        self.obs_dim, self.action_dim, self.window = obs_dim, action_dim, window
        self.hidden_size, self.dense_size, self.activation = hidden_size, dense_size, activation
        self.in_keys = [obs_key, action_key]
        self.out_keys = [out_key]
        self.lstm = nn.LSTM(obs_dim + action_dim, hidden_size, batch_first=True)
        self.dense = nn.Linear(hidden_size, dense_size)
        self.head = nn.Linear(dense_size, obs_dim)
        self.obs_norm = Normalizer(obs_dim)
        self.action_norm = Normalizer(action_dim)
        self.delta_norm = Normalizer(obs_dim)

    def config(self) -> dict:
        """Constructor arguments, stored in checkpoints and checked on load."""
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "hidden_size": self.hidden_size,
            "dense_size": self.dense_size,
            "window": self.window,
            "activation": self.activation,
        }

    @property
    def feature_dim(self) -> int:
        """Features per step of the LSTM's input, N + M."""
        return self.obs_dim + self.action_dim

    def fit_normalization(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> None:
        """Fit input and target statistics from real transitions ``[..., N]``, ``[..., M]``, ``[..., N]``."""
        check_features("obs", obs, self.obs_dim)
        check_features("action", action, self.action_dim)
        check_features("next_obs", next_obs, self.obs_dim)
        self.obs_norm.fit(obs)
        self.action_norm.fit(action)
        self.delta_norm.fit(next_obs - obs)

    def normalize_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The LSTM's input for raw ``obs`` ``[..., N]`` and ``action`` ``[..., M]``: both
        standardised, concatenated, ``[..., N + M]``.

        Examples:
            >>> LSTMWorldModel(6, 3).normalize_inputs(torch.zeros(5, 6), torch.ones(5, 3)).shape
            torch.Size([5, 9])
        """
        return torch.cat([self.obs_norm.normalize(obs), self.action_norm.normalize(action)], -1)

    def predict_delta(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Teacher-forced normalised Δs predictions for sequences ``[*B, L, N]``, ``[*B, L, M]``."""
        check_features("obs", obs, self.obs_dim, min_ndim=2)
        check_features("action", action, self.action_dim, min_ndim=2)
        if obs.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"obs {tuple(obs.shape)} and action {tuple(action.shape)} disagree on batch/time dims."
            )
        x = self.normalize_inputs(obs, action)
        batch, length = x.shape[:-2], x.shape[-2]
        out, _ = self.lstm(x.reshape(-1, length, x.shape[-1]))
        z = ACTIVATIONS[self.activation](self.dense(out))
        return self.head(z).reshape(*batch, length, self.obs_dim)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action = tensordict.get(self.in_keys[0]), tensordict.get(self.in_keys[1])
        delta = self.delta_norm.denormalize(self.predict_delta(obs, action))
        tensordict.set(self.out_keys[0], obs + delta)
        return tensordict

    def warmup(
        self, context_obs: torch.Tensor, context_action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Run the LSTM over a real context ``[*B, T, N]``, ``[*B, T, M]``; return ``(h, c)`` ``[*B, hidden]``."""
        check_features("context_obs", context_obs, self.obs_dim, min_ndim=2)
        check_features("context_action", context_action, self.action_dim, min_ndim=2)
        check_window("context_obs", context_obs, self.window)
        if context_obs.shape[:-1] != context_action.shape[:-1]:
            raise ValueError(
                f"context_obs {tuple(context_obs.shape)} and context_action {tuple(context_action.shape)} "
                "disagree on batch/time dims."
            )
        check_finite("context_obs", context_obs)
        x = self.normalize_inputs(
            context_obs[..., -self.window :, :], context_action[..., -self.window :, :]
        )
        batch = x.shape[:-2]
        _, (h, c) = self.lstm(x.reshape(-1, self.window, x.shape[-1]))
        return h[0].reshape(*batch, self.hidden_size), c[0].reshape(*batch, self.hidden_size)

    def _folded_weights(self) -> tuple[torch.Tensor, ...]:
        """Fold the normalisations into the weights so the rollout works in raw units."""
        lstm = self.lstm
        return fold_weights(
            lstm.weight_ih_l0,
            lstm.weight_hh_l0,
            lstm.bias_ih_l0,
            lstm.bias_hh_l0,
            self.dense.weight,
            self.dense.bias,
            self.head.weight,
            self.head.bias,
            self.norm_stats(),
        )

    def norm_stats(self) -> tuple[torch.Tensor, ...]:
        """``(obs_loc, obs_scale, action_loc, action_scale, delta_loc, delta_scale)``."""
        return tuple(
            t
            for norm in (self.obs_norm, self.action_norm, self.delta_norm)
            for t in (norm.loc, norm.scale)
        )

    def imagine(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        actions: torch.Tensor,
        *,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Predict states for candidate action sequences, all candidates in one batch.

        Args:
            context_obs: real past states s_{t-T..t-1}, ``[*B, T', N]`` with T' >= window.
            context_action: real past actions a_{t-T..t-1}, ``[*B, T', M]``.
            observation: the current real state s_t, ``[*B, N]``.
            actions: candidates a_{t..t+H-1}, ``[*B, K, H, M]``.
            state: ``(h, c)`` from :meth:`warmup` on this context, to skip recomputing it
                (planners call ``imagine`` many times on one context).

        Returns:
            Predicted states s_{t+1..t+H}, ``[*B, K, H, N]`` (differentiable w.r.t. ``actions``).
        """
        check_features("observation", observation, self.obs_dim)
        check_features("actions", actions, self.action_dim, min_ndim=3)
        batch = observation.shape[:-1]
        if actions.shape[:-3] != batch:
            raise ValueError(
                f"actions has shape {tuple(actions.shape)}; expected [*B, K, H, {self.action_dim}] with *B = {tuple(batch)}."
            )
        check_finite("observation", observation)
        h, c = self.warmup(context_obs, context_action) if state is None else state
        k, horizon = actions.shape[-3], actions.shape[-2]
        rows = int(torch.Size(batch).numel()) * k
        s0 = observation.reshape(-1, 1, self.obs_dim).expand(-1, k, -1).reshape(rows, self.obs_dim)
        h = h.reshape(-1, 1, self.hidden_size).expand(-1, k, -1).reshape(rows, self.hidden_size)
        c = c.reshape(-1, 1, self.hidden_size).expand(-1, k, -1).reshape(rows, self.hidden_size)
        flat_actions = actions.reshape(rows, horizon, self.action_dim)
        states = self._rollout(s0, h, c, flat_actions)
        return states.reshape(*batch, k, horizon, self.obs_dim)

    def step(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """One-step prediction: s_{t+1} from s_t ``[*B, N]``, a_t ``[*B, M]`` and the LSTM state.

        Args:
            observation: s_t, ``[*B, N]``.
            action: a_t, ``[*B, M]``.
            state: ``(h, c)`` ``[*B, hidden]`` from :meth:`warmup` or the previous step; zeros
                when None.

        Returns:
            ``(s_{t+1} [*B, N], (h, c))``: feed both back for the next step (this calls the
            model's ``nn.LSTM`` once per step; :meth:`rollout` does many steps at once).

        Examples:
            >>> model = LSTMWorldModel(6, 3)
            >>> s, state = model.step(torch.zeros(2, 6), torch.zeros(2, 3))
            >>> s, state = model.step(s, torch.ones(2, 3), state)
            >>> s.shape, state[0].shape
            (torch.Size([2, 6]), torch.Size([2, 32]))
        """
        check_features("observation", observation, self.obs_dim)
        check_features("action", action, self.action_dim)
        if observation.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"observation {tuple(observation.shape)} and action {tuple(action.shape)} "
                "disagree on batch dims."
            )
        batch, hid = observation.shape[:-1], self.hidden_size
        x = self.normalize_inputs(observation, action).reshape(-1, 1, self.feature_dim)
        hx = None
        if state is not None:
            hx = tuple(s.reshape(1, -1, hid).contiguous() for s in state)
        out, (h, c) = self.lstm(x, hx)
        z = ACTIVATIONS[self.activation](self.dense(out[:, 0]))
        delta = self.delta_norm.denormalize(self.head(z)).reshape(*batch, self.obs_dim)
        return observation + delta, (h[0].reshape(*batch, hid), c[0].reshape(*batch, hid))

    def rollout(
        self,
        observation: torch.Tensor,
        actions: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor],
        *,
        recorded: bool = False,
    ) -> torch.Tensor:
        """Roll action sequences out autoregressively from a warmed-up state, one row each.

        Args:
            observation: s_t, ``[*B, N]``.
            actions: a_{t..t+H-1}, ``[*B, H, M]``.
            state: ``(h, c)`` ``[*B, hidden]`` (from :meth:`warmup`).

        Keyword Args:
            recorded: record every op with autograd (the slow reference) instead of the
                default: an in-place loop when nothing needs a gradient, else one autograd
                node with a hand-written backward through time, bitwise the reference's
                states and gradients.

        Returns:
            s_{t+1..t+H}, ``[*B, H, N]``, differentiable w.r.t. the actions, the start state and
            the model's parameters.

        Examples:
            >>> model = LSTMWorldModel(6, 3, window=4)
            >>> state = model.warmup(torch.zeros(2, 4, 6), torch.zeros(2, 4, 3))
            >>> model.rollout(torch.zeros(2, 6), torch.rand(2, 20, 3), state).shape
            torch.Size([2, 20, 6])
        """
        check_features("observation", observation, self.obs_dim)
        check_features("actions", actions, self.action_dim, min_ndim=2)
        batch, hid = observation.shape[:-1], self.hidden_size
        if actions.shape[:-2] != batch:
            raise ValueError(
                f"actions has shape {tuple(actions.shape)}; expected [*B, H, {self.action_dim}] "
                f"with *B = {tuple(batch)}."
            )
        horizon = actions.shape[-2]
        s0 = observation.reshape(-1, self.obs_dim)
        h, c = (x.reshape(-1, hid) for x in state)
        flat_actions = actions.reshape(-1, horizon, self.action_dim)
        if recorded:
            states = recorded_rollout(
                s0, h, c, flat_actions, self.activation, *self._folded_weights()
            )
        else:
            states = self._rollout(s0, h, c, flat_actions)
        return states.reshape(*batch, horizon, self.obs_dim)

    def _rollout(
        self, s0: torch.Tensor, h: torch.Tensor, c: torch.Tensor, actions: torch.Tensor
    ) -> torch.Tensor:
        """``[R, N]``, ``[R, hid]``, ``[R, hid]``, ``[R, H, M]`` → ``[R, H, N]`` on the fastest path."""
        needs_grad = torch.is_grad_enabled() and any(
            x.requires_grad for x in (s0, h, c, actions, *self.parameters())
        )
        if needs_grad:  # one autograd node with a hand-written backward through time
            return LSTMRollout.apply(s0, h, c, actions, self.activation, *self._folded_weights())
        return rollout_inplace(s0, h, c, actions, self.activation, *self._folded_weights())
