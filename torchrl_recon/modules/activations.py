"""The hidden-layer activations the modules accept by name, with their in-place and backward forms."""

from __future__ import annotations

import torch
from torch.nn import functional as F

ACTIVATIONS = {"relu": F.relu, "tanh": torch.tanh, "elu": F.elu}
"""Name → activation function (``activation=`` of the world model and the estimators).

Examples:
    >>> ACTIVATIONS["tanh"](torch.zeros(2))
    tensor([0., 0.])
"""

INPLACE_ACTIVATIONS = {"relu": torch.relu_, "tanh": torch.tanh_, "elu": F.elu_}
"""The same, in place (the no-grad fast paths)."""

ACTIVATION_BACKWARDS = {
    "relu": lambda grad, pre, out: torch.ops.aten.threshold_backward.default(grad, out, 0),
    "tanh": lambda grad, pre, out: torch.ops.aten.tanh_backward.default(grad, out),
    "elu": lambda grad, pre, out: torch.ops.aten.elu_backward.default(grad, 1.0, 1, 1, False, pre),
}
"""``backward(grad, pre, out)`` of each: the kernel autograd's own derivative formula calls, from
the pre-activation and the output (the hand-written BPTT in ``_lstm_rollout.py``)."""
