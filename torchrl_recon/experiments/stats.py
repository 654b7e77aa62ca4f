"""The one mean ± std rule of the experiments and their summaries."""

from __future__ import annotations

from collections.abc import Iterable

import torch


def mean_std(values: Iterable[float], *, dtype: torch.dtype = torch.float64) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof = 1) of ``values``.

    One value has no spread to measure: its std is NaN (not 0). No value: both are NaN.
    Callers drop the values they do not count (NaN episodes, ...) before calling.

    Args:
        values: the numbers.
        dtype: the precision the sums are taken in (explore's arms keep float32, as recorded).

    Examples:
        >>> mean_std([1.0, 3.0])
        (2.0, 1.4142135623730951)
        >>> mean_std([2.0])
        (2.0, nan)
    """
    t = torch.as_tensor(list(values), dtype=dtype)
    if t.numel() == 0:
        return float("nan"), float("nan")
    return float(t.mean()), float(t.std()) if t.numel() > 1 else float("nan")
