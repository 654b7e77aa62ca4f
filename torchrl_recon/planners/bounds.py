"""Action bounds read from a TorchRL action spec, and the check that a planner's bounds match an env's."""

from __future__ import annotations

import torch
from torchrl.data import Bounded, TensorSpec

__all__ = ["action_bounds", "bounds_from_spec", "check_bounds_match"]

CONTINUOUS_ACTIONS = (
    "the planners need a bounded continuous vector of floats (a gymnasium Box with finite low "
    "and high)"
)
"""What the planners need of an env's actions (the wording of ``make_env``'s error)."""


def _fmt(x: torch.Tensor) -> str:
    values = [round(float(v), 6) for v in x.flatten()]
    if len(set(values)) == 1:
        return f"{values[0]:g}"
    return "[" + ", ".join(f"{v:g}" for v in values) + "]"


def _bound(name: str, value: object, action_dim: int, dtype: torch.dtype) -> torch.Tensor:
    """One bound as a CPU tensor ``[action_dim]`` of ``dtype`` (see :func:`action_bounds`)."""
    values = "value" if action_dim == 1 else "values"
    expected = f"a float or a tensor of {action_dim} {values}, shape [{action_dim}]"
    if isinstance(value, bool | str | bytes) or value is None:
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__} {value!r}.")
    try:
        x = torch.as_tensor(value, device="cpu").detach()  # (CPU under any default device)
    except (TypeError, ValueError, RuntimeError) as e:
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__} {value!r}.") from e
    if x.dtype == torch.bool or x.is_complex():
        raise TypeError(f"{name} must be {expected} (real numbers), got dtype {x.dtype}.")
    if x.ndim > 1 or (x.ndim == 1 and x.shape[0] not in (1, action_dim)):
        raise ValueError(f"{name} has shape {list(x.shape)}; expected {expected}.")
    return x.to("cpu", dtype).expand(action_dim).clone()


def action_bounds(
    action_low: object,
    action_high: object,
    action_dim: int,
    *,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Check a planner's action bounds and return them as CPU tensors ``[M]`` of ``dtype``.

    Each bound is a float (the same for every action dim) or a tensor (or list) of ``M`` values;
    both must be finite and ``low < high`` in every dim.

    Raises:
        TypeError: a bound is not a number or a tensor of numbers.
        ValueError: a bound's shape is not ``[M]`` (or a scalar), a bound is not finite, or
            ``low >= high`` somewhere; naming the argument, what was given and what was expected.

    Examples:
        >>> low, high = action_bounds(-2.0, torch.tensor([2.0, 1.0]), 2)
        >>> low.tolist(), high.tolist()
        ([-2.0, -2.0], [2.0, 1.0])
        >>> action_bounds(torch.tensor([-1.0, -1.0]), 1.0, 1)
        Traceback (most recent call last):
        ...
        ValueError: action_low has shape [2]; expected a float or a tensor of 1 value, shape [1].
    """
    low = _bound("action_low", action_low, action_dim, dtype)
    high = _bound("action_high", action_high, action_dim, dtype)
    if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
        raise ValueError(
            f"action bounds must be finite, got action_low={low.tolist()}, "
            f"action_high={high.tolist()}."
        )
    if not (low < high).all():
        raise ValueError(
            f"action_low must be below action_high in every dim, got action_low={low.tolist()}, "
            f"action_high={high.tolist()}."
        )
    return low, high


def bounds_from_spec(action_spec: TensorSpec) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``(low, high)`` bounds ``[M]`` of a bounded continuous TorchRL action spec, on the CPU.

    A batched spec (``[*B, M]``, e.g. from a ``ParallelEnv``) must have the same bounds in every
    env of the batch.

    Raises:
        ValueError: the spec is discrete (the planners need continuous bounded actions), not a
            ``Bounded`` spec or has infinite bounds (the message says to pass ``action_low`` /
            ``action_high`` instead), or its batch disagrees.

    Examples:
        >>> from torchrl.data import Bounded
        >>> low, high = bounds_from_spec(Bounded(-2.0, 2.0, shape=(1,)))
        >>> low.tolist(), high.tolist()
        ([-2.0], [2.0])
    """
    if not isinstance(action_spec, TensorSpec):
        raise TypeError(
            f"action_spec must be a torchrl TensorSpec (env.action_spec), got "
            f"{type(action_spec).__name__}."
        )
    remedy = "pass action_low= / action_high= to PlanningModel explicitly."
    domain = getattr(action_spec, "domain", "continuous")
    dtype = action_spec.dtype
    if domain != "continuous" or (dtype is not None and not dtype.is_floating_point):
        raise ValueError(
            f"the env has a {domain} action space ({type(action_spec).__name__} of shape "
            f"{list(action_spec.shape)}); {CONTINUOUS_ACTIONS}."
        )
    if not isinstance(action_spec, Bounded):
        raise ValueError(
            f"the env's action spec is a {type(action_spec).__name__}, not a bounded continuous "
            f"spec (torchrl.data.Bounded), so the planner cannot read its action bounds; {remedy}"
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
    for name, value in (("low", low), ("high", high)):
        if not isinstance(value, torch.Tensor):
            raise TypeError(
                f"{name} must be a tensor [M] of the planner's action bounds, got "
                f"{type(value).__name__}."
            )
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
