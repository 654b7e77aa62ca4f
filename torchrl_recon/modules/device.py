"""Where a module lives: the device and dtype that tensors made for it should have."""

from __future__ import annotations

import torch
from torch import nn


def _check_module(module: object) -> None:
    if not isinstance(module, nn.Module):
        raise TypeError(f"module must be a torch.nn.Module, got {type(module).__name__}.")


def module_device(module: nn.Module) -> torch.device:
    """The device of ``module``'s first parameter (else buffer); the CPU when it has neither.

    Examples:
        >>> module_device(nn.Linear(2, 2))
        device(type='cpu')
        >>> module_device(nn.Linear(2, 2, device="meta"))
        device(type='meta')
    """
    _check_module(module)
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return torch.device("cpu")


def module_dtype(module: nn.Module) -> torch.dtype:
    """The dtype of ``module``'s first floating-point parameter (else buffer); the default dtype
    when it has neither.

    Examples:
        >>> module_dtype(nn.Linear(2, 2).double())
        torch.float64
    """
    _check_module(module)
    for tensor in (*module.parameters(), *module.buffers()):
        if tensor.is_floating_point():
            return tensor.dtype
    return torch.get_default_dtype()
