"""Row blocks on several CPU cores at once: each block one compiled call that runs without the GIL.

The candidates' rows are independent, so a planning pass splits into blocks that could run on
every core. Eager PyTorch holds Python's GIL between its small kernels, so blocks in Python
threads ran slower than one thread (0.65–0.79×, ``benchmarks/cpu_blocks.py``), and intra-op
threads do not pay at these sizes. Inductor's C++ wrapper (its ``cpp_wrapper`` option) runs a
whole compiled graph in C++ with the GIL released, so the blocks of such a graph, called from
several threads, run in parallel. ``executors.threaded_pass`` compiles a pass that way, and
:func:`run_blocks` runs its blocks (for ``executors.Threaded``) on a shared thread pool, one
intra-op thread each; :func:`run_aside` starts serial work between two passes (a sampling
planner's next noise draw) on the same pool while the caller goes on.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import torch

from torchrl_recon.modules.checks import check_int

__all__ = ["run_aside", "run_blocks"]


def check_threads(threads: object) -> int:
    """``threads`` as a positive int, or a ``ValueError`` naming it.

    Examples:
        >>> check_threads(2)
        2
        >>> check_threads(0)
        Traceback (most recent call last):
        ...
        ValueError: threads must be an int >= 1, got 0.
    """
    check_int("threads", threads)
    return int(threads)


@functools.cache
def _pool(workers: int, pid: int) -> ThreadPoolExecutor:
    """Process ``pid``'s pool of ``workers`` block threads (shared by every planning model; a
    forked child, whose copy of its parent's pool has no threads, makes its own)."""
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="torchrl_recon-block")


@contextmanager
def one_intra_op_thread() -> Iterator[None]:
    """Run the body at one intra-op thread, the process's count restored after.

    ``torch.set_num_threads`` is process-wide: while blocks run, every thread's ops use one
    core each, so ``threads`` blocks use ``threads`` cores.
    """
    before = torch.get_num_threads()
    if before == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _in_callers_modes(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` to be called from another thread under the calling thread's grad and inference
    modes (they are per thread)."""
    grad, inference = torch.is_grad_enabled(), torch.is_inference_mode_enabled()

    def call(*args: Any) -> Any:
        with torch.inference_mode(inference), torch.set_grad_enabled(grad):
            return fn(*args)

    return call


def run_blocks(
    fn: Callable[[int], Any], blocks: int, threads: int, *, first_alone: bool = False
) -> list[Any]:
    """``[fn(0), ..., fn(blocks - 1)]``, the blocks spread over ``threads`` threads (the
    calling one included), each thread's blocks one after another, at one intra-op thread.

    ``fn`` must be safe to call from several threads at once (a compiled pass is; so is
    reading shared tensors). The caller's grad and inference modes, which are per thread, hold
    in every block thread too. ``first_alone``: run ``fn(0)`` before the others start (a call
    that compiles: Dynamo compiles under a process-wide lock, but a thread that looked up its
    cache before the first compile ended compiles the same graph again).

    Examples:
        >>> run_blocks(lambda i: i * i, blocks=5, threads=2)
        [0, 1, 4, 9, 16]
    """
    check_int("blocks", blocks)
    threads = min(check_threads(threads), blocks)
    if threads == 1:
        return [fn(i) for i in range(blocks)]
    run_group = _in_callers_modes(lambda group: [(i, fn(i)) for i in group])
    with one_intra_op_thread():
        done = run_group([0]) if first_alone else []
        rest = range(len(done), blocks)
        groups = [rest[g::threads] for g in range(threads)]
        pool = _pool(threads - 1, os.getpid())
        futures = [pool.submit(run_group, g) for g in groups[1:]]
        done += run_group(groups[0])
        for future in futures:
            done += future.result()
    return [out for _, out in sorted(done, key=lambda pair: pair[0])]


def run_aside(fn: Callable[[], Any], threads: int) -> Future:
    """Start ``fn()`` on the block threads' pool (of ``threads``), under the caller's grad and
    inference modes, while the calling thread goes on; ``.result()`` waits for it.

    For serial work between two threaded passes that two things can share: a sampling
    planner draws its next iteration's noise this way while it ranks the last one.

    Examples:
        >>> run_aside(lambda: 6 * 7, threads=2).result()
        42
    """
    pool = _pool(max(1, check_threads(threads) - 1), os.getpid())
    return pool.submit(_in_callers_modes(fn))
