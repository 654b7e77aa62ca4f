"""The hidden-layer activations the modules accept by name."""

from __future__ import annotations

import torch
from torch.nn import functional as F

ACTIVATIONS = {"relu": F.relu, "tanh": torch.tanh, "elu": F.elu}
INPLACE_ACTIVATIONS = {"relu": torch.relu_, "tanh": torch.tanh_, "elu": F.elu_}
"""The same, in place (the no-grad fast paths)."""

ACTIVATION_BACKWARDS = {
    "relu": lambda grad, pre, out: torch.ops.aten.threshold_backward.default(grad, out, 0),
    "tanh": lambda grad, pre, out: torch.ops.aten.tanh_backward.default(grad, out),
    "elu": lambda grad, pre, out: torch.ops.aten.elu_backward.default(grad, 1.0, 1, 1, False, pre),
}
"""``backward(grad, pre, out)`` of each: the kernel autograd's own derivative formula calls, from
the pre-activation and the output (the hand-written BPTT in ``_lstm_rollout.py``)."""


def check_activation(activation: str) -> None:
    """Raise unless ``activation`` names one of :data:`ACTIVATIONS`.

    Examples:
        >>> check_activation("relu")
        >>> check_activation("gelu")
        Traceback (most recent call last):
        ...
        ValueError: activation 'gelu' is not one of ['elu', 'relu', 'tanh'].
    """
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation {activation!r} is not one of {sorted(ACTIVATIONS)}.")
