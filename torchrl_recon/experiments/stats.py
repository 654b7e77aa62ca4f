"""The one mean ± std rule of the experiments and their summaries, and the paired tests across seeds."""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import torch


def mean_std(
    values: Iterable[float], *, dtype: torch.dtype = torch.float64, finite: bool = False
) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof = 1) of ``values``.

    One value has no spread to measure: its std is NaN (not 0). No value: both are NaN.

    Args:
        values: the numbers.
        dtype: the precision the sums are taken in (explore's arms keep float32, as recorded).
        finite: leave out NaN and infinite values first (a control episode without a planned
            step reports NaN metrics).

    Examples:
        >>> mean_std([1.0, 3.0])
        (2.0, 1.4142135623730951)
        >>> mean_std([2.0])
        (2.0, nan)
        >>> mean_std([1.0, float("nan"), 3.0], finite=True)
        (2.0, 1.4142135623730951)
    """
    t = torch.as_tensor(list(values), dtype=dtype)
    t = t[t.isfinite()] if finite else t
    if t.numel() == 0:
        return float("nan"), float("nan")
    return float(t.mean()), float(t.std()) if t.numel() > 1 else float("nan")


MIN_SEEDS_TTEST, MIN_SEEDS_WILCOXON = 2, 5
"""The fewest pairs a paired t-test and a Wilcoxon signed-rank test are computed from."""


def not_computed(n: int, minimum: int, what: str = "seeds") -> dict[str, Any]:
    """A test entry for too little data: NaN statistic and p-value, and why.

    Examples:
        >>> not_computed(1, 2)["note"]
        'not computed: needs at least 2 seeds, got 1'
    """
    nan = float("nan")
    note = f"not computed: needs at least {minimum} {what}, got {n}"
    return {"statistic": nan, "p_value": nan, "n": n, "note": note}


def paired_tests(
    a: Sequence[float], b: Sequence[float], *, t_note: str = "paired t-test across seeds"
) -> dict[str, Any]:
    """A paired t-test (``scipy.stats.ttest_rel``, from 2 pairs) and a two-sided Wilcoxon
    signed-rank test (``scipy.stats.wilcoxon``, from 5) of ``a`` against ``b``, paired by position.

    Examples:
        >>> tests = paired_tests([1.0, 2.0, 3.0], [2.0, 3.5, 4.0])
        >>> round(tests["paired_t"]["p_value"], 3), tests["wilcoxon"]["note"]
        (0.02, 'not computed: needs at least 5 seeds, got 3')
    """
    from scipy import stats

    n = len(a)
    out: dict[str, Any] = {}
    if n >= MIN_SEEDS_TTEST:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            t = stats.ttest_rel(a, b)
        out["paired_t"] = {
            "statistic": float(t.statistic),
            "p_value": float(t.pvalue),
            "n": n,
            "note": t_note,
        }
    else:
        out["paired_t"] = not_computed(n, MIN_SEEDS_TTEST)
    if n < MIN_SEEDS_WILCOXON:
        out["wilcoxon"] = not_computed(n, MIN_SEEDS_WILCOXON)
    elif np.all(np.subtract(a, b) == 0):
        out["wilcoxon"] = {
            "statistic": float("nan"),
            "p_value": 1.0,
            "n": n,
            "note": "all paired differences are zero",
        }
    else:
        w = stats.wilcoxon(a, b)
        out["wilcoxon"] = {
            "statistic": float(w.statistic),
            "p_value": float(w.pvalue),
            "n": n,
            "note": "Wilcoxon signed-rank test across seeds (two-sided)",
        }
    return out
