"""Input checks shared by the environments: one clear error per kind of bad action."""

from __future__ import annotations

import numpy as np


def validate_action(
    action, *, shape: tuple[int, ...], env_name: str, low: float = -1.0, high: float = 1.0
) -> np.ndarray:
    """Return ``action`` as a float64 array clipped to ``[low, high]``.

    Raises a ``ValueError`` naming the offending value when the action has the wrong
    shape or contains NaN/inf. Finite out-of-range values are clipped (each spec says so).

    Examples:
        >>> validate_action([0.5, 2.0, -0.1], shape=(3,), env_name="IB").tolist()
        [0.5, 1.0, -0.1]
    """
    try:
        arr = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"{env_name}: action {action!r} is not numeric; expected an array of shape {shape}."
        ) from err
    if arr.shape != shape:
        if arr.size == int(np.prod(shape)) and arr.ndim <= 2:
            arr = arr.reshape(shape)
        else:
            raise ValueError(f"{env_name}: action has shape {arr.shape}, expected {shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(
            f"{env_name}: action {arr.tolist()} contains NaN or inf; expected finite values in [{low}, {high}]."
        )
    return np.clip(arr, low, high)
