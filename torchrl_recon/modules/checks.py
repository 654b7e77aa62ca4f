"""Argument checks shared by the modules, planners and policies, with errors that name the bad
value and what was expected."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable

import torch
from tensordict import NestedKey, TensorDictBase

from torchrl_recon.modules.activations import ACTIVATIONS

__all__ = [
    "capturing_cuda_graph",
    "in_graph",
    "check_activation",
    "check_features",
    "check_finite",
    "check_finite_keys",
    "check_flag",
    "check_int",
    "check_keys",
    "check_real",
    "check_type",
    "check_window",
    "is_key",
]


def check_features(name: str, x: torch.Tensor, dim: int, *, min_ndim: int = 1) -> None:
    """Raise if ``x`` is not a tensor with last dimension ``dim`` and at least ``min_ndim`` dims.

    Examples:
        >>> check_features("obs", torch.zeros(4, 3), 2)
        Traceback (most recent call last):
        ...
        ValueError: obs has shape (4, 3); expected at least 1 dims with last dim 2.
    """
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}.")
    if x.ndim < min_ndim or x.shape[-1] != dim:
        raise ValueError(
            f"{name} has shape {tuple(x.shape)}; expected at least {min_ndim} dims with last dim {dim}."
        )


def capturing_cuda_graph() -> bool:
    """True while a CUDA graph is being captured on the current stream (a fit's
    ``cuda_graph=True`` step): a check that reads a tensor's values on the host would fail the
    capture, so such checks are left out then (the fit checks each step's loss after it).

    While ``torch.compile`` traces it is False without asking CUDA (Dynamo need not trace the
    query; a compiled region is not a capture).

    Examples:
        >>> capturing_cuda_graph()
        False
    """
    if torch.compiler.is_compiling():
        return False
    return torch.cuda.is_available() and torch.cuda.is_current_stream_capturing()


def in_graph() -> bool:
    """True while ``torch.compile`` traces or a CUDA graph is captured: a check that reads a
    tensor's values on the host would cut the graph or fail the capture, so such checks are left
    out then. The speed paths that build graphs (a fit's compiled or captured step, a compiled
    plan) check what such a check would have caught: a step whose loss is not finite is run
    again eagerly, checks included. The one question the library's parts ask of the speed path.

    Examples:
        >>> in_graph()
        False
    """
    return torch.compiler.is_compiling() or capturing_cuda_graph()


def check_finite(name: str, x: torch.Tensor) -> None:
    """Raise if ``x`` holds NaN or inf (pass ``x.detach()`` for a tensor that requires grad).

    Not checked while a graph is built (a fit's ``compile=True`` or
    ``cuda_graph=True`` training step): the fit's check of each step's loss stops on the same
    NaN or inf and runs the eager step, this check included, on that batch.

    Examples:
        >>> check_finite("obs", torch.tensor([0.0, float("nan")]))
        Traceback (most recent call last):
        ...
        ValueError: obs contains NaN or inf (first at index [1]); expected finite values.
    """
    if in_graph():
        return
    if not torch.isfinite(x).all():
        bad = (~torch.isfinite(x)).nonzero()[0].tolist()
        raise ValueError(
            f"{name} contains NaN or inf (first at index {bad}); expected finite values."
        )


CLEAN_DATA = "clean the data first (drop or repair those steps)"
"""What to do about NaN or inf in collected data."""
FIX_ENV = (
    "the env returned it: fix the env (or the reward or cost it computes) so that every step "
    "is finite"
)
"""What to do about NaN or inf that an env returned while collecting."""


def nonfinite_key(
    data: TensorDictBase, keys: Iterable[NestedKey] | None = None
) -> tuple[NestedKey, int, int] | None:
    """The first of ``keys`` (default: every floating-point entry) whose values in ``data`` hold
    NaN or inf, with the first such row (over ``data``'s batch dims flattened) and feature
    (over the rest flattened): ``(key, row, feature)``, or None when all are finite. A key
    ``data`` lacks is skipped.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.zeros(4, 2), ("next", "reward"): torch.zeros(4, 1)}, [4])
        >>> td["next", "reward"][2] = float("nan")
        >>> nonfinite_key(td)
        (('next', 'reward'), 2, 0)
    """
    if keys is None:
        keys = [
            k
            for k in data.keys(True, True)
            if isinstance(data.get(k), torch.Tensor) and data.get(k).is_floating_point()
        ]
    rows = max(1, int(data.batch_size.numel()))
    for key in keys:
        x = data.get(key, None)
        if not isinstance(x, torch.Tensor) or not x.is_floating_point() or x.numel() == 0:
            continue
        bad = ~torch.isfinite(x.detach().reshape(rows, -1))
        if bool(bad.any()):
            row, feature = bad.nonzero()[0].tolist()
            return key, row, feature
    return None


def check_finite_keys(
    data: TensorDictBase,
    keys: Iterable[NestedKey] | None = None,
    *,
    where: str = "the data",
    rows: torch.Tensor | None = None,
    remedy: str = CLEAN_DATA,
) -> None:
    """Raise if one of ``keys`` (default: every floating-point entry) of ``data`` holds NaN or
    inf, naming the key, its first bad row (an index over the batch dims where ``data`` has
    several) and what to do (see :func:`nonfinite_key`).

    Args:
        data: the transitions (a replay buffer's contents, a collected or sampled batch).
        keys: the entries to check, in order.

    Keyword Args:
        where: what ``data`` is, for the message (``"the replay buffer"``).
        rows: the row each of ``data``'s (flattened) rows stands for, ``[*batch]`` or
            ``[*batch, 1]``, e.g. a sample's buffer ``"index"``; the message then names that row.
        remedy: what the message says to do (default :data:`CLEAN_DATA`).

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.zeros(4, 2), "action": torch.zeros(4, 1)}, [4])
        >>> td["action"][3, 0] = float("inf")
        >>> check_finite_keys(td, ["observation", "action"], where="the replay buffer")
        Traceback (most recent call last):
        ...
        ValueError: 'action' in the replay buffer holds NaN or inf (first at row 3, feature 0); clean the data first (drop or repair those steps).
    """
    found = nonfinite_key(data, keys)
    if found is None:
        return
    key, row, feature = found
    if rows is not None:
        at = rows.reshape(max(1, int(data.batch_size.numel())), -1)[row].tolist()
        row = at[0] if len(at) == 1 else at
    elif data.batch_dims > 1:  # e.g. [envs, steps]: the index in the batch dims
        row = [int(i) for i in torch.unravel_index(torch.tensor(row), data.batch_size)]
    raise ValueError(
        f"{key!r} in {where} holds NaN or inf (first at row {row}, feature {feature}); {remedy}."
    )


def is_key(key: object) -> bool:
    """Whether ``key`` is a TensorDict key: a str, or a non-empty tuple of str.

    Examples:
        >>> is_key("observation"), is_key(("next", "reward")), is_key(3)
        (True, True, False)
    """
    if isinstance(key, str):
        return True
    return isinstance(key, tuple) and bool(key) and all(isinstance(k, str) for k in key)


def check_flag(name: str, value: object) -> None:
    """Raise unless ``value`` is True or False (a switch such as ``compile``).

    Examples:
        >>> check_flag("cuda_graph", "yes")
        Traceback (most recent call last):
        ...
        TypeError: cuda_graph must be True or False, got 'yes'.
    """
    if not isinstance(value, bool):
        raise TypeError(f"{name} must be True or False, got {value!r}.")


def check_int(name: str, value: object, minimum: int = 1) -> None:
    """Raise unless ``value`` is an int (not a bool) of at least ``minimum``.

    Examples:
        >>> check_int("horizon", 0)
        Traceback (most recent call last):
        ...
        ValueError: horizon must be an int >= 1, got 0.
    """
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}.")


def _short(value: object, limit: int = 40) -> str:
    """``value``'s repr after its type name when it is a short plain value, else nothing."""
    if value is None or isinstance(value, str | bytes | int | float | complex):
        text = repr(value)
        return " " + (text if len(text) <= limit else text[: limit - 3] + "...")
    return ""


def check_type(name: str, value: object, types: type | tuple[type, ...], expected: str) -> None:
    """Raise ``TypeError`` unless ``value`` is an instance of ``types``, naming the argument,
    what it got and ``expected`` (how the message describes ``types``).

    Examples:
        >>> check_type("buffer", "rb", TensorDictBase, "a TensorDict")
        Traceback (most recent call last):
        ...
        TypeError: buffer must be a TensorDict, got str 'rb'.
    """
    if not isinstance(value, types):
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__}{_short(value)}.")


def check_keys(name: str, data: object, keys: Iterable[NestedKey]) -> None:
    """Raise unless ``data`` is a TensorDict holding every one of ``keys``: ``TypeError`` for
    another type, ``ValueError`` naming the missing keys and those it has.

    Examples:
        >>> from tensordict import TensorDict
        >>> check_keys("data", TensorDict({"observation": torch.zeros(2, 3)}, [2]), ["observation", ("next", "reward")])
        Traceback (most recent call last):
        ...
        ValueError: data lacks ('next', 'reward'); it has ['observation'].
    """
    check_type(name, data, TensorDictBase, "a TensorDict")
    have = data.keys(True, True)
    missing = [k for k in keys if k not in have]
    if missing:
        shown = ", ".join(repr(k) for k in missing)
        raise ValueError(f"{name} lacks {shown}; it has {sorted(map(str, have))}.")


def check_real(
    name: str,
    value: object,
    *,
    minimum: float | None = None,
    exclusive: bool = False,
    finite: bool = True,
) -> None:
    """Raise unless ``value`` is a real number (not a bool), not NaN, finite (unless
    ``finite=False``) and at least ``minimum`` (above it with ``exclusive=True``).

    Examples:
        >>> check_real("lr", -1.0, minimum=0, exclusive=True)
        Traceback (most recent call last):
        ...
        ValueError: lr must be a finite number > 0, got -1.0.
        >>> check_real("beta", float("nan"))
        Traceback (most recent call last):
        ...
        ValueError: beta must be a finite number, got nan.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number, got {value!r}.")
    number = float(value)
    bad = math.isnan(number) or (finite and math.isinf(number))
    if minimum is not None:
        bad = bad or number < minimum or (exclusive and number == minimum)
    if bad:
        kind = "a finite number" if finite else "a number, not NaN"
        bound = "" if minimum is None else f" {'>' if exclusive else '>='} {minimum}"
        raise ValueError(f"{name} must be {kind}{bound}, got {value!r}.")


def check_window(name: str, x: torch.Tensor, window: int) -> None:
    """Raise if the time dimension (-2) of ``x`` is shorter than ``window``.

    Examples:
        >>> check_window("context_obs", torch.zeros(3, 6), 10)
        Traceback (most recent call last):
        ...
        ValueError: context_obs has shape (3, 6); expected a time dimension (-2) of at least window=10 steps.
    """
    if x.ndim < 2 or x.shape[-2] < window:
        raise ValueError(
            f"{name} has shape {tuple(x.shape)}; expected a time dimension (-2) of at least window={window} steps."
        )


def check_window_pair(
    obs: torch.Tensor,
    action: torch.Tensor,
    *,
    obs_dim: int,
    action_dim: int,
    window: int,
    min_ndim: int = 2,
) -> None:
    """Raise unless ``obs`` ``[*B, L, obs_dim]`` and ``action`` ``[*B, L, action_dim]`` agree on
    their batch and time dims and hold at least ``window`` steps (what an estimator scores).

    Examples:
        >>> check_window_pair(torch.zeros(5, 6), torch.zeros(4, 3), obs_dim=6, action_dim=3, window=2)
        Traceback (most recent call last):
        ...
        ValueError: obs (5, 6) and action (4, 3) disagree on batch/time dims.
    """
    check_features("obs", obs, obs_dim, min_ndim=min_ndim)
    check_features("action", action, action_dim, min_ndim=min_ndim)
    if obs.shape[:-1] != action.shape[:-1]:
        raise ValueError(
            f"obs {tuple(obs.shape)} and action {tuple(action.shape)} disagree on batch/time dims."
        )
    check_window("obs", obs, window)


def check_activation(activation: str) -> None:
    """Raise unless ``activation`` names one of :data:`~torchrl_recon.modules.activations.ACTIVATIONS`.

    Examples:
        >>> check_activation("relu")
        >>> check_activation("gelu")
        Traceback (most recent call last):
        ...
        ValueError: activation 'gelu' is not one of ['elu', 'relu', 'tanh'].
    """
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation {activation!r} is not one of {sorted(ACTIVATIONS)}.")
