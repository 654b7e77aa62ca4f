"""The skip mark of the tests that run ``torch.compile`` on the CPU (it builds C++ kernels)."""

from __future__ import annotations

import pytest

from torchrl_recon.devices import check_compile_support


def has_cpp_compiler() -> bool:
    """Whether torch.compile can build its CPU kernels here (a C++ compiler on ``PATH``)."""
    try:
        check_compile_support("cpu")
    except RuntimeError:
        return False
    return True


needs_cpp_compiler = pytest.mark.skipif(
    not has_cpp_compiler(), reason="torch.compile on the CPU needs a C++ compiler"
)
