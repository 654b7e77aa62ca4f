"""The one mean ± std rule of the experiments and their summaries (the tests across seeds are
:mod:`torchrl_recon.evaluation.significance`), and its use over episodes."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch

from torchrl_recon.evaluation.mpc import METRICS


def mean_std(
    values: Iterable[float], *, dtype: torch.dtype = torch.float64, finite: bool = False
) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof = 1) of ``values``, summed in ``dtype``
    (explore's arms keep float32, as recorded); with ``finite``, NaN and ±inf left out first.

    One value has no spread to measure: its std is NaN (not 0). No value: both are NaN.

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


def episode_mean_std(episodes: list[dict], metrics: Sequence[str] = METRICS) -> tuple[dict, dict]:
    """Mean and std over episodes of each of ``metrics``, non-finite values left out.

    Examples:
        >>> mean, std = episode_mean_std([{k: 1.0 for k in METRICS}, {k: 3.0 for k in METRICS}])
        >>> mean["prediction_mse"], round(std["prediction_mse"], 3)
        (2.0, 1.414)
    """
    stats = {m: mean_std((e[m] for e in episodes if m in e), finite=True) for m in metrics}
    return {m: s[0] for m, s in stats.items()}, {m: s[1] for m, s in stats.items()}
