"""Choosing the torch device of a run (``device: auto``), describing it for ``meta.json`` and
naming it back from there; and where a module lives (:func:`module_device`, :func:`module_dtype`),
the device and dtype that tensors made for it should have."""

from __future__ import annotations

import os
import platform
import re
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchrl_recon.errors import CompilerNotFoundError

DEVICE_CHOICES = ("auto", "cpu", "cuda", "cuda:N")
_CUDA_INDEX = re.compile(r"cuda:(\d+)")


def check_device(spec: str) -> str:
    """Refuse a device name that is none of :data:`DEVICE_CHOICES`; return it unchanged.

    Only the spelling is checked here (a recipe is checked before any work, perhaps on a machine
    without the GPU it will run on); :func:`resolve_device` checks that the device exists.

    Examples:
        >>> check_device("cuda:1")
        'cuda:1'
        >>> check_device("gpu")
        Traceback (most recent call last):
        ...
        ValueError: device must be one of auto, cpu, cuda, cuda:N (N = 0, 1, ...), got 'gpu'.
    """
    if spec in ("auto", "cpu", "cuda") or _CUDA_INDEX.fullmatch(str(spec)):
        return spec
    raise ValueError(
        f"device must be one of auto, cpu, cuda, cuda:N (N = 0, 1, ...), got {spec!r}."
    )


def resolve_device(spec: str = "auto") -> torch.device:
    """The torch device a recipe's ``device`` names: ``auto`` is CUDA when available, else CPU.

    Raises:
        ValueError: the name is not a device choice, or names a CUDA device this machine lacks.

    Examples:
        >>> resolve_device("cpu")
        device(type='cpu')
        >>> resolve_device("auto").type in ("cpu", "cuda")
        True
    """
    check_device(spec)
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(spec)
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = device.index or 0
        if index >= count:
            raise ValueError(
                f"device {spec!r}: this machine has {count} CUDA device(s); "
                "use device=cpu or device=auto."
            )
    return device


def check_compile_support(device: torch.device | str) -> None:
    """Refuse ``compile=True`` where ``torch.compile`` cannot build its kernels: on the CPU its
    backend compiles C++ with ``$CXX`` (else ``g++``), which must be on ``PATH``. Nothing to
    check on CUDA (Triton comes with torch's CUDA wheels) or on Windows (MSVC's ``cl``).

    Raises:
        CompilerNotFoundError: a ``RuntimeError`` naming the compiler it looked for.

    Examples:
        >>> check_compile_support("cuda")  # checked on the CPU only
    """
    if torch.device(device).type != "cpu" or sys.platform == "win32":
        return
    cxx = os.environ.get("CXX") or "g++"
    if shutil.which(cxx) is None:
        raise CompilerNotFoundError(
            f"compile=True on the CPU needs a C++ compiler for torch.compile's kernels, and "
            f"{cxx!r} is not on PATH: install one (or point CXX at it), or set compile false."
        )


def cpu_model() -> str:
    """The processor's model name (``/proc/cpuinfo`` on Linux, else ``platform.processor()``)."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.lower().startswith(("model name", "cpu model", "hardware")):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def describe_device(device: torch.device | str) -> dict[str, Any]:
    """What ``meta.json`` records of the device: its name, and for the CPU its model and the
    vector instructions torch uses (results are bit-identical only on the same kind).

    Examples:
        >>> info = describe_device("cpu")
        >>> sorted(info)
        ['cpu_capability', 'cpu_model', 'device', 'name']
    """
    device = torch.device(device)
    info: dict[str, Any] = {
        "device": str(device),
        "cpu_model": cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
    }
    if device.type == "cuda":
        info["name"] = torch.cuda.get_device_name(device)
        info["cuda"] = torch.version.cuda
    else:
        info["name"] = info["cpu_model"]
    return info


def processor(info: Mapping[str, Any] | None) -> str:
    """One line naming the device :func:`describe_device` described (``meta.json``'s
    ``device``): results are bit-identical only on the same commit and kind of processor.

    Examples:
        >>> processor({"device": "cpu", "cpu_model": "AMD EPYC", "cpu_capability": "AVX512"})
        'cpu: AMD EPYC (AVX512)'
        >>> processor(None)
        'not recorded'
    """
    if not info:
        return "not recorded"
    if str(info.get("device", "")).startswith("cuda"):
        return f"{info['device']}: {info.get('name')} (CPU {info.get('cpu_model')})"
    return f"{info.get('device')}: {info.get('cpu_model')} ({info.get('cpu_capability')})"


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
