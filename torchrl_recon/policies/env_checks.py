"""Checks that a planning policy fits the env it acts in: action bounds, primer and InitTracker."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data import Composite
from torchrl.envs import EnvBase, TensorDictPrimer, Transform

from torchrl_recon.planners.bounds import check_bounds_match

IS_INIT = "is_init"
MISSING_INIT_TRACKER = (
    "no 'is_init' entry in the tensordict, so the policy cannot tell when an episode starts and "
    "would run a stale plan after a reset; add TorchRL's InitTracker to the env: "
    "env.append_transform(InitTracker()) (make_env adds it)."
)


def _cpu_bounds(low: torch.Tensor, high: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """CPU copies of the bounds, or None when they have no values (a model on the meta device)."""
    for name, value in (("action_low", low), ("action_high", high)):
        if not isinstance(value, torch.Tensor):
            raise TypeError(
                f"{name} must be a tensor [M] of the planner's bounds, got {type(value).__name__}."
            )
        if value.ndim != 1 or value.shape != low.shape:
            raise ValueError(
                f"{name} has shape {list(value.shape)}; expected [M], the shape of action_low."
            )
    if low.device.type == "meta":
        return None
    return low.detach().cpu().clone(), high.detach().cpu().clone()


def check_policy_env(
    env: EnvBase,
    low: torch.Tensor,
    high: torch.Tensor,
    *,
    action_key: NestedKey,
    state_key: NestedKey,
    owner: str,
) -> None:
    """Refuse an env whose action spec, ``InitTracker`` or primer does not fit the policy.

    Raises:
        ValueError: the planner's action bounds differ from the env's action spec.
        KeyError: the env has no ``InitTracker`` (no ``is_init``) or no primer for ``state_key``.
    """
    spec = env.full_action_spec
    if action_key not in spec.keys(True, True):
        raise KeyError(
            f"the env has no action {action_key!r} (its actions: "
            f"{list(spec.keys(True, True))}); pass action_key= to the policy."
        )
    bounds = _cpu_bounds(low, high)
    if bounds is not None:
        check_bounds_match(*bounds, spec[action_key], owner=owner)
    observed = env.observation_spec.keys(True, True)
    if IS_INIT not in observed:
        raise KeyError(MISSING_INIT_TRACKER)
    if state_key not in observed:
        raise KeyError(
            f"the env does not carry the policy's state {state_key!r}; append its primer: "
            "env.append_transform(policy.make_tensordict_primer())."
        )


class PlannerStatePrimer(TensorDictPrimer):
    """The ``TensorDictPrimer`` of a planning policy's state that checks the env it is appended to.

    When appended to an env (``env.append_transform(policy.make_tensordict_primer())``), it
    compares the planner's action bounds with the action spec of the env it follows and refuses
    a mismatch, naming both ranges: a planner searching another box than the env's acts in is
    silently wrong otherwise. Everything else is TorchRL's ``TensorDictPrimer``.

    Args:
        primers: the state specs (a ``Composite``).

    Keyword Args:
        action_low, action_high: the planner's bounds ``[M]``.
        action_key: the env's action key.
        owner: how errors name the policy.
        **kwargs: passed on to ``TensorDictPrimer`` (``default_value``, ``expand_specs``, ...).

    Examples:
        >>> from torchrl.data import Unbounded
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> primer = PlannerStatePrimer(Composite(x=Unbounded(2)), action_low=torch.tensor([-1.0]),
        ...                             action_high=torch.tensor([1.0]), default_value=0)
        >>> try:
        ...     TransformedEnv(GymEnv("Pendulum-v1")).append_transform(primer)
        ... except ValueError as e:
        ...     print(str(e).split(";")[0])
        the planner's action range [-1, 1] differs from the env's action spec [-2, 2]
    """

    def __init__(
        self,
        primers: Composite,
        *,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
        action_key: NestedKey = "action",
        owner: str = "the planner",
        **kwargs,
    ) -> None:
        if not isinstance(primers, Composite):
            raise TypeError(
                f"primers must be a torchrl Composite of the state specs, got "
                f"{type(primers).__name__}."
            )
        super().__init__(primers, **kwargs)
        self._planner_bounds = _cpu_bounds(action_low, action_high)
        self._planner_action_key = action_key
        self._planner_owner = owner

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        # A reset's source tensordict stays where the base env made it (a DeviceCastTransform
        # before this primer casts only the reset's output): read it on the specs' device.
        device = self.primers.device
        if device is not None and tensordict is not None and tensordict.device != device:
            tensordict = tensordict.to(device)
        return super()._reset(tensordict, tensordict_reset)

    def set_container(self, container: Transform | EnvBase) -> None:
        super().set_container(container)
        try:  # TorchRL raises while a Compose it joins has no env yet (TransformedEnv's unwrap)
            in_env = isinstance(self.container, EnvBase)
        except ValueError:
            in_env = False
        if self._planner_bounds is None or not in_env:
            return  # not (yet) in an env: checked when its Compose joins one
        parent = self.parent
        if parent is None:
            return
        spec = parent.full_action_spec
        if self._planner_action_key not in spec.keys(True, True):
            return  # the policy's forward names the missing key
        check_bounds_match(
            *self._planner_bounds, spec[self._planner_action_key], owner=self._planner_owner
        )
