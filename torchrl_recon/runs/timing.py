"""Wall-clock timing shared by the benchmarks and the calibration experiment."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch


def interleaved_median_ms(
    fns: dict[str, Callable[[], object]], repeats: int, *, device: torch.device | str | None = None
) -> dict[str, float]:
    """Median wall time in ms of each function, timed in round-robin rounds after one warm-up.

    Interleaving spreads a change of machine load over all functions alike, so their ratios
    stay comparable on a busy machine. With a CUDA ``device``, each call is timed until the
    device has finished its work (``torch.cuda.synchronize``).

    Examples:
        >>> times = interleaved_median_ms({"a": lambda: sum(range(10)), "b": lambda: None}, 3)
        >>> sorted(times), all(t >= 0 for t in times.values())
        (['a', 'b'], True)
    """
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    cuda = device is not None and torch.device(device).type == "cuda"

    def call(fn: Callable[[], object]) -> None:
        fn()
        if cuda:
            torch.cuda.synchronize(device)

    for fn in fns.values():
        call(fn)
    samples: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            call(fn)
            samples[name].append(time.perf_counter() - start)
    return {name: statistics.median(times) * 1e3 for name, times in samples.items()}
