"""A population of LSTM world models whose disagreement is the uncertainty (PETS style)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey

from torchrl_recon.estimators._one_step import blocked_scores, population_variance
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator, window_view
from torchrl_recon.modules.checks import check_finite, check_int
from torchrl_recon.modules.normalization import Normalizer
from torchrl_recon.modules.world_model import LSTMWorldModel


class WorldModelEnsembleUncertainty(UncertaintyEstimator):
    """Disagreement of E LSTM world models, the world model's own uncertainty.

    The members are world models of the paper's kind (:class:`~torchrl_recon.modules.LSTMWorldModel`,
    held as one with ``num_members=E``). Each reads a window of T
    (s, a) pairs as the planner's world model reads its context, from a fresh LSTM state, and
    predicts the state change after the window's last pair. The u of the window is the variance
    of those predictions across members, in units of the standardised state (σ_s² of the
    fitted data), averaged over the N state features:

        u = (1/N) Σ_n Var_e[ Δ̂_e,n / σ_s,n ]

    Unlike the other estimators it is not a separate kind of network: its members can be the
    world models fitted for the task (:meth:`from_world_models`, e.g. a population fit's
    members), or it trains its own with :func:`~torchrl_recon.fitting.fit_uncertainty`: each
    member fits the one-step change after every T-window of the batch's sequences, on its own
    bootstrap resample of those windows (as PETS' ensemble does). Scoring costs T LSTM steps per
    window and member (the input projection once per step, the head once per window), several
    times the autoencoder's cost; it runs without autograd in cache-sized row blocks.

    Args:
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        window: T, the number of steps per window (the members' context).
        num_members: E, the number of world models (at least 2).
        hidden_size, dense_size, activation: each member's LSTM width, dense width and activation.
        obs_key, action_key, out_key: TensorDict keys used by ``forward``.

    Examples:
        >>> est = WorldModelEnsembleUncertainty(6, 3, window=10, num_members=4)
        >>> est.score(torch.randn(4, 30, 6), torch.randn(4, 30, 3)).shape
        torch.Size([4, 21])
        >>> est.loss(torch.randn(8, 12, 6), torch.randn(8, 12, 3)).shape
        torch.Size([])
    """

    window_local = True  # u of a window depends on that window alone

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        *,
        window: int = 10,
        num_members: int = 5,
        hidden_size: int = 32,
        dense_size: int = 32,
        activation: str = "relu",
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = "uncertainty",
    ) -> None:
        super().__init__(
            obs_dim, action_dim, window, obs_key=obs_key, action_key=action_key, out_key=out_key
        )
        check_int("num_members", num_members, 2)
        self.num_members = num_members
        self.hidden_size, self.dense_size, self.activation = hidden_size, dense_size, activation
        self.members = LSTMWorldModel(
            obs_dim,
            action_dim,
            num_members=num_members,
            window=window,
            hidden_size=hidden_size,
            dense_size=dense_size,
            activation=activation,
        )
        self.input_norm = Normalizer(self.feature_dim)

    @classmethod
    def from_world_models(
        cls, models: Sequence[LSTMWorldModel], *, window: int | None = None
    ) -> WorldModelEnsembleUncertainty:
        """The estimator whose members are copies of fitted world models (all of one config).

        u is in units of the first model's state standard deviation (its ``obs_norm``).

        Examples:
            >>> models = [LSTMWorldModel(6, 3, window=5) for _ in range(3)]
            >>> est = WorldModelEnsembleUncertainty.from_world_models(models)
            >>> est.num_members, est.window
            (3, 5)
        """
        models = list(models)
        if len(models) < 2:
            raise ValueError(f"from_world_models needs at least 2 world models, got {len(models)}.")
        first = models[0]
        with torch.device("meta"):
            est = cls(
                first.obs_dim,
                first.action_dim,
                window=window or first.window,
                num_members=len(models),
                hidden_size=first.hidden_size,
                dense_size=first.dense_size,
                activation=first.activation,
            )
        device = next(first.parameters()).device
        est = est.to_empty(device=device)
        est.members = LSTMWorldModel.from_members(models)
        with torch.no_grad():
            loc = torch.cat([first.obs_norm.loc, first.action_norm.loc])
            scale = torch.cat([first.obs_norm.scale, first.action_norm.scale])
            est.input_norm.loc.copy_(loc)
            est.input_norm.scale.copy_(scale)
            est.input_norm.fitted.fill_(True)
        return est

    def config(self) -> dict:
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "window": self.window,
            "num_members": self.num_members,
            "hidden_size": self.hidden_size,
            "dense_size": self.dense_size,
            "activation": self.activation,
        }

    @torch.no_grad()
    def fit_normalization(self, obs: torch.Tensor, action: torch.Tensor) -> None:
        """Fit the input statistics and give every member the same ones; the members predict
        the state change in units of σ_s (their ``delta`` statistics are 0 and σ_s)."""
        super().fit_normalization(obs, action)
        n, members = self.obs_dim, self.members
        loc, scale = self.input_norm.loc, self.input_norm.scale
        for which, mean, std in (
            ("obs", loc[:n], scale[:n]),
            ("action", loc[n:], scale[n:]),
            ("delta", torch.zeros_like(loc[:n]), scale[:n]),
        ):
            norm = getattr(members, f"{which}_norm")
            norm.loc.copy_(mean.expand(self.num_members, -1))
            norm.scale.copy_(std.expand(self.num_members, -1))
            norm.fitted.fill_(True)

    def _windows(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every T-window of raw sequences ``[R, L, N + M]`` as each member's input: obs
        ``[E, R·W, T, N]`` and actions ``[E, R·W, T, M]`` (expanded, not copied)."""
        windows = window_view(x, self.window).reshape(-1, self.window, self.feature_dim)
        windows = windows.expand(self.num_members, *windows.shape)
        return windows[..., : self.obs_dim], windows[..., self.obs_dim :]

    def _standardised_change(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each member's predicted change after each window ``[E, R·W, T, *]``, in units of
        σ_s: ``[E, R·W, N]``."""
        return self._in_state_units(self.members.predict_delta(obs, action)[..., -1, :])

    def _in_state_units(self, pred: torch.Tensor) -> torch.Tensor:
        """Members' normalised changes ``[E, P, N]`` in units of σ_s."""
        members, sigma = self.members, self.input_norm.scale[: self.obs_dim]
        scale = members.delta_norm.scale[:, None] / sigma
        return pred * scale + members.delta_norm.loc[:, None] / sigma

    def score_sequence(self, x: torch.Tensor) -> torch.Tensor:
        needs_grad = torch.is_grad_enabled() and (
            x.requires_grad or self.members.lstm.weight_ih_l0.requires_grad
        )
        return blocked_scores(self._score_rows, x, needs_grad)

    def _score_rows(self, x: torch.Tensor) -> torch.Tensor:
        rows, length, _ = x.shape
        n, members = self.obs_dim, self.num_members
        x = x.expand(members, *x.shape)
        pred = self.members.predict_window_deltas(x[..., :n], x[..., n:], self.window)
        pred = self._in_state_units(pred.reshape(members, -1, n))
        return population_variance(pred).mean(-1).view(rows, length - self.window + 1)

    def loss(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Mean over members of their one-step error after each T-window of the sequences
        ``[*B, L, N]``, ``[*B, L, M]`` (L > T), each member on its own bootstrap resample of the
        windows (``torch.randint`` from the global RNG of the inputs' device)."""
        self._check_pair(obs, action)
        check_finite("obs", obs.detach())
        check_finite("action", action.detach())
        length = obs.shape[-2]
        if length <= self.window:
            raise ValueError(
                f"obs has shape {tuple(obs.shape)}; the loss needs sequences longer than "
                f"window={self.window} (a window and the step after it)."
            )
        x = torch.cat([obs, action], -1).reshape(-1, length, self.feature_dim)
        w_obs, w_act = self._windows(x[:, :-1])
        n = self.obs_dim
        change = x[:, self.window :, :n] - x[:, self.window - 1 : -1, :n]
        target = (change / self.input_norm.scale[:n]).reshape(-1, n)
        count = target.shape[0]
        index = torch.randint(count, (self.num_members, count), device=obs.device)
        members = torch.arange(self.num_members, device=obs.device)[:, None]
        pred = self._standardised_change(w_obs[members, index], w_act[members, index])
        return (pred - target[index]).pow(2).mean()
