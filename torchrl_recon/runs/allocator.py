"""Keep freed memory in the process: CPU tensors of a few MB stop costing page faults.

glibc's ``malloc`` serves each block above its mmap threshold (dynamic, 128 KiB to 32 MiB) with
fresh pages from the kernel and returns freed memory at the heap's top once it passes the trim
threshold. A population's fit step allocates and frees tens of tensors of 0.1–10 MB (its
``[members, rows, 4·hidden]`` gates and their gradients), so with the defaults every step
faults thousands of fresh pages in: on the 2-core test machine ~5,500 faults and ~25% of a
20-member rollout's forward and backward. :func:`keep_freed_memory` raises both thresholds
(``mallopt``), so freed blocks are reused; the process keeps up to ``trim_threshold`` bytes of
freed memory instead of handing it back at once.

The experiment runner calls it before a run (``meta.json`` records whether it took effect), as do
the benchmarks. It changes how fast memory is handed out, never what is computed. On a platform
without glibc (macOS, Windows, musl) it does nothing and returns False.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 * 1024 * 1024  # glibc's largest mmap threshold on 64-bit systems


def keep_freed_memory(trim_threshold: int = 1 << 30) -> bool:
    """Make glibc's ``malloc`` reuse freed blocks of up to 32 MiB instead of re-faulting them.

    Args:
        trim_threshold: bytes of free memory at the heap's top kept before any is returned to
            the operating system (default 1 GiB).

    Returns:
        True when both settings took effect; False without glibc (nothing changed).

    Examples:
        >>> keep_freed_memory() in (True, False)
        True
    """
    if not MMAP_THRESHOLD_MAX <= trim_threshold < 2**31:
        raise ValueError(
            f"trim_threshold must be between {MMAP_THRESHOLD_MAX} bytes (glibc's largest mmap "
            f"threshold) and 2**31 - 1 (mallopt takes an int), got {trim_threshold}."
        )
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    libc = ctypes.CDLL(name)
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)) and bool(
        libc.mallopt(_M_TRIM_THRESHOLD, int(trim_threshold))
    )
