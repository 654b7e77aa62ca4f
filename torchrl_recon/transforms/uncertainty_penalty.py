"""The paper's uncertainty as a TorchRL transform: u of each step, and the reward α·r − β·u."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from torchrl.data import Composite, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.transforms import Transform

from torchrl_recon.data.buffers import TRAJ_KEY
from torchrl_recon.devices import module_dtype
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator, checked_scores
from torchrl_recon.modules.checks import check_real
from torchrl_recon.modules.fitted import ESTIMATOR, FittedCheck
from torchrl_recon.planners.beta import relative_beta
from torchrl_recon.planners.objective import UncertaintyBand

__all__ = ["UncertaintyPenalty"]


class UncertaintyPenalty(Transform):
    """Score each step's (s, a) window with an uncertainty estimator, and penalise the reward.

    Appended to any TorchRL env, a model-based one above all (TorchRL's ``WorldModelEnv`` or
    ``DreamerEnv``, :class:`~torchrl_recon.planners.model_env.WorldModelPlanningEnv`, a real env
    to log u), the transform keeps the last ``T − 1`` (state, action) pairs of each trajectory in the
    TensorDict (``history_key``, ``[*B, T − 1, N + M]``, in the observation and state specs as a
    ``TensorDictPrimer``'s entry). At each step it scores the window of those pairs followed by
    (s_t, a_t), the state the action is taken from and the action (as
    :class:`~torchrl_recon.planners.PlanningModel` scores u_k), writes u under
    ``("next", uncertainty_key)`` (a reward-spec entry, as TorchRL's ``RNDTransform`` writes its
    bonus) and rolls the history on. Every env dim is one batch dim of a single
    ``score_windows`` call, on the env's device; any
    :class:`~torchrl_recon.estimators.UncertaintyEstimator` works (the library's five, or yours).

    Where the reward is asked for (``alpha != 1``, ``beta != 0`` or a ``band``), the step's
    reward becomes ``α·r − β·u`` (paper eq. 3; eq. 4 is ``alpha=0, beta<0``), so TorchRL's
    ``CEMPlanner`` and ``MPPIPlanner`` plan with u. β is absolute; a β in cost units (the
    library's *relative* β) comes from :meth:`from_relative_beta`. A ``band`` on Σu is an
    absolute :class:`~torchrl_recon.planners.UncertaintyBand` only (its quantile and mean-ratio
    kinds need the whole batch of candidates, which one env step does not see): Σu is carried
    too (``sum_key``), and each step's reward is lowered by ``band_weight`` times the growth of
    Σu's distance outside the band, so a trajectory's summed reward is ``Σ(α·r − β·u) −
    band_weight·distance`` (up to a constant): CEM's ranking, as a penalty rather than the
    library's feasible-first order.

    At reset (where the env resets, every env or those of ``"_reset"``), the history starts at
    rest: the first observation and the zero action, the convention the estimators train on
    for an episode's start. Under a model-based env, a history the caller passes in the reset
    tensordict (an imagined rollout's start, e.g. :meth:`history` of a real context) is kept.

    Args:
        estimator: the (fitted) estimator; its window T sets the history's length.

    Keyword Args:
        alpha: weight of the env's reward.
        beta: weight of u (negative to seek uncertainty).
        band: an absolute :class:`~torchrl_recon.planners.UncertaintyBand` on Σu, or None.
        band_weight: reward per unit of Σu outside the band.
        obs_key: the state the estimator reads (the observation, or a decoded one).
        action_key: the action.
        reward_key: the reward to penalise.
        uncertainty_key: where u is written, under ``"next"``.
        history_key: the last ``T − 1`` pairs.
        sum_key: Σu since reset (with a band only).

    Examples:
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> estimator = ReconstructionUncertainty(3, 1, window=4)
        >>> estimator.fit_normalization(torch.randn(64, 3), torch.rand(64, 1) * 4 - 2)
        >>> env = TransformedEnv(GymEnv("Pendulum-v1"), UncertaintyPenalty(estimator, beta=0.5))
        >>> rollout = env.rollout(5)
        >>> rollout["next", "uncertainty"].shape, rollout["uncertainty_history"].shape
        (torch.Size([5, 1]), torch.Size([5, 3, 4]))
    """

    def __init__(
        self,
        estimator: UncertaintyEstimator,
        *,
        alpha: float = 1.0,
        beta: float = 0.0,
        band: UncertaintyBand | None = None,
        band_weight: float = 100.0,
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        reward_key: NestedKey = "reward",
        uncertainty_key: NestedKey = "uncertainty",
        history_key: NestedKey = "uncertainty_history",
        sum_key: NestedKey = "uncertainty_sum",
    ) -> None:
        if not isinstance(estimator, UncertaintyEstimator):
            raise TypeError(
                f"estimator must be an UncertaintyEstimator, got {type(estimator).__name__}."
            )
        check_real("alpha", alpha)
        check_real("beta", beta)
        check_real("band_weight", band_weight, minimum=0)
        if band is not None and not isinstance(band, UncertaintyBand):
            raise TypeError(f"band must be an UncertaintyBand or None, got {band!r}.")
        if band is not None and band.kind != "absolute":
            raise ValueError(
                f"UncertaintyPenalty takes an absolute band only, got kind={band.kind!r}: a "
                "relative band is resolved over a batch of candidates, which one env step does "
                "not see; give absolute values of Σu, or plan with the library's planners "
                "(PlanningModel.from_torchrl)."
            )
        self.obs_key, self.action_key = unravel_key(obs_key), unravel_key(action_key)
        self.reward_key, self.uncertainty_key = (
            unravel_key(reward_key),
            unravel_key(uncertainty_key),
        )
        self.history_key, self.sum_key = unravel_key(history_key), unravel_key(sum_key)
        self.alpha, self.beta, self.band, self.band_weight = alpha, beta, band, band_weight
        self.penalize = alpha != 1.0 or beta != 0.0 or band is not None
        state = [self.history_key] if estimator.window > 1 else []
        if band is not None:
            state.append(self.sum_key)
        out_keys = [self.uncertainty_key, *state] + ([self.reward_key] if self.penalize else [])
        in_keys = [self.obs_key, self.action_key, *state] + (
            [self.reward_key] if self.penalize else []
        )
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.estimator = estimator
        self._state_keys = state
        self._fitted = FittedCheck(ESTIMATOR)

    @classmethod
    def from_relative_beta(
        cls,
        estimator: UncertaintyEstimator,
        beta: float,
        data: TensorDictBase,
        *,
        sequence_length: int | None = None,
        traj_key: NestedKey = TRAJ_KEY,
        **kwargs,
    ) -> UncertaintyPenalty:
        """The transform with β given in cost units, measured on ``data``
        (:func:`~torchrl_recon.planners.relative_beta`: ``beta=1.0`` makes a window of average
        u cost as much as an average step of ``data``'s reward); ``kwargs`` as the constructor's.

        Examples:
            >>> from tensordict import TensorDict
            >>> from torchrl_recon.modules import ReconstructionUncertainty
            >>> estimator = ReconstructionUncertainty(3, 1, window=4)
            >>> data = TensorDict({"observation": torch.randn(40, 3), "action": torch.rand(40, 1),
            ...                    ("next", "reward"): -torch.full((40, 1), 6.0),
            ...                    ("collector", "traj_ids"): torch.arange(40) // 20}, [40])
            >>> estimator.fit_normalization(data["observation"], data["action"])
            >>> penalty = UncertaintyPenalty.from_relative_beta(estimator, 0.5, data)
            >>> penalty.beta > 0
            True
        """
        absolute = relative_beta(
            beta, data, estimator, sequence_length=sequence_length, traj_key=traj_key
        )
        return cls(estimator, beta=absolute, **kwargs)

    @property
    def window(self) -> int:
        """The estimator's window T."""
        return self.estimator.window

    def history(self, context_obs: torch.Tensor, context_action: torch.Tensor) -> torch.Tensor:
        """The history entry for a start after a real context ``[*B, L, N]``, ``[*B, L, M]``
        (L ≥ T − 1): its last ``T − 1`` pairs, ``[*B, T − 1, N + M]``. Put it in the tensordict
        an imagined rollout starts from (``td[penalty.history_key] = penalty.history(...)``),
        so that u's first windows reach into the real context, as the library's planners do.

        Examples:
            >>> from torchrl_recon.modules import ReconstructionUncertainty
            >>> penalty = UncertaintyPenalty(ReconstructionUncertainty(3, 1, window=4))
            >>> penalty.history(torch.zeros(2, 10, 3), torch.zeros(2, 10, 1)).shape
            torch.Size([2, 3, 4])
        """
        est, past = self.estimator, self.window - 1
        if context_obs.shape[-1] != est.obs_dim or context_action.shape[-1] != est.action_dim:
            raise ValueError(
                f"context_obs {tuple(context_obs.shape)} and context_action "
                f"{tuple(context_action.shape)} must end in the estimator's sizes "
                f"({est.obs_dim} and {est.action_dim})."
            )
        if context_obs.ndim < 2 or context_obs.shape[:-1] != context_action.shape[:-1]:
            raise ValueError(
                f"context_obs {tuple(context_obs.shape)} and context_action "
                f"{tuple(context_action.shape)} must be [*B, L, N] and [*B, L, M] with the same "
                "batch and time dims."
            )
        if context_obs.shape[-2] < past:
            raise ValueError(
                f"the context has {context_obs.shape[-2]} steps; the history needs the last "
                f"{past} (the estimator's window {self.window} - 1)."
            )
        pairs = torch.cat([context_obs, context_action], -1)
        return pairs[..., pairs.shape[-2] - past :, :]

    def _at_rest(self, obs: torch.Tensor) -> torch.Tensor:
        """A history at rest: ``obs`` ``[*B, N]`` and the zero action, T − 1 times."""
        pair = torch.cat([obs, obs.new_zeros(*obs.shape[:-1], self.estimator.action_dim)], -1)
        return pair.unsqueeze(-2).expand(*pair.shape[:-1], self.window - 1, pair.shape[-1])

    # -- specs ---------------------------------------------------------------------------

    def _state_specs(self, spec: Composite) -> Composite:
        """``spec`` with the history (and Σu) entries, on its batch shape."""
        obs_spec = spec.get(self.obs_key, None)
        dtype = module_dtype(self.estimator) if obs_spec is None else obs_spec.dtype
        device = spec.device if obs_spec is None else obs_spec.device
        batch = spec.shape
        if self.window > 1:
            shape = (*batch, self.window - 1, self.estimator.feature_dim)
            spec[self.history_key] = Unbounded(shape, device=device, dtype=dtype)
        if self.band is not None:
            spec[self.sum_key] = Unbounded((*batch, 1), device=device, dtype=dtype)
        return spec

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        if self.obs_key not in observation_spec.keys(True, True):
            raise KeyError(
                f"UncertaintyPenalty reads the state at {self.obs_key!r}, which the env's "
                f"observation spec does not have (it has {list(observation_spec.keys(True, True))}); "
                "pass obs_key= (e.g. a decoded observation's key)."
            )
        return self._state_specs(observation_spec)

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        input_spec = input_spec.clone()
        state = input_spec.get("full_state_spec", None)
        if state is None:
            state = Composite(shape=input_spec.shape, device=input_spec.device)
        input_spec["full_state_spec"] = self._state_specs(state)
        return input_spec

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        reference = reward_spec.get(self.reward_key, None)
        shape = (*reward_spec.shape, 1) if reference is None else reference.shape
        device = reward_spec.device if reference is None else reference.device
        reward_spec[self.uncertainty_key] = Unbounded(shape, device=device, dtype=torch.float32)
        return reward_spec

    # -- env hooks -----------------------------------------------------------------------

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._fitted(self.estimator)
        obs, action = tensordict.get(self.obs_key), tensordict.get(self.action_key)
        pair = torch.cat([obs, action.to(obs.dtype)], -1).unsqueeze(-2)
        if self.window > 1:
            history = tensordict.get(self.history_key, None)
            if history is None:
                raise KeyError(
                    f"the tensordict has no {self.history_key!r} (the last {self.window - 1} "
                    "(s, a) pairs the uncertainty window needs); start from env.reset(td), "
                    "which primes it, or set it with UncertaintyPenalty.history(context_obs, "
                    "context_action)."
                )
            window = torch.cat([history, pair], -2)
            next_tensordict.set(self.history_key, window[..., 1:, :])
        else:
            window = pair
        u = self.estimator.score_windows(window).unsqueeze(-1)  # [*B, 1]
        next_tensordict.set(self.uncertainty_key, u)
        if self.penalize:
            reward = next_tensordict.get(self.reward_key)
            u_r = u.reshape(reward.shape).to(reward.dtype)
            new = self.alpha * reward - self.beta * u_r
            if self.band is not None:
                before = tensordict.get(self.sum_key)
                after = before + u
                next_tensordict.set(self.sum_key, after)
                growth = self._distance(after) - self._distance(before)
                new = new - self.band_weight * growth.reshape(reward.shape).to(reward.dtype)
            next_tensordict.set(self.reward_key, new)
        return next_tensordict

    def _distance(self, total: torch.Tensor) -> torch.Tensor:
        """How far Σu lies outside the band (0 inside)."""
        out = torch.zeros_like(total)
        if self.band.low is not None:
            out = out + (self.band.low - total).clamp_min(0)
        if self.band.high is not None:
            out = out + (total - self.band.high).clamp_min(0)
        return out

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        if not self._state_keys:
            return tensordict_reset
        self._fitted(self.estimator)
        reset_key = self.parent.reset_keys[0] if self.parent is not None else "_reset"
        mask = None if tensordict is None else tensordict.get(reset_key, None)
        batch = tensordict_reset.batch_size
        fresh = {}
        if self.window > 1:
            fresh[self.history_key] = self._at_rest(tensordict_reset.get(self.obs_key))
        if self.band is not None:
            fresh[self.sum_key] = tensordict_reset.get(self.obs_key).new_zeros(*batch, 1)
        model_based = self.parent is not None and isinstance(
            self.parent.base_env, ModelBasedEnvBase
        )
        for key, value in fresh.items():
            given = None if tensordict is None else tensordict.get(key, None)
            if given is not None and mask is None and model_based and key == self.history_key:
                value = given  # an imagined rollout's start, as the caller gave it
            elif given is not None and mask is not None:  # partial reset: the others go on
                keep = mask.reshape(*mask.shape, *([1] * (value.ndim - mask.ndim)))
                value = torch.where(keep, value, given)
            tensordict_reset.set(key, value.contiguous() if value.ndim else value)
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """u (and the penalised reward) of every step of trajectories ``[*B, L]`` (time last, as
        ``env.rollout`` and a ``SliceSampler`` slice reshaped to ``[B, L]`` give), each row one
        trajectory: the history before its first step is the one it holds
        (``history_key`` at step 0), else at rest. All windows are scored in one call.

        Examples:
            >>> from tensordict import TensorDict
            >>> from torchrl_recon.modules import ReconstructionUncertainty
            >>> estimator = ReconstructionUncertainty(3, 1, window=4)
            >>> estimator.fit_normalization(torch.randn(64, 3), torch.randn(64, 1))
            >>> td = TensorDict({"observation": torch.randn(2, 6, 3), "action": torch.randn(2, 6, 1),
            ...                  ("next", "reward"): torch.zeros(2, 6, 1)}, [2, 6])
            >>> UncertaintyPenalty(estimator, beta=1.0)(td)["next", "uncertainty"].shape
            torch.Size([2, 6, 1])
        """
        self._fitted(self.estimator)
        if tensordict.batch_dims < 1:
            raise ValueError(
                "UncertaintyPenalty.forward scores trajectories [*B, L] (time last); got a "
                "tensordict without batch dims."
            )
        obs, action = tensordict.get(self.obs_key), tensordict.get(self.action_key)
        pairs = torch.cat([obs, action.to(obs.dtype)], -1)  # [*B, L, F]
        *batch, length, features = pairs.shape
        if self.window > 1:
            first = tensordict[..., 0]
            history = first.get(self.history_key, None)
            if history is None:
                history = self._at_rest(obs[..., 0, :])
            pairs = torch.cat([history.to(pairs.dtype), pairs], -2)
        u = checked_scores(self.estimator, pairs.reshape(-1, pairs.shape[-2], features))
        u = u.reshape(*batch, length, 1)
        tensordict.set(unravel_key(("next", self.uncertainty_key)), u)
        if self.penalize:
            key = unravel_key(("next", self.reward_key))
            reward = tensordict.get(key)
            new = self.alpha * reward - self.beta * u.reshape(reward.shape).to(reward.dtype)
            if self.band is not None:
                total = u.cumsum(-2)
                before = torch.cat([torch.zeros_like(total[..., :1, :]), total[..., :-1, :]], -2)
                growth = self._distance(total) - self._distance(before)
                new = new - self.band_weight * growth.reshape(reward.shape).to(reward.dtype)
            tensordict.set(key, new)
        return tensordict

    def __repr__(self) -> str:
        band = "" if self.band is None else f", band={self.band}"
        return (
            f"{type(self).__name__}(estimator={type(self.estimator).__name__}(window="
            f"{self.window}), alpha={self.alpha}, beta={self.beta}{band})"
        )
