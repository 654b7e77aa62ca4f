"""keep_freed_memory: raises glibc's malloc thresholds, or says it could not."""

from __future__ import annotations

import platform

import pytest

from torchrl_recon.runs.allocator import MMAP_THRESHOLD_MAX, keep_freed_memory


def test_keep_freed_memory_takes_effect_on_glibc_and_refuses_bad_thresholds():
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    assert keep_freed_memory() is glibc
    for bad in (MMAP_THRESHOLD_MAX - 1, 2**31):
        with pytest.raises(ValueError, match="trim_threshold must be between"):
            keep_freed_memory(bad)
