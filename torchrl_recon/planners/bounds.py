"""Action bounds read from a TorchRL action spec, and the check that a planner's bounds match an env's."""

from __future__ import annotations

import torch
from torchrl.data import Bounded, TensorSpec

__all__ = ["bounds_from_spec", "check_bounds_match"]


def _fmt(x: torch.Tensor) -> str:
    values = [round(float(v), 6) for v in x.flatten()]
    if len(set(values)) == 1:
        return f"{values[0]:g}"
    return "[" + ", ".join(f"{v:g}" for v in values) + "]"


def bounds_from_spec(action_spec: TensorSpec) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``(low, high)`` bounds ``[M]`` of a bounded continuous TorchRL action spec, on the CPU.

    A batched spec (``[*B, M]``, e.g. from a ``ParallelEnv``) must have the same bounds in every
    env of the batch.

    Raises:
        ValueError: the spec is not a ``Bounded`` continuous spec, has infinite bounds, or its
            batch disagrees; the message says to pass ``action_low`` / ``action_high`` instead.

    Examples:
        >>> from torchrl.data import Bounded
        >>> low, high = bounds_from_spec(Bounded(-2.0, 2.0, shape=(1,)))
        >>> low.tolist(), high.tolist()
        ([-2.0], [2.0])
    """
    remedy = "pass action_low= / action_high= to PlanningModel explicitly."
    if not isinstance(action_spec, Bounded):
        raise ValueError(
            f"the env's action spec is a {type(action_spec).__name__}, not a bounded continuous "
            f"spec (torchrl.data.Bounded), so the planner cannot read its action bounds; {remedy}"
        )
    if action_spec.dtype is not None and not action_spec.dtype.is_floating_point:
        raise ValueError(
            f"the env's action spec has dtype {action_spec.dtype}; the planners need continuous "
            f"(floating point) actions."
        )
    low = action_spec.space.low.detach().to("cpu", torch.float64)
    high = action_spec.space.high.detach().to("cpu", torch.float64)
    if low.ndim == 0:
        low, high = low.reshape(1), high.reshape(1)
    m = low.shape[-1]
    low, high = low.reshape(-1, m), high.reshape(-1, m)
    if not ((low == low[:1]).all() and (high == high[:1]).all()):
        raise ValueError(
            f"the env's action bounds differ between the envs of its batch (low {low.tolist()}, "
            f"high {high.tolist()}); one planner needs one action box."
        )
    low, high = low[0], high[0]
    if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
        raise ValueError(
            f"the env's action spec is unbounded (low {_fmt(low)}, high {_fmt(high)}); "
            f"the planner samples actions inside a finite box: {remedy}"
        )
    return low, high


def check_bounds_match(
    low: torch.Tensor,
    high: torch.Tensor,
    action_spec: TensorSpec,
    *,
    owner: str = "the planner",
    remedy: str = "build the planning model with PlanningModel.from_env(world_model, cost, env, ...)",
) -> None:
    """Refuse planner bounds ``low`` / ``high`` ``[M]`` that differ from the env's action spec.

    Raises:
        ValueError: naming both ranges (or both action sizes) and what to do.

    Examples:
        >>> from torchrl.data import Bounded
        >>> spec = Bounded(-2.0, 2.0, shape=(1,))
        >>> check_bounds_match(torch.tensor([-2.0]), torch.tensor([2.0]), spec)
        >>> try:
        ...     check_bounds_match(torch.tensor([-1.0]), torch.tensor([1.0]), spec)
        ... except ValueError as e:
        ...     print(str(e).split(";")[0])
        the planner's action range [-1, 1] differs from the env's action spec [-2, 2]
    """
    env_low, env_high = bounds_from_spec(action_spec)
    low = low.detach().to("cpu", torch.float64).reshape(-1)
    high = high.detach().to("cpu", torch.float64).reshape(-1)
    if low.shape != env_low.shape:
        raise ValueError(
            f"{owner} plans {low.numel()}-dim actions but the env's action spec has "
            f"{env_low.numel()} dims; {remedy}."
        )
    # float32 round trips of the same bounds are equal to ~1e-7 relative.
    tol = dict(rtol=1e-5, atol=1e-6)
    if not (torch.allclose(low, env_low, **tol) and torch.allclose(high, env_high, **tol)):
        raise ValueError(
            f"{owner}'s action range [{_fmt(low)}, {_fmt(high)}] differs from the env's action "
            f"spec [{_fmt(env_low)}, {_fmt(env_high)}]; {remedy} (or pass action_low="
            f"{_fmt(env_low)}, action_high={_fmt(env_high)})."
        )
