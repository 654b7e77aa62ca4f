"""Populations: R models of one kind with stacked weights ``[R, ...]``, run as one batch.

Retraining a paper-size model 20 times is overhead-bound (small matmuls, many autograd nodes);
a population runs every member's step with one batched matmul (``bmm``/``baddbmm``) over a
leading member dim, through the same rollout engine as the single model
(:mod:`torchrl_recon.modules._lstm_rollout`). Members are independent: each one's outputs and
gradients depend on its own weights and inputs only. A population of one runs the single
model's own ops (2-D matmuls, ``torch.lstm``), so its results are bitwise the single model's.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.nn import functional as F

from torchrl_recon.modules._lstm_rollout import (
    LSTMRollout,
    fold_weights,
    recorded_rollout,
    rollout_inplace,
    sigmoid_tanh,
)
from torchrl_recon.modules.activations import ACTIVATIONS
from torchrl_recon.modules.checks import (
    check_features,
    check_finite,
    check_int,
    check_window,
    check_window_pair,
)
from torchrl_recon.modules.reconstruction import (
    ReconstructionUncertainty,
    window_errors,
    window_errors_blocked,
)
from torchrl_recon.modules.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.world_model import LSTMWorldModel


class _Population(TensorDictModuleBase):
    """Stacks the ``state_dict`` of R members of ``member_type``: entry ``a.b`` becomes ``a_b`` ``[R, ...]``."""

    member_type: ClassVar[type[nn.Module]]

    def __init__(self, *args, num_members: int, **kwargs) -> None:
        check_int("num_members", num_members)
        # Members built one after the other from the global RNG: member 0 of a population made
        # after torch.manual_seed(s) is the single model made after the same call.
        members = [self.member_type(*args, **kwargs) for _ in range(num_members)]
        super().__init__()
        self._stack(members)

    @classmethod
    def from_members(cls, members: Sequence[nn.Module]) -> _Population:
        """A population holding copies of ``members``' weights (all of one config and device).

        Examples:
            >>> pop = WorldModelPopulation.from_members([LSTMWorldModel(6, 3) for _ in range(4)])
            >>> pop.num_members, pop.lstm_weight_hh_l0.shape
            (4, torch.Size([4, 128, 32]))
        """
        members = list(members)
        if not members or not all(type(m) is cls.member_type for m in members):
            raise ValueError(
                f"{cls.__name__}.from_members needs at least one {cls.member_type.__name__}, "
                f"got {[type(m).__name__ for m in members]}."
            )
        configs = [m.config() for m in members]
        if any(c != configs[0] for c in configs):
            raise ValueError(f"All members must share one config; got {configs}.")
        pop = cls.__new__(cls)
        TensorDictModuleBase.__init__(pop)
        pop._stack(members)
        return pop

    def _stack(self, members: list[nn.Module]) -> None:
        template = members[0]
        self.num_members = len(members)
        self._member_config = template.config()
        self.in_keys, self.out_keys = list(template.in_keys), list(template.out_keys)
        self._keys = {}
        params = dict(template.named_parameters())
        states = [m.state_dict() for m in members]
        for key in states[0]:
            name = key.replace(".", "_")
            stacked = torch.stack([s[key].detach() for s in states])
            if key in params:
                self.register_parameter(name, nn.Parameter(stacked))
            else:
                self.register_buffer(name, stacked)
            self._keys[key] = name
        self._init_member_attrs(template)

    def _init_member_attrs(self, template: nn.Module) -> None:
        """Copy the members' size attributes (obs_dim, window, ...)."""

    def config(self) -> dict:
        """The members' constructor arguments and ``num_members`` (checkpoints rebuild from it)."""
        return {**self._member_config, "num_members": self.num_members}

    def member(self, index: int) -> nn.Module:
        """A standalone copy of member ``index`` (a ``member_type`` on this population's device)."""
        with torch.device("meta"):
            model = self.member_type(**self._member_config)
        ref = next(iter(self.state_dict().values()))
        model = model.to_empty(device=ref.device)
        state = {
            key: getattr(self, name)[index].detach().clone() for key, name in self._keys.items()
        }
        model.load_state_dict(state)
        model.in_keys, model.out_keys = list(self.in_keys), list(self.out_keys)
        return model

    def split(self) -> list[nn.Module]:
        """Every member as a standalone model; ``from_members(pop.split())`` gives ``pop`` back.

        Examples:
            >>> pop = WorldModelPopulation(6, 3, num_members=2)
            >>> [type(m).__name__ for m in pop.split()]
            ['LSTMWorldModel', 'LSTMWorldModel']
        """
        return [self.member(i) for i in range(self.num_members)]

    @torch.no_grad()
    def load_member(self, index: int, model: nn.Module) -> None:
        """Copy ``model``'s weights into member ``index``."""
        state = model.state_dict()
        for key, name in self._keys.items():
            getattr(self, name)[index].copy_(state[key])

    def _members_first(self, name: str, x: torch.Tensor, min_ndim: int) -> None:
        if x.dim() < min_ndim or x.shape[0] != self.num_members:
            raise ValueError(
                f"{name} has shape {tuple(x.shape)}; a population of {self.num_members} expects "
                f"the member dim first, [{self.num_members}, ...] with at least {min_ndim} dims."
            )

    def _bcast(self, stat: torch.Tensor, ndim: int) -> torch.Tensor:
        """A per-member ``[P, D]`` statistic viewed to broadcast against ``[P, ..., D]`` of ``ndim`` dims."""
        return stat.reshape(stat.shape[0], *([1] * (ndim - 2)), stat.shape[-1])


def _linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Per-member ``nn.Linear``: ``x`` ``[P, *B, in]``, ``weight`` ``[P, out, in]`` → ``[P, *B, out]``."""
    if weight.shape[0] == 1:  # one member: the single model's exact op
        return F.linear(x[0], weight[0], bias[0]).unsqueeze(0)
    flat = x.reshape(x.shape[0], -1, x.shape[-1])
    out = torch.baddbmm(bias.unsqueeze(-2), flat, weight.transpose(-1, -2))
    return out.reshape(*x.shape[:-1], weight.shape[-2])


def _lstm_cell(
    gates_x: torch.Tensor, h: torch.Tensor, c: torch.Tensor, w_hh_t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One LSTM step of every member: input gates ``[P, B, 4·hid]`` and state ``[P, B, hid]``."""
    gates = torch.baddbmm(gates_x, h, w_hh_t)
    i, f, g, o = gates.chunk(4, -1)
    c = torch.sigmoid(f) * c + torch.sigmoid(i) * sigmoid_tanh(g)
    h = torch.sigmoid(o) * sigmoid_tanh(c)
    return h, c


class WorldModelPopulation(_Population):
    """R :class:`~torchrl_recon.modules.LSTMWorldModel` members with weights ``[R, ...]``, run as one batch.

    Every input and output carries the member dim first: what the single model takes as
    ``[*B, ...]`` a population takes as ``[R, *B, ...]`` (member r's rows go through member r).
    The methods are the single model's: :meth:`warmup`, :meth:`step`, :meth:`rollout`,
    :meth:`imagine`, :meth:`predict_delta`, ``forward``, :meth:`normalize_inputs`, plus
    :meth:`prediction_loss` (one loss per member).

    Args:
        obs_dim, action_dim: as :class:`~torchrl_recon.modules.LSTMWorldModel`.

    Keyword Args:
        num_members: R, the members, initialised one after the other from the global RNG.
        **kwargs: the members' keyword arguments (``hidden_size``, ``window``, ...).

    Examples:
        >>> pop = WorldModelPopulation(6, 3, num_members=5, window=4)
        >>> ctx_s, ctx_a, s0 = torch.randn(5, 2, 4, 6), torch.randn(5, 2, 4, 3), torch.randn(5, 2, 6)
        >>> pop.imagine(ctx_s, ctx_a, s0, torch.rand(5, 2, 100, 30, 3)).shape
        torch.Size([5, 2, 100, 30, 6])
        >>> len(pop.split())
        5
    """

    member_type = LSTMWorldModel

    def __init__(self, obs_dim: int, action_dim: int, *, num_members: int, **kwargs) -> None:
        super().__init__(obs_dim, action_dim, num_members=num_members, **kwargs)

    def _init_member_attrs(self, template: LSTMWorldModel) -> None:
        self.obs_dim, self.action_dim = template.obs_dim, template.action_dim
        self.window, self.activation = template.window, template.activation
        self.hidden_size, self.dense_size = template.hidden_size, template.dense_size

    @property
    def feature_dim(self) -> int:
        """Features per step of the LSTM's input, N + M."""
        return self.obs_dim + self.action_dim

    def _norm(self, which: str, x: torch.Tensor) -> torch.Tensor:
        loc = self._bcast(getattr(self, f"{which}_norm_loc"), x.dim())
        return (x - loc) / self._bcast(getattr(self, f"{which}_norm_scale"), x.dim())

    def _denorm(self, which: str, x: torch.Tensor) -> torch.Tensor:
        scale = self._bcast(getattr(self, f"{which}_norm_scale"), x.dim())
        return x * scale + self._bcast(getattr(self, f"{which}_norm_loc"), x.dim())

    def normalize_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each member's LSTM input for ``obs`` ``[R, ..., N]``, ``action`` ``[R, ..., M]`` → ``[R, ..., N + M]``."""
        return torch.cat([self._norm("obs", obs), self._norm("action", action)], -1)

    def _lstm(
        self, x: torch.Tensor, hx: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """Each member's LSTM over ``x`` ``[P, B, L, F]`` from ``hx`` ``[P, B, hid]`` (zeros when None).

        Returns the outputs ``[P, B, L, hid]`` and the last ``(h, c)`` ``[P, B, hid]``.
        """
        w_ih, w_hh = self.lstm_weight_ih_l0, self.lstm_weight_hh_l0
        b_ih, b_hh = self.lstm_bias_ih_l0, self.lstm_bias_hh_l0
        members, rows, length, _ = x.shape
        hid = self.hidden_size
        if members == 1:  # one member: nn.LSTM's own kernel, as the single model runs it
            zeros = x.new_zeros(1, rows, hid)
            h0, c0 = (zeros, zeros) if hx is None else (s[0][None].contiguous() for s in hx)
            weights = [w_ih[0], w_hh[0], b_ih[0], b_hh[0]]
            out, h, c = torch.lstm(
                x[0], (h0, c0), weights, True, 1, 0.0, self.training, False, True
            )
            return out[None], (h, c)
        h, c = (x.new_zeros(members, rows, hid),) * 2 if hx is None else hx
        gates_x = self._input_gates(x)
        w_hh_t = w_hh.transpose(-1, -2)
        outs = []
        # `unbind`, not `gates_x[:, :, t]`: a slice's backward zero-fills a full-size gradient
        # per step (O(L²) memory traffic); unbind's is one stack.
        for gates_t in gates_x.unbind(2):
            h, c = _lstm_cell(gates_t, h, c, w_hh_t)
            outs.append(h)
        return torch.stack(outs, 2), (h, c)

    def _input_gates(self, x: torch.Tensor) -> torch.Tensor:
        """Each member's input part of the LSTM gates, ``x`` ``[P, B, L, F]`` → ``[P, B, L, 4·hid]``."""
        members, rows, length, features = x.shape
        bias = (self.lstm_bias_ih_l0 + self.lstm_bias_hh_l0).unsqueeze(-2)
        flat = x.reshape(members, -1, features)
        gates = torch.baddbmm(bias, flat, self.lstm_weight_ih_l0.transpose(-1, -2))
        return gates.reshape(members, rows, length, -1)

    def predict_window_deltas(
        self, obs: torch.Tensor, action: torch.Tensor, window: int
    ) -> torch.Tensor:
        """Normalised Δs predicted after every ``window``-step window of the sequences, each
        window read from a fresh LSTM state: ``[P, *B, L, N]``, ``[P, *B, L, M]`` →
        ``[P, *B, L − window + 1, N]``.

        The same as :meth:`predict_delta` on a copy of each window, last step (a sliding-window
        score), without the copies: the input part of the gates is computed once per step and
        only each window's last output goes through the head.

        Examples:
            >>> pop = WorldModelPopulation(6, 3, num_members=2, window=4)
            >>> pop.predict_window_deltas(torch.randn(2, 5, 12, 6), torch.randn(2, 5, 12, 3), 4).shape
            torch.Size([2, 5, 9, 6])
        """
        check_int("window", window)
        x = self._lstm_inputs(obs, action)
        if obs.shape[-2] < window:
            raise ValueError(
                f"obs has shape {tuple(obs.shape)}; expected at least window={window} steps (dim -2)."
            )
        members, length, hid = self.num_members, x.shape[-2], self.hidden_size
        windows = length - window + 1
        gates_x = self._input_gates(x)
        gates_x = gates_x.unfold(2, window, 1)  # [P, B, W, 4·hid, window], a view
        rows = gates_x.shape[1] * windows
        h = c = x.new_zeros(members, rows, hid)
        w_hh_t = self.lstm_weight_hh_l0.transpose(-1, -2)
        for t in range(window):
            h, c = _lstm_cell(gates_x[..., t].reshape(members, rows, -1), h, c, w_hh_t)
        return self._head(h).reshape(*obs.shape[:-2], windows, self.obs_dim)

    def _head(self, out: torch.Tensor) -> torch.Tensor:
        z = ACTIVATIONS[self.activation](_linear(out, self.dense_weight, self.dense_bias))
        return _linear(z, self.head_weight, self.head_bias)

    def predict_delta(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Teacher-forced normalised Δs for ``[R, *B, L, N]``, ``[R, *B, L, M]`` → ``[R, *B, L, N]``."""
        out, _ = self._lstm(self._lstm_inputs(obs, action))
        return self._head(out).reshape(*obs.shape)

    def _lstm_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Checked and normalised sequences ``[P, *B, L, N]``, ``[P, *B, L, M]`` as the LSTM's
        input ``[P, B, L, N + M]``."""
        self._members_first("obs", obs, 3)
        check_features("obs", obs, self.obs_dim, min_ndim=3)
        check_features("action", action, self.action_dim, min_ndim=3)
        if obs.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"obs {tuple(obs.shape)} and action {tuple(action.shape)} disagree on batch/time dims."
            )
        x = self.normalize_inputs(obs, action)
        return x.reshape(self.num_members, -1, x.shape[-2], x.shape[-1])

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action = tensordict.get(self.in_keys[0]), tensordict.get(self.in_keys[1])
        delta = self._denorm("delta", self.predict_delta(obs, action))
        tensordict.set(self.out_keys[0], obs + delta)
        return tensordict

    def warmup(
        self, context_obs: torch.Tensor, context_action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each member's LSTM state after a context ``[R, *B, T, N]``, ``[R, *B, T, M]`` → ``[R, *B, hid]``."""
        self._members_first("context_obs", context_obs, 3)
        check_features("context_obs", context_obs, self.obs_dim, min_ndim=3)
        check_features("context_action", context_action, self.action_dim, min_ndim=3)
        check_window("context_obs", context_obs, self.window)
        if context_obs.shape[:-1] != context_action.shape[:-1]:
            raise ValueError(
                f"context_obs {tuple(context_obs.shape)} and context_action "
                f"{tuple(context_action.shape)} disagree on batch/time dims."
            )
        check_finite("context_obs", context_obs)
        x = self.normalize_inputs(
            context_obs[..., -self.window :, :], context_action[..., -self.window :, :]
        )
        batch = x.shape[:-2]
        _, (h, c) = self._lstm(x.reshape(self.num_members, -1, self.window, x.shape[-1]))
        return h.reshape(*batch, self.hidden_size), c.reshape(*batch, self.hidden_size)

    def step(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """One step of every member: s_{t+1} ``[R, *B, N]`` and ``(h, c)`` ``[R, *B, hid]``."""
        self._members_first("observation", observation, 2)
        check_features("observation", observation, self.obs_dim)
        check_features("action", action, self.action_dim)
        if observation.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"observation {tuple(observation.shape)} and action {tuple(action.shape)} "
                "disagree on batch dims."
            )
        batch, hid, members = observation.shape[:-1], self.hidden_size, self.num_members
        x = self.normalize_inputs(observation, action).reshape(members, -1, 1, self.feature_dim)
        hx = None if state is None else tuple(s.reshape(members, -1, hid) for s in state)
        out, (h, c) = self._lstm(x, hx)
        delta = self._denorm("delta", self._head(out[:, :, 0]))
        return observation + delta.reshape(*batch, self.obs_dim), (
            h.reshape(*batch, hid),
            c.reshape(*batch, hid),
        )

    def folded_weights(self) -> tuple[torch.Tensor, ...]:
        """The members' weights for the rollout engine, ``[R, ...]`` each (see ``fold_weights``).

        A population of one gets its member's 2-D weights, folded by the single model's ops.
        """
        names = ("obs", "action", "delta")
        norms = tuple(getattr(self, f"{n}_norm_{s}") for n in names for s in ("loc", "scale"))
        raw = (
            self.lstm_weight_ih_l0,
            self.lstm_weight_hh_l0,
            self.lstm_bias_ih_l0,
            self.lstm_bias_hh_l0,
            self.dense_weight,
            self.dense_bias,
            self.head_weight,
            self.head_bias,
        )
        if self.num_members == 1:
            raw, norms = tuple(w[0] for w in raw), tuple(x[0] for x in norms)
        return fold_weights(*raw, norms)

    def _rollout(
        self,
        s0: torch.Tensor,
        h: torch.Tensor,
        c: torch.Tensor,
        actions: torch.Tensor,
        recorded: bool = False,
    ) -> torch.Tensor:
        """``[P, R, N]``, ``[P, R, hid]`` x2, ``[P, R, H, M]`` → ``[P, R, H, N]`` on the engine's fastest path."""
        weights = self.folded_weights()
        inputs = (s0, h, c, actions)
        one = self.num_members == 1
        if one:  # one member: the single model's 2-D ops
            inputs = tuple(x[0] for x in inputs)
        needs_grad = torch.is_grad_enabled() and any(x.requires_grad for x in (*inputs, *weights))
        if recorded:
            states = recorded_rollout(*inputs, self.activation, *weights)
        elif needs_grad:
            states = LSTMRollout.apply(*inputs, self.activation, *weights)
        elif one:
            states = rollout_inplace(*inputs, self.activation, *weights)
        else:
            with torch.no_grad():
                states = recorded_rollout(*inputs, self.activation, *weights)
        return states[None] if one else states

    def rollout(
        self,
        observation: torch.Tensor,
        actions: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor],
        *,
        recorded: bool = False,
    ) -> torch.Tensor:
        """Every member's autoregressive rollout: ``[R, *B, N]``, ``[R, *B, H, M]`` → ``[R, *B, H, N]``.

        Examples:
            >>> pop = WorldModelPopulation(6, 3, num_members=3, window=4)
            >>> state = pop.warmup(torch.zeros(3, 2, 4, 6), torch.zeros(3, 2, 4, 3))
            >>> pop.rollout(torch.zeros(3, 2, 6), torch.rand(3, 2, 20, 3), state).shape
            torch.Size([3, 2, 20, 6])
        """
        self._members_first("observation", observation, 2)
        check_features("observation", observation, self.obs_dim)
        check_features("actions", actions, self.action_dim, min_ndim=3)
        batch, hid, members = observation.shape[:-1], self.hidden_size, self.num_members
        if actions.shape[:-2] != batch:
            raise ValueError(
                f"actions has shape {tuple(actions.shape)}; expected [R, *B, H, {self.action_dim}] "
                f"with [R, *B] = {tuple(batch)}."
            )
        horizon = actions.shape[-2]
        s0 = observation.reshape(members, -1, self.obs_dim)
        h, c = (x.reshape(members, -1, hid) for x in state)
        flat = actions.reshape(members, -1, horizon, self.action_dim)
        states = self._rollout(s0, h, c, flat, recorded)
        return states.reshape(*batch, horizon, self.obs_dim)

    def imagine(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        actions: torch.Tensor,
        *,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Every member's predicted states for its candidates ``[R, *B, K, H, M]`` → ``[R, *B, K, H, N]``.

        Arguments as :meth:`LSTMWorldModel.imagine`, each with the member dim first.
        """
        self._members_first("observation", observation, 2)
        check_features("observation", observation, self.obs_dim)
        check_features("actions", actions, self.action_dim, min_ndim=4)
        batch, members, hid = observation.shape[:-1], self.num_members, self.hidden_size
        if actions.shape[:-3] != batch:
            raise ValueError(
                f"actions has shape {tuple(actions.shape)}; expected [R, *B, K, H, "
                f"{self.action_dim}] with [R, *B] = {tuple(batch)}."
            )
        check_finite("observation", observation)
        h, c = self.warmup(context_obs, context_action) if state is None else state
        k, horizon = actions.shape[-3], actions.shape[-2]

        def expand(x: torch.Tensor, size: int) -> torch.Tensor:
            return x.reshape(members, -1, 1, size).expand(-1, -1, k, -1).reshape(members, -1, size)

        s0, h, c = expand(observation, self.obs_dim), expand(h, hid), expand(c, hid)
        flat = actions.reshape(members, -1, horizon, self.action_dim)
        states = self._rollout(s0, h, c, flat)
        return states.reshape(*batch, k, horizon, self.obs_dim)

    def prediction_loss(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, mode: str
    ) -> torch.Tensor:
        """Each member's ``WorldModelPredictionLoss`` on its sequences ``[R, B, L, ...]`` → ``[R]``."""
        if mode == "one_step":
            pred = self.predict_delta(obs, action)
            err = pred - self._norm("delta", next_obs - obs)
        elif mode == "multi_step":
            w = self.window
            if obs.shape[-2] <= w:
                raise ValueError(
                    f"multi_step loss needs sequences longer than window={w}, got length {obs.shape[-2]}."
                )
            pred = self.imagine(
                obs[..., :w, :], action[..., :w, :], obs[..., w, :], action[..., None, w:, :]
            )[..., 0, :, :]
            scale = self._bcast(self.obs_norm_scale, pred.dim())
            err = (pred - next_obs[..., w:, :]) / scale
        else:
            raise ValueError(f"mode must be 'multi_step' or 'one_step', got {mode!r}.")
        return err.pow(2).reshape(self.num_members, -1).mean(1)


class ReconstructionPopulation(_Population):
    """R :class:`~torchrl_recon.modules.ReconstructionUncertainty` autoencoders, weights ``[R, ...]``.

    Inputs carry the member dim first (``[R, *B, L, N]``); :meth:`score` gives ``[R, *B, W]``
    and :meth:`loss` one mean u per member ``[R]``.

    Examples:
        >>> pop = ReconstructionPopulation(6, 3, num_members=4, window=10)
        >>> pop.score(torch.randn(4, 2, 30, 6), torch.randn(4, 2, 30, 3)).shape
        torch.Size([4, 2, 21])
        >>> pop.loss(torch.randn(4, 2, 30, 6), torch.randn(4, 2, 30, 3)).shape
        torch.Size([4])
    """

    member_type = ReconstructionUncertainty

    def __init__(self, obs_dim: int, action_dim: int, *, num_members: int, **kwargs) -> None:
        super().__init__(obs_dim, action_dim, num_members=num_members, **kwargs)

    def _init_member_attrs(self, template: UncertaintyEstimator) -> None:
        self.obs_dim, self.action_dim = template.obs_dim, template.action_dim
        self.window, self.activation = template.window, template.activation
        self.hidden_size = template.hidden_size

    def score(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each member's u for every window of ``[R, *B, L, N]``, ``[R, *B, L, M]`` → ``[R, *B, L - T + 1]``."""
        self._members_first("obs", obs, 3)
        check_window_pair(
            obs,
            action,
            obs_dim=self.obs_dim,
            action_dim=self.action_dim,
            window=self.window,
            min_ndim=3,
        )
        check_finite("obs", obs.detach())
        check_finite("action", action.detach())
        length, members = obs.shape[-2], self.num_members
        x = torch.cat([obs, action], -1).reshape(
            members, -1, length, obs.shape[-1] + action.shape[-1]
        )
        loc = self._bcast(self.input_norm_loc, 4)
        x = ((x - loc) / self._bcast(self.input_norm_scale, 4)).contiguous()
        weights = (self.encoder_weight, self.encoder_bias, self.decoder_weight, self.decoder_bias)
        needs_grad = torch.is_grad_enabled() and (x.requires_grad or weights[0].requires_grad)
        if members == 1:  # one member: the single autoencoder's own ops
            weights = tuple(w[0] for w in weights)
            fn = window_errors if needs_grad else window_errors_blocked
            u = fn(x[0], self.window, self.activation, *weights)[None]
        else:
            u = window_errors(x, self.window, self.activation, *weights)
        return u.reshape(*obs.shape[:-2], length - self.window + 1)

    def loss(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each member's training loss, the mean u over its windows (paper eq. 1), ``[R]``."""
        return self.score(obs, action).reshape(self.num_members, -1).mean(1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action = tensordict.get(self.in_keys[0]), tensordict.get(self.in_keys[1])
        u = self.score(obs, action)
        pad = u.new_full((*u.shape[:-1], self.window - 1), float("nan"))
        tensordict.set(self.out_keys[0], torch.cat([pad, u], -1))
        return tensordict
