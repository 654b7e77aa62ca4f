"""The control experiment across seeds (Fig. 3's claim tested across models): per-seed means of
each setting, paired tests against the first setting (the baseline), and a trend test over the
settings with an uncertainty band, paired by seed."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from torchrl_recon.experiments.stats import mean_std, not_computed, paired_tests

TESTED = ("prediction_mse", "real_cost")
"""The metrics tested across seeds."""
MIN_SEEDS_TREND = 2


def seed_mean(record: Mapping[str, Any], metric: str) -> float:
    """The mean of ``metric`` over a setting record's episodes (NaN episodes left out).

    Examples:
        >>> seed_mean({"episodes": [{"real_cost": 1.0}, {"real_cost": 3.0}]}, "real_cost")
        2.0
    """
    episodes = record.get("episodes", [])
    return mean_std((e[metric] for e in episodes if metric in e), finite=True)[0]


def band_order(runs: Sequence[Mapping[str, Any]], names: Sequence[str]) -> list[str]:
    """The settings whose records name an uncertainty band, from the lowest band to the highest."""
    bands: dict[str, tuple[float, float]] = {}
    for r in runs:
        for name in names:
            band = r["settings"].get(name, {}).get("band")
            if band:
                bands[name] = (float(band["low"]), float(band["high"]))
    return sorted(bands, key=lambda n: bands[n])


def trend_test(per_seed: Mapping[str, Mapping[int, float]], order: Sequence[str]) -> dict[str, Any]:
    """Page's L test that ``per_seed[setting][seed]`` grows along ``order`` (the bands from low
    to high), over the seeds that ran every setting of ``order``."""
    from scipy import stats

    seeds = sorted(set.intersection(*(set(per_seed[n]) for n in order))) if order else []
    if len(order) < 3:
        return not_computed(len(order), 3, "banded settings")
    if len(seeds) < MIN_SEEDS_TREND:
        return not_computed(len(seeds), MIN_SEEDS_TREND)
    data = np.array([[per_seed[n][s] for n in order] for s in seeds])
    result = stats.page_trend_test(data)
    return {
        "statistic": float(result.statistic),
        "p_value": float(result.pvalue),
        "n": len(seeds),
        "order": list(order),
        "note": "Page's L test: the metric grows from the lowest band to the highest (paired by seed)",
    }


def across_seeds(runs: Sequence[Mapping[str, Any]], names: Sequence[str]) -> dict[str, Any]:
    """Per setting the per-seed means of :data:`TESTED`, their mean ± std across seeds and paired
    tests against ``names[0]``; and per metric the trend test over the banded settings.

    Examples:
        >>> runs = [{"seed": s, "settings": {
        ...     "baseline": {"episodes": [{"prediction_mse": 2.0 + s, "real_cost": 1.0}]},
        ...     "u_low": {"episodes": [{"prediction_mse": 1.0 + s, "real_cost": 1.0}]}}}
        ...     for s in range(3)]
        >>> out = across_seeds(runs, ["baseline", "u_low"])
        >>> out["settings"]["u_low"]["per_seed"]["prediction_mse"], out["reference"]
        ([1.0, 2.0, 3.0], 'baseline')
    """
    reference = names[0]
    per_seed = {
        metric: {
            name: {
                r["seed"]: seed_mean(r["settings"][name], metric)
                for r in runs
                if name in r["settings"]
            }
            for name in names
        }
        for metric in TESTED
    }
    settings: dict[str, Any] = {}
    for name in names:
        entry: dict[str, Any] = {"seeds": sorted(per_seed[TESTED[0]][name]), "per_seed": {}}
        entry["mean"], entry["std"], entry["vs_reference"] = {}, {}, {}
        for metric in TESTED:
            values = per_seed[metric][name]
            entry["per_seed"][metric] = [values[s] for s in entry["seeds"]]
            entry["mean"][metric], entry["std"][metric] = mean_std(values.values())
            if name != reference:
                ref = per_seed[metric][reference]
                common = [s for s in entry["seeds"] if s in ref]
                entry["vs_reference"][metric] = paired_tests(
                    [values[s] for s in common], [ref[s] for s in common]
                )
        settings[name] = entry
    order = band_order(runs, names)
    trend = {metric: trend_test(per_seed[metric], order) for metric in TESTED}
    return {"reference": reference, "settings": settings, "trend": trend}
