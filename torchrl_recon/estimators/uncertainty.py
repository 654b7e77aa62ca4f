"""The interface every uncertainty estimator implements: score T-step windows of (s, a)."""

from __future__ import annotations

import abc
from typing import ClassVar

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_recon.modules.checks import (
    check_features,
    check_finite,
    check_int,
    check_window_pair,
)
from torchrl_recon.modules.padding import masked_mean, windows_at_rest


def window_view(x: torch.Tensor, window: int) -> torch.Tensor:
    """Every ``window``-step window of contiguous sequences ``[R, L, D]`` as a view ``[R, L - T + 1, T·D]``.

    Each window of T rows is one contiguous run of T·D values, so no data is copied (a
    non-contiguous ``x`` is made contiguous first; the strides below assume it).

    Examples:
        >>> window_view(torch.arange(8.0).view(1, 4, 2), 3).tolist()
        [[[0.0, 1.0, 2.0, 3.0, 4.0, 5.0], [2.0, 3.0, 4.0, 5.0, 6.0, 7.0]]]
    """
    x = x.contiguous()
    rows, length, dim = x.shape
    return x.as_strided((rows, length - window + 1, window * dim), (length * dim, dim, 1))


class UncertaintyEstimator(TensorDictModuleBase, abc.ABC):
    """Scores how unfamiliar windows of ``window`` consecutive (s, a) pairs are.

    Model-agnostic: an estimator reads only states and actions, never a world model.
    Subclasses implement :meth:`config` and :meth:`score_sequence` (and :meth:`fit_normalization`
    unless they keep their statistics in an ``input_norm`` Normalizer); everything else
    (trajectory scoring, TensorDict ``forward``) is shared.

    ``forward`` reads ``obs_key`` ``[*B, L, N]`` and ``action_key`` ``[*B, L, M]`` and writes
    ``out_key`` ``[*B, L]``: the u of the window *ending* at each step; the first
    ``window - 1`` steps have no full window and hold NaN.

    ``window_local`` (class attribute) says that a window's u depends on that window alone, with
    no random draw per call, so a planner may score its candidates in blocks of rows and get
    the same u (:class:`~torchrl_recon.planners.PlanningModel`'s ``block_rows``). It is False
    unless a subclass sets it (MC dropout draws its masks per call and leaves it False).
    """

    window_local: ClassVar[bool] = False

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        window: int,
        *,
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = "uncertainty",
    ) -> None:
        super().__init__()
        for name, value in (("obs_dim", obs_dim), ("action_dim", action_dim), ("window", window)):
            check_int(name, value)
        self.obs_dim, self.action_dim, self.window = obs_dim, action_dim, window
        self.in_keys = [obs_key, action_key]
        self.out_keys = [out_key]

    @property
    def feature_dim(self) -> int:
        """Features per step, N + M."""
        return self.obs_dim + self.action_dim

    @abc.abstractmethod
    def config(self) -> dict:
        """Constructor arguments, stored in checkpoints and checked on load."""

    def fit_normalization(self, obs: torch.Tensor, action: torch.Tensor) -> None:
        """Fit input statistics from real data ``[..., N]``, ``[..., M]``.

        The default fits ``self.input_norm``, a :class:`~torchrl_recon.modules.Normalizer`
        over the N + M features, which every built-in estimator has; an estimator without one
        overrides this. NaN or inf in ``obs`` or ``action`` is refused (``ValueError`` naming
        the argument and the first bad index).
        """
        norm = getattr(self, "input_norm", None)
        if norm is None:
            raise NotImplementedError(
                f"{type(self).__name__} has no input_norm; override fit_normalization."
            )
        check_features("obs", obs, self.obs_dim)
        check_features("action", action, self.action_dim)
        if obs.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"obs {tuple(obs.shape)} and action {tuple(action.shape)} disagree on batch dims; "
                "expected one action per observation."
            )
        check_finite("obs", obs)
        check_finite("action", action)
        norm.fit(torch.cat([obs, action], -1))

    @abc.abstractmethod
    def score_sequence(self, x: torch.Tensor) -> torch.Tensor:
        """Score every T-window of raw (s, a) sequences ``x`` ``[R, L, N + M]`` → ``[R, L - T + 1]``."""

    def loss(
        self, obs: torch.Tensor, action: torch.Tensor, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Training loss on real sequences ``[*B, L, N]``, ``[*B, L, M]`` (default: mean u, paper eq. 1).

        With ``mask`` ``[*B, L]`` (True at real steps, then padding: slices of episodes shorter
        than L) the mean runs over the windows that end at a real step, short episodes started
        at rest (``torchrl_recon.modules.padding.windows_at_rest``); padding never counts.
        """
        if mask is None:
            return self.score(obs, action).mean()
        obs, action, valid = windows_at_rest(obs, action, mask, self.window)
        return masked_mean(self.score(obs, action), valid, valid.dim())

    def _check_pair(self, obs: torch.Tensor, action: torch.Tensor) -> None:
        check_window_pair(
            obs, action, obs_dim=self.obs_dim, action_dim=self.action_dim, window=self.window
        )

    def score(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """u for every window of trajectories ``[*B, L, N]``, ``[*B, L, M]`` → ``[*B, L - T + 1]``.

        One batched call over all windows; differentiable w.r.t. both inputs.
        """
        self._check_pair(obs, action)
        check_finite("obs", obs.detach())
        check_finite("action", action.detach())
        batch, length = obs.shape[:-2], obs.shape[-2]
        x = torch.cat([obs, action], -1).reshape(-1, length, self.feature_dim)
        return checked_scores(self, x).reshape(*batch, length - self.window + 1)

    def score_windows(self, windows: torch.Tensor) -> torch.Tensor:
        """u of single windows ``[*B, T, N + M]`` → ``[*B]``."""
        check_features("windows", windows, self.feature_dim, min_ndim=2)
        if windows.shape[-2] != self.window:
            raise ValueError(
                f"windows has shape {tuple(windows.shape)}; expected [*B, {self.window}, {self.feature_dim}]."
            )
        batch = windows.shape[:-2]
        return checked_scores(self, windows.reshape(-1, self.window, self.feature_dim)).reshape(
            batch
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action = tensordict.get(self.in_keys[0]), tensordict.get(self.in_keys[1])
        u = self.score(obs, action)
        pad = u.new_full((*u.shape[:-1], self.window - 1), float("nan"))
        tensordict.set(self.out_keys[0], torch.cat([pad, u], -1))
        return tensordict


def checked_scores(estimator: UncertaintyEstimator, x: torch.Tensor) -> torch.Tensor:
    """``estimator.score_sequence(x)`` with its shape checked, ``[R, L - T + 1]``: what the
    library calls, so an estimator of your own that returns another shape is one clear error,
    not a failed (or silently wrong) reshape further on.

    Examples:
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> checked_scores(ReconstructionUncertainty(2, 1, window=3), torch.zeros(4, 5, 3)).shape
        torch.Size([4, 3])
    """
    u = estimator.score_sequence(x)
    expected = (x.shape[0], x.shape[1] - estimator.window + 1)
    if not isinstance(u, torch.Tensor) or tuple(u.shape) != expected:
        got = tuple(u.shape) if isinstance(u, torch.Tensor) else type(u).__name__
        raise ValueError(
            f"{type(estimator).__name__}.score_sequence returned {got} for sequences "
            f"{tuple(x.shape)}; expected {expected}: one u per window of {estimator.window} steps."
        )
    return u
