"""The paper's recurrent world model: an LSTM that predicts state changes Δs, one model or R."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.nn import functional as F

from torchrl_recon.modules._lstm_rollout import (
    _addmm,
    _addmm_step,
    fold_weights,
    lstm_cell,
    rollout,
    sigmoid_tanh,
)
from torchrl_recon.modules.activations import ACTIVATIONS
from torchrl_recon.modules.checks import (
    check_activation,
    check_features,
    check_finite,
    check_int,
    check_window,
)
from torchrl_recon.modules.members import StackedMembers
from torchrl_recon.modules.normalization import Normalizer, refit_inputs, refit_outputs
from torchrl_recon.modules.padding import check_prefix_mask, masked_mean, start_at_rest


class LSTMWorldModel(StackedMembers, TensorDictModuleBase):
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

    **Members.** With ``num_members=R`` the model is R independent world models run as one
    batch (retraining many models is overhead-bound: each step becomes one batched matmul over
    the members). Every parameter and buffer keeps its name with the member dim first
    (``lstm.weight_ih_l0`` ``[R, 4·hid, N + M]``, stacked by ``TensorDict.from_modules``), and
    every input and output carries it first: ``[R, *B, ...]``, member r's rows through member
    r. :meth:`from_members`, :meth:`member`, :meth:`split` and :meth:`load_member` move
    members in and out; :meth:`prediction_loss` gives one loss per member. Member 0 of
    ``LSTMWorldModel(..., num_members=R)`` made after ``torch.manual_seed(s)`` is the single
    model made after the same call, and R = 1 runs the single model's own ops (its results are
    bitwise the single model's).

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
        num_members: None (default) for one model; R for R members with a leading member
            dim, initialised one after the other from the global RNG.

    Examples:
        >>> model = LSTMWorldModel(6, 3)
        >>> ctx_s, ctx_a, s0 = torch.randn(2, 10, 6), torch.randn(2, 10, 3), torch.randn(2, 6)
        >>> model.imagine(ctx_s, ctx_a, s0, torch.rand(2, 100, 30, 3)).shape
        torch.Size([2, 100, 30, 6])
        >>> models = LSTMWorldModel(6, 3, num_members=5, window=4)
        >>> ctx_s, ctx_a, s0 = torch.randn(5, 2, 4, 6), torch.randn(5, 2, 4, 3), torch.randn(5, 2, 6)
        >>> models.imagine(ctx_s, ctx_a, s0, torch.rand(5, 2, 100, 30, 3)).shape
        torch.Size([5, 2, 100, 30, 6])
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
        num_members: int | None = None,
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
        self.num_members = num_members
        self._register_member_hooks()
        if num_members is not None:
            check_int("num_members", num_members)
            member = dict(
                hidden_size=hidden_size,
                dense_size=dense_size,
                window=window,
                activation=activation,
                obs_key=obs_key,
                action_key=action_key,
                out_key=out_key,
            )
            self._hold([LSTMWorldModel(obs_dim, action_dim, **member) for _ in range(num_members)])
            return
        self.lstm = nn.LSTM(obs_dim + action_dim, hidden_size, batch_first=True)
        self.dense = nn.Linear(hidden_size, dense_size)
        self.head = nn.Linear(dense_size, obs_dim)
        self.obs_norm = Normalizer(obs_dim)
        self.action_norm = Normalizer(action_dim)
        self.delta_norm = Normalizer(obs_dim)

    def config(self) -> dict:
        """Constructor arguments, stored in checkpoints and checked on load."""
        config = {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "hidden_size": self.hidden_size,
            "dense_size": self.dense_size,
            "window": self.window,
            "activation": self.activation,
        }
        if self.num_members is not None:
            config["num_members"] = self.num_members
        return config

    @property
    def feature_dim(self) -> int:
        """Features per step of the LSTM's input, N + M."""
        return self.obs_dim + self.action_dim

    # -- the member dim: inputs carry ``[R]`` first when num_members is set; the engine runs
    # a member dim only for R > 1 (R = 1 takes member 0's weights and the single model's ops).

    @property
    def _lead(self) -> tuple[int, ...]:
        """The engine's member dim: ``(R,)`` for R > 1 members, else none."""
        return (self.num_members,) if (self.num_members or 1) > 1 else ()

    def _engine(self, weight: torch.Tensor) -> torch.Tensor:
        """A weight as the engine takes it: member 0's for one member, else as held."""
        return weight[0] if self.num_members == 1 else weight

    def _ndim(self, ndim: int) -> int:
        """Dims an input needs: ``ndim`` plus the member dim when there is one."""
        return ndim + (self.num_members is not None)

    def _shape_error(self, name: str, x: torch.Tensor, tail: str, batch: torch.Size) -> ValueError:
        dims, named = ("*B", "*B") if self.num_members is None else ("R, *B", "[R, *B]")
        return ValueError(
            f"{name} has shape {tuple(x.shape)}; expected [{dims}, {tail}] with {named} = "
            f"{tuple(batch)}."
        )

    def _stat(self, which: str, stat: str, ndim: int) -> torch.Tensor:
        """``{which}_norm``'s ``loc`` or ``scale``, to broadcast against ``[*R, ..., D]`` of ``ndim`` dims."""
        value = getattr(getattr(self, f"{which}_norm"), stat)
        return value if self.num_members is None else self._bcast(value, ndim)

    def _norm(self, which: str, x: torch.Tensor) -> torch.Tensor:
        return (x - self._stat(which, "loc", x.dim())) / self._stat(which, "scale", x.dim())

    def _denorm(self, which: str, x: torch.Tensor) -> torch.Tensor:
        return x * self._stat(which, "scale", x.dim()) + self._stat(which, "loc", x.dim())

    def fit_normalization(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> None:
        """Fit input and target statistics from real transitions ``[..., N]``, ``[..., M]``, ``[..., N]``.

        The three must agree on their leading (row) dims, one action and one next observation
        per observation; NaN or inf in any of them is refused (``ValueError`` naming the
        argument and the first bad index).

        Examples:
            >>> LSTMWorldModel(2, 1).fit_normalization(torch.zeros(5, 2), torch.zeros(4, 1), torch.zeros(5, 2))
            Traceback (most recent call last):
            ...
            ValueError: obs (5, 2), action (4, 1) and next_obs (5, 2) disagree on batch dims; expected one action and one next_obs per observation.
        """
        if self.num_members is not None:
            raise ValueError(
                "fit_normalization fits one model; fit each member's before stacking them "
                "(LSTMWorldModel.from_members)."
            )
        check_features("obs", obs, self.obs_dim)
        check_features("action", action, self.action_dim)
        check_features("next_obs", next_obs, self.obs_dim)
        if not obs.shape[:-1] == action.shape[:-1] == next_obs.shape[:-1]:
            raise ValueError(
                f"obs {tuple(obs.shape)}, action {tuple(action.shape)} and next_obs "
                f"{tuple(next_obs.shape)} disagree on batch dims; expected one action and one "
                "next_obs per observation."
            )
        check_finite("obs", obs)
        check_finite("action", action)
        check_finite("next_obs", next_obs)
        self.obs_norm.fit(obs)
        self.action_norm.fit(action)
        self.delta_norm.fit(next_obs - obs)

    @torch.no_grad()
    def refit_normalization(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> None:
        """Refit the statistics on (more) real transitions and keep the model's function: the
        LSTM's input weights and the output layer are rewritten so that every prediction, in raw
        units, stays what it was (``modules.normalization.refit_inputs``,
        ``refit_outputs``); an input the old statistics saw constant starts from zero weight.
        A warm refit then trains in statistics of all the data so far (mbrl-lib refits its
        normaliser before each training too), so a feature that only started to move late (a
        constraint force at a rail) is not read at tens of its old, unit scale. Members all get
        the statistics of the same data.

        Examples:
            >>> model = LSTMWorldModel(2, 1, window=3)
            >>> s, a = torch.randn(40, 2), torch.randn(40, 1)
            >>> model.fit_normalization(s, a, s + 0.1)
            >>> ctx_s, ctx_a, plans = torch.randn(3, 2), torch.randn(3, 1), torch.rand(5, 4, 1)
            >>> before = model.imagine(ctx_s, ctx_a, s[0], plans)
            >>> model.refit_normalization(3 * s, a + 1, 3 * s + 0.5)
            >>> after = model.imagine(ctx_s, ctx_a, s[0], plans)
            >>> torch.allclose(before, after, atol=1e-5), bool(model.obs_norm.scale.mean() > 2)
            (True, True)
        """
        check_features("obs", obs, self.obs_dim)
        check_features("action", action, self.action_dim)
        check_features("next_obs", next_obs, self.obs_dim)
        pairs = (
            (self.obs_norm, obs),
            (self.action_norm, action),
            (self.delta_norm, next_obs - obs),
        )
        old = [(norm.loc.clone(), norm.scale.clone()) for norm, _ in pairs]
        new = [Normalizer(x.shape[-1]).to(norm.loc).statistics(x) for norm, x in pairs]
        new = [tuple(t.expand_as(o) for t in stats) for stats, (o, _) in zip(new, old, strict=True)]
        old_in, new_in = (
            tuple(torch.cat([o[i], a[i]], -1) for i in (0, 1))
            for o, a in ((old[0], old[1]), (new[0], new[1]))
        )
        refit_inputs(self.lstm.weight_ih_l0, self.lstm.bias_ih_l0, old_in, new_in)
        refit_outputs(self.head.weight, self.head.bias, old[2], new[2])
        for (norm, _), (loc, scale) in zip(pairs, new, strict=True):
            norm.loc.copy_(loc)
            norm.scale.copy_(scale)
            norm.fitted.fill_(True)

    def normalize_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The LSTM's input for raw ``obs`` ``[*R, ..., N]`` and ``action`` ``[*R, ..., M]``: both
        standardised, concatenated, ``[*R, ..., N + M]``.

        Examples:
            >>> LSTMWorldModel(6, 3).normalize_inputs(torch.zeros(5, 6), torch.ones(5, 3)).shape
            torch.Size([5, 9])
        """
        return torch.cat([self._norm("obs", obs), self._norm("action", action)], -1)

    def norm_stats(self) -> tuple[torch.Tensor, ...]:
        """``(obs_loc, obs_scale, action_loc, action_scale, delta_loc, delta_scale)``."""
        return tuple(
            t
            for norm in (self.obs_norm, self.action_norm, self.delta_norm)
            for t in (norm.loc, norm.scale)
        )

    def _lstm_weights(self) -> tuple[torch.Tensor, ...]:
        lstm = self.lstm
        return lstm.weight_ih_l0, lstm.weight_hh_l0, lstm.bias_ih_l0, lstm.bias_hh_l0

    def _lstm(
        self, x: torch.Tensor, hx: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """The LSTM over ``x`` ``[*R, B, L, F]`` from ``hx`` ``[*R, B, hid]`` (zeros when None).

        Returns the outputs ``[*R, B, L, hid]`` and the last ``(h, c)`` ``[*R, B, hid]``.

        One model runs ``nn.LSTM``'s own kernel (``torch.lstm``, cuDNN on a GPU): the one
        reference fast path, kept for its speed and for the bitwise numbers of saved models and
        published runs (R = 1 runs it on member 0's weights). R > 1 members run
        :func:`~torchrl_recon.modules._lstm_rollout.lstm_cell` step by step, each step's
        recurrent part one batched matmul.
        """
        if not self._lead:
            hx = None if hx is None else tuple(s[None].contiguous() for s in hx)
            if self.num_members is None:
                out, (h, c) = self.lstm(x, hx)
            else:
                if hx is None:
                    zeros = x.new_zeros(1, x.shape[0], self.hidden_size)
                    hx = (zeros, zeros)
                weights = [self._engine(w) for w in self._lstm_weights()]
                out, h, c = torch.lstm(x, hx, weights, True, 1, 0.0, self.training, False, True)
            return out, (h[0], c[0])
        w_ih, w_hh, b_ih, b_hh = self._lstm_weights()
        members, rows = x.shape[:2]
        h, c = (x.new_zeros(members, rows, self.hidden_size),) * 2 if hx is None else hx
        gates_x = _input_gates(x, w_ih, b_ih, b_hh)
        w_hh_t = w_hh.transpose(-1, -2)
        outs = []
        # `unbind`, not `gates_x[:, :, t]`: a slice's backward zero-fills a full-size gradient
        # per step (O(L²) memory traffic); unbind's is one stack.
        for gates_t in gates_x.unbind(2):
            h, c = _members_step(gates_t, h, c, w_hh_t)
            outs.append(h)
        return torch.stack(outs, 2), (h, c)

    def _head(self, out: torch.Tensor) -> torch.Tensor:
        """The dense layer and the output layer on LSTM outputs ``[*R, ..., hid]``."""
        dense, head = self.dense, self.head
        z = _linear(out, self._engine(dense.weight), self._engine(dense.bias))
        z = ACTIVATIONS[self.activation](z)
        return _linear(z, self._engine(head.weight), self._engine(head.bias))

    def _lstm_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Checked and normalised sequences ``[*R, *B, L, N]``, ``[*R, *B, L, M]`` as the LSTM's
        input ``[*R, B, L, N + M]``."""
        self._members_first("obs", obs, 3)
        check_features("obs", obs, self.obs_dim, min_ndim=self._ndim(2))
        check_features("action", action, self.action_dim, min_ndim=self._ndim(2))
        if obs.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"obs {tuple(obs.shape)} and action {tuple(action.shape)} disagree on batch/time dims."
            )
        x = self.normalize_inputs(obs, action)
        return x.reshape(*self._lead, -1, x.shape[-2], x.shape[-1])

    def predict_delta(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Teacher-forced normalised Δs predictions for sequences ``[*R, *B, L, N]``, ``[*R, *B, L, M]``."""
        out, _ = self._lstm(self._lstm_inputs(obs, action))
        return self._head(out).reshape(obs.shape)

    def predict_window_deltas(
        self, obs: torch.Tensor, action: torch.Tensor, window: int
    ) -> torch.Tensor:
        """Normalised Δs predicted after every ``window``-step window of the sequences, each
        window read from a fresh LSTM state: ``[*R, *B, L, N]``, ``[*R, *B, L, M]`` →
        ``[*R, *B, L − window + 1, N]``.

        The same as :meth:`predict_delta` on a copy of each window, last step (a sliding-window
        score), without the copies: the input part of the gates is computed once per step and
        only each window's last output goes through the head.

        Examples:
            >>> models = LSTMWorldModel(6, 3, num_members=2, window=4)
            >>> models.predict_window_deltas(torch.randn(2, 5, 12, 6), torch.randn(2, 5, 12, 3), 4).shape
            torch.Size([2, 5, 9, 6])
        """
        check_int("window", window)
        x = self._lstm_inputs(obs, action)
        if obs.shape[-2] < window:
            raise ValueError(
                f"obs has shape {tuple(obs.shape)}; expected at least window={window} steps (dim -2)."
            )
        # The batched cell with a member dim (of one for a single model).
        weights = self._lstm_weights()
        if self.num_members is None:
            weights = tuple(w[None] for w in weights)
        if not self._lead:
            x = x[None]
        w_ih, w_hh, b_ih, b_hh = weights
        members, length, hid = x.shape[0], x.shape[-2], self.hidden_size
        windows = length - window + 1
        gates_x = _input_gates(x, w_ih, b_ih, b_hh).unfold(2, window, 1)  # [P, B, W, 4·hid, T]
        rows = gates_x.shape[1] * windows
        h = c = x.new_zeros(members, rows, hid)
        w_hh_t = w_hh.transpose(-1, -2)
        for t in range(window):
            h, c = _members_step(gates_x[..., t].reshape(members, rows, -1), h, c, w_hh_t)
        out = self._head(h if self._lead else h[0])
        return out.reshape(*obs.shape[:-2], windows, self.obs_dim)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action = tensordict.get(self.in_keys[0]), tensordict.get(self.in_keys[1])
        delta = self._denorm("delta", self.predict_delta(obs, action))
        tensordict.set(self.out_keys[0], obs + delta)
        return tensordict

    def warmup(
        self, context_obs: torch.Tensor, context_action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Run the LSTM over a real context ``[*R, *B, T, N]``, ``[*R, *B, T, M]``; return ``(h, c)`` ``[*R, *B, hidden]``."""
        self._members_first("context_obs", context_obs, 3)
        check_features("context_obs", context_obs, self.obs_dim, min_ndim=self._ndim(2))
        check_features("context_action", context_action, self.action_dim, min_ndim=self._ndim(2))
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
        _, (h, c) = self._lstm(x.reshape(*self._lead, -1, self.window, x.shape[-1]))
        return h.reshape(*batch, self.hidden_size), c.reshape(*batch, self.hidden_size)

    def _folded_weights(self) -> tuple[torch.Tensor, ...]:
        """Fold the normalisations into the weights so the rollout works in raw units
        (``[R, ...]`` each for R > 1 members; see ``fold_weights``)."""
        dense, head = self.dense, self.head
        raw = (*self._lstm_weights(), dense.weight, dense.bias, head.weight, head.bias)
        norms = tuple(self._engine(x) for x in self.norm_stats())
        return fold_weights(*(self._engine(w) for w in raw), norms)

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
            context_obs: real past states s_{t-T..t-1}, ``[*R, *B, T', N]`` with T' >= window.
            context_action: real past actions a_{t-T..t-1}, ``[*R, *B, T', M]``.
            observation: the current real state s_t, ``[*R, *B, N]``.
            actions: candidates a_{t..t+H-1}, ``[*R, *B, K, H, M]``.
            state: ``(h, c)`` from :meth:`warmup` on this context, to skip recomputing it
                (planners call ``imagine`` many times on one context).

        Returns:
            Predicted states s_{t+1..t+H}, ``[*R, *B, K, H, N]`` (differentiable w.r.t. ``actions``).
        """
        self._members_first("observation", observation, 2)
        check_features("observation", observation, self.obs_dim)
        check_features("actions", actions, self.action_dim, min_ndim=self._ndim(3))
        batch, hid, lead = observation.shape[:-1], self.hidden_size, self._lead
        if actions.shape[:-3] != batch:
            raise self._shape_error("actions", actions, f"K, H, {self.action_dim}", batch)
        check_finite("observation", observation)
        h, c = self.warmup(context_obs, context_action) if state is None else state
        k, horizon = actions.shape[-3], actions.shape[-2]

        def expand(x: torch.Tensor, size: int) -> torch.Tensor:  # each row once per candidate
            return x.reshape(*lead, -1, 1, size).expand(*lead, -1, k, -1).reshape(*lead, -1, size)

        s0, h, c = expand(observation, self.obs_dim), expand(h, hid), expand(c, hid)
        flat_actions = actions.reshape(*lead, -1, horizon, self.action_dim)
        states = self._rollout(s0, h, c, flat_actions)
        return states.reshape(*batch, k, horizon, self.obs_dim)

    def step(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """One-step prediction: s_{t+1} from s_t ``[*R, *B, N]``, a_t ``[*R, *B, M]`` and the LSTM state.

        Args:
            observation: s_t, ``[*R, *B, N]``.
            action: a_t, ``[*R, *B, M]``.
            state: ``(h, c)`` ``[*R, *B, hidden]`` from :meth:`warmup` or the previous step;
                zeros when None.

        Returns:
            ``(s_{t+1} [*R, *B, N], (h, c))``: feed both back for the next step (this runs the
            LSTM once per step; :meth:`rollout` does many steps at once).

        Examples:
            >>> model = LSTMWorldModel(6, 3)
            >>> s, state = model.step(torch.zeros(2, 6), torch.zeros(2, 3))
            >>> s, state = model.step(s, torch.ones(2, 3), state)
            >>> s.shape, state[0].shape
            (torch.Size([2, 6]), torch.Size([2, 32]))
        """
        self._members_first("observation", observation, 2)
        check_features("observation", observation, self.obs_dim)
        check_features("action", action, self.action_dim)
        if observation.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"observation {tuple(observation.shape)} and action {tuple(action.shape)} "
                "disagree on batch dims."
            )
        batch, hid, lead = observation.shape[:-1], self.hidden_size, self._lead
        x = self.normalize_inputs(observation, action).reshape(*lead, -1, 1, self.feature_dim)
        hx = None if state is None else tuple(s.reshape(*lead, -1, hid) for s in state)
        out, (h, c) = self._lstm(x, hx)
        delta = self._denorm("delta", self._head(out[..., 0, :]))
        return observation + delta.reshape(*batch, self.obs_dim), (
            h.reshape(*batch, hid),
            c.reshape(*batch, hid),
        )

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
            observation: s_t, ``[*R, *B, N]``.
            actions: a_{t..t+H-1}, ``[*R, *B, H, M]``.
            state: ``(h, c)`` ``[*R, *B, hidden]`` (from :meth:`warmup`).

        Keyword Args:
            recorded: record every op with autograd (the slow reference) instead of the
                default: an in-place loop when nothing needs a gradient, else one autograd
                node with a hand-written backward through time, bitwise the reference's
                states and gradients.

        Returns:
            s_{t+1..t+H}, ``[*R, *B, H, N]``, differentiable w.r.t. the actions, the start state
            and the model's parameters.

        Examples:
            >>> model = LSTMWorldModel(6, 3, window=4)
            >>> state = model.warmup(torch.zeros(2, 4, 6), torch.zeros(2, 4, 3))
            >>> model.rollout(torch.zeros(2, 6), torch.rand(2, 20, 3), state).shape
            torch.Size([2, 20, 6])
        """
        self._members_first("observation", observation, 2)
        check_features("observation", observation, self.obs_dim)
        check_features("actions", actions, self.action_dim, min_ndim=self._ndim(2))
        batch, hid, lead = observation.shape[:-1], self.hidden_size, self._lead
        if actions.shape[:-2] != batch:
            raise self._shape_error("actions", actions, f"H, {self.action_dim}", batch)
        horizon = actions.shape[-2]
        s0 = observation.reshape(*lead, -1, self.obs_dim)
        h, c = (x.reshape(*lead, -1, hid) for x in state)
        flat_actions = actions.reshape(*lead, -1, horizon, self.action_dim)
        states = self._rollout(s0, h, c, flat_actions, recorded)
        return states.reshape(*batch, horizon, self.obs_dim)

    def _rollout(
        self,
        s0: torch.Tensor,
        h: torch.Tensor,
        c: torch.Tensor,
        actions: torch.Tensor,
        recorded: bool = False,
    ) -> torch.Tensor:
        """``[*R, B, N]``, ``[*R, B, hid]`` x2, ``[*R, B, H, M]`` → ``[*R, B, H, N]``: the
        reference when ``recorded``, else the fastest path for the call (``_lstm_rollout.rollout``)."""
        weights = self._folded_weights()
        return rollout(s0, h, c, actions, self.activation, *weights, reference=recorded)

    def prediction_loss(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        mode: str,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Each member's ``WorldModelPredictionLoss`` on its sequences ``[*R, B, L, ...]`` → ``[*R]``.

        ``mask`` ``[*R, B, L]`` is True at each row's real steps, then False at its padding (the
        layout of TorchRL's ``SliceSampler(strict_length=False, pad_output=True)``, whose short
        slices are whole episodes): only real steps count. ``"one_step"``: the LSTM is causal,
        so padding after the real steps changes nothing. ``"multi_step"``: a row with at most
        ``window`` real steps is started at rest
        (``torchrl_recon.modules.padding.start_at_rest``: the slots before the episode hold
        its first observation and the zero action, as ``MPCPolicy(warmup="plan")`` plans an
        episode's start), and the error counts at the real steps after the warm-up. No padded
        value is read into a counted error.

        Examples:
            >>> model = LSTMWorldModel(3, 1, window=4)
            >>> obs, act, nxt = torch.randn(2, 6, 3), torch.randn(2, 6, 1), torch.randn(2, 6, 3)
            >>> mask = torch.tensor([[True] * 6, [True] * 2 + [False] * 4])
            >>> loss = model.prediction_loss(obs, act, nxt, "multi_step", mask)
            >>> nxt[1, 2:] = 1e3  # padding
            >>> bool(model.prediction_loss(obs, act, nxt, "multi_step", mask) == loss)
            True
        """
        if mask is not None:
            mask = check_prefix_mask(mask, obs.shape[:-1])
        if mode == "one_step":
            pred = self.predict_delta(obs, action)
            err = pred - self._norm("delta", next_obs - obs)
        elif mode == "multi_step":
            w = self.window
            if obs.shape[-2] <= w:
                raise ValueError(
                    f"multi_step loss needs sequences longer than window={w}, got length {obs.shape[-2]}."
                )
            if mask is not None:
                mask, (obs, action, next_obs) = start_at_rest(
                    mask, w + 1, obs, action, next_obs, rest={1: 0.0}
                )
                mask = mask[..., w:]
            pred = self.imagine(
                obs[..., :w, :], action[..., :w, :], obs[..., w, :], action[..., None, w:, :]
            )[..., 0, :, :]
            err = (pred - next_obs[..., w:, :]) / self._stat("obs", "scale", pred.dim())
        else:
            raise ValueError(f"mode must be 'multi_step' or 'one_step', got {mode!r}.")
        members = () if self.num_members is None else (self.num_members,)
        if mask is None:
            return err.pow(2).reshape(*members, -1).mean(-1)
        err = torch.where(mask[..., None], err, err.new_zeros(()))
        return masked_mean(err.pow(2), mask[..., None], err.dim() - len(members))


WorldModelPopulation = LSTMWorldModel
"""The former population class: ``LSTMWorldModel`` with ``num_members`` (same arguments)."""


def _linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``nn.Linear`` for 2-D weights; per member for ``[P, out, in]`` ones and ``x`` ``[P, *B, in]``."""
    if weight.dim() == 2:
        return F.linear(x, weight, bias)
    flat = x.reshape(x.shape[0], -1, x.shape[-1])
    out = _addmm(bias, flat, weight.transpose(-1, -2))
    return out.reshape(*x.shape[:-1], weight.shape[-2])


def _input_gates(
    x: torch.Tensor, w_ih: torch.Tensor, b_ih: torch.Tensor, b_hh: torch.Tensor
) -> torch.Tensor:
    """Each member's input part of the LSTM gates, ``x`` ``[P, B, L, F]`` → ``[P, B, L, 4·hid]``."""
    members, rows, length, features = x.shape
    gates = _addmm(b_ih + b_hh, x.reshape(members, -1, features), w_ih.transpose(-1, -2))
    return gates.reshape(members, rows, length, -1)


def _members_step(
    gates_x: torch.Tensor, h: torch.Tensor, c: torch.Tensor, w_hh_t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One teacher-forced LSTM step of every member, from the input part of the gates
    ``[P, B, 4·hid]`` and the state ``[P, B, hid]`` (:func:`lstm_cell`, tanh as
    :func:`sigmoid_tanh`)."""
    h, c, _ = lstm_cell(_addmm_step(gates_x, h, w_hh_t), c, tanh=sigmoid_tanh)
    return h, c
