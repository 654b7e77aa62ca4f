"""Statistics across seeds: paired tests (t, Wilcoxon) and Page's trend test of per-seed
numbers; and how sure Table 1 is: the mean per-seed ratio with a bootstrap interval, the
direction of each seed, the effect size, and how many seeds the observed spread needs to
detect the paper's effect.

Each seed (one repeat of the whole experiment) gives one pair: the mean validation MSE of the
random arm and of the active arm over its retrainings.

The power statement asks: if the true effect were the paper's (active = ``r`` × random, ``r``
from its Table 1), how many seeds would a two-sided paired t-test at ``alpha`` need to find it
with probability ``power``, when the per-seed differences spread as much as ours do? The
paper's effect in our units is ``(r − 1) × mean(random)``, its standardised size ``d_z`` that
over the sample std of our per-seed differences, and the power of ``n`` seeds the noncentral
t's: ``P(|T| > t_{1−alpha/2, n−1})`` with ``T ~ t'(n − 1, d_z √n)``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

PAPER_RATIOS: dict[str, float] = {
    "industrial_benchmark": 26.2 / 44.8,
    "drone": 7.6 / 10.3,
    "minitaur": 6.4 / 7.5,
}
"""Active / random of the paper's Table 1 (means of 5 repeats): IB 26.2 / 44.8 = 0.585, Drone
7.6 / 10.3 = 0.738, Minitaur 6.4 / 7.5 = 0.853."""

CONFIDENCE = 0.95
N_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
"""The bootstrap interval: 95%, percentile method, 10,000 resamples of the seeds, generator
seeded with 0 (the same numbers give the same interval)."""

ALPHA, POWER = 0.05, 0.80
"""The power statement's two-sided level and power."""

MAX_SEEDS = 1_000_000
"""Above this many seeds the power statement says "more than"."""

MIN_SEEDS_TTEST, MIN_SEEDS_WILCOXON, MIN_SEEDS_TREND = 2, 5, 2
"""The fewest pairs a paired t-test, a Wilcoxon signed-rank test and a trend test need."""


def not_computed(n: int, minimum: int, what: str = "seeds") -> dict[str, Any]:
    """A test entry for too little data: NaN statistic and p-value, and why.

    Examples:
        >>> not_computed(1, 2)["note"]
        'not computed: needs at least 2 seeds, got 1'
    """
    nan = float("nan")
    note = f"not computed: needs at least {minimum} {what}, got {n}"
    return {"statistic": nan, "p_value": nan, "n": n, "note": note}


def _test(result: Any, n: int, note: str, **extra: Any) -> dict[str, Any]:
    return {"statistic": float(result.statistic), "p_value": float(result.pvalue), "n": n,
            **extra, "note": note}  # fmt: skip


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

    n, out = len(a), {}
    if n >= MIN_SEEDS_TTEST:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out["paired_t"] = _test(stats.ttest_rel(a, b), n, t_note)
    else:
        out["paired_t"] = not_computed(n, MIN_SEEDS_TTEST)
    if n < MIN_SEEDS_WILCOXON:
        out["wilcoxon"] = not_computed(n, MIN_SEEDS_WILCOXON)
    elif np.all(np.subtract(a, b) == 0):
        note = "all paired differences are zero"
        out["wilcoxon"] = {"statistic": float("nan"), "p_value": 1.0, "n": n, "note": note}
    else:
        note = "Wilcoxon signed-rank test across seeds (two-sided)"
        out["wilcoxon"] = _test(stats.wilcoxon(a, b), n, note)
    return out


def trend_test(per_seed: Mapping[str, Mapping[int, float]], order: Sequence[str]) -> dict[str, Any]:
    """Page's L test that ``per_seed[name][seed]`` grows along ``order`` (from 3 names), over
    the seeds that have every name of ``order``.

    Examples:
        >>> up = {"lo": {0: 1.0, 1: 2.0}, "mid": {0: 2.0, 1: 3.0}, "hi": {0: 3.0, 1: 4.0}}
        >>> trend_test(up, ["lo", "mid", "hi"])["statistic"]
        28.0
    """
    from scipy import stats

    seeds = sorted(set.intersection(*(set(per_seed[n]) for n in order))) if order else []
    if len(order) < 3:
        return not_computed(len(order), 3, "banded settings")
    if len(seeds) < MIN_SEEDS_TREND:
        return not_computed(len(seeds), MIN_SEEDS_TREND)
    data = np.array([[per_seed[n][s] for n in order] for s in seeds])
    note = "Page's L test: the metric grows from the lowest band to the highest (paired by seed)"
    return _test(stats.page_trend_test(data), len(seeds), note, order=list(order))


def _pairs(active: Sequence[float], random: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    a, r = np.asarray(active, dtype=np.float64), np.asarray(random, dtype=np.float64)
    if a.shape != r.shape or a.ndim != 1:
        raise ValueError(
            f"active and random need one value per seed each, got {a.shape}, {r.shape}"
        )
    return a, r


def bootstrap_ci(
    values: Sequence[float],
    *,
    confidence: float = CONFIDENCE,
    n_resamples: int = N_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> dict[str, Any]:
    """Percentile bootstrap interval of the mean of ``values`` (``scipy.stats.bootstrap``),
    resampling with a generator seeded with ``seed``: reproducible.

    Fewer than 2 values have no interval (NaN, with a note); values all equal give the value.

    Examples:
        >>> ci = bootstrap_ci([0.9, 0.95, 1.0, 0.96, 0.84])
        >>> round(ci["low"], 3), round(ci["high"], 3)
        (0.876, 0.974)
    """
    from scipy import stats

    x = np.asarray(values, dtype=np.float64)
    out: dict[str, Any] = {
        "confidence": confidence,
        "method": "percentile bootstrap over seeds",
        "n_resamples": n_resamples,
        "seed": seed,
    }
    if x.size < 2:
        nan = float("nan")
        return {
            "low": nan,
            "high": nan,
            **out,
            "note": f"not computed: needs at least 2 seeds, got {x.size}",
        }
    if np.all(x == x[0]):
        return {"low": float(x[0]), "high": float(x[0]), **out}
    result = stats.bootstrap(
        (x,),
        np.mean,
        n_resamples=n_resamples,
        confidence_level=confidence,
        method="percentile",
        random_state=np.random.default_rng(seed),
    )
    ci = result.confidence_interval
    return {"low": float(ci.low), "high": float(ci.high), **out}


def directions(active: Sequence[float], random: Sequence[float]) -> dict[str, int]:
    """How many seeds have the active arm lower (the paper's way), higher, or equal.

    Examples:
        >>> directions([1.0, 2.0, 3.0], [2.0, 2.0, 1.0])
        {'active_lower': 1, 'active_higher': 1, 'equal': 1}
    """
    a, r = _pairs(active, random)
    return {
        "active_lower": int(np.sum(a < r)),
        "active_higher": int(np.sum(a > r)),
        "equal": int(np.sum(a == r)),
    }


def cohens_dz(active: Sequence[float], random: Sequence[float]) -> float:
    """Cohen's ``d_z`` of the paired differences ``active − random``: their mean over their
    sample std (ddof = 1); NaN from fewer than 2 seeds or no spread.

    Examples:
        >>> round(cohens_dz([1.0, 2.0, 4.0], [2.0, 4.0, 5.0]), 4)
        -2.3094
    """
    a, r = _pairs(active, random)
    d = a - r
    if d.size < 2:
        return float("nan")
    sd = float(np.std(d, ddof=1))
    return float(np.mean(d)) / sd if sd > 0 else float("nan")


def paired_t_power(dz: float, n: int, alpha: float = ALPHA) -> float:
    """Power of a two-sided paired t-test of ``n`` pairs at level ``alpha`` when the true
    standardised effect is ``dz``: ``P(|T| > t_{1−alpha/2, n−1})``, ``T`` noncentral t with
    ``n − 1`` degrees of freedom and noncentrality ``dz √n``.

    Examples:
        >>> round(paired_t_power(0.5, 34), 4)  # the textbook case: d = 0.5 needs 34 pairs
        0.8078
    """
    from scipy import stats

    if n < 2:
        return float("nan")
    df, nc = n - 1, abs(dz) * math.sqrt(n)
    crit = stats.t.ppf(1 - alpha / 2, df)
    wrong_side = float(stats.nct.cdf(-crit, df, nc))  # below 1e-15 it can come back NaN
    return float(stats.nct.sf(crit, df, nc)) + (wrong_side if math.isfinite(wrong_side) else 0.0)


def seeds_needed(dz: float, alpha: float = ALPHA, power: float = POWER) -> int | None:
    """The fewest pairs (from 2) whose two-sided paired t-test at ``alpha`` has at least
    ``power`` against the effect ``dz``; None when ``dz`` is 0 or not finite, or more than
    :data:`MAX_SEEDS` would be needed.

    Examples:
        >>> seeds_needed(0.5), seeds_needed(0.8), seeds_needed(1.0)
        (34, 15, 10)
    """
    if not math.isfinite(dz) or dz == 0:
        return None
    if paired_t_power(dz, MAX_SEEDS, alpha) < power:
        return None
    low, high = 1, 2  # power(low) < power <= power(high), power grows with n
    while paired_t_power(dz, high, alpha) < power:
        low, high = high, high * 2
    while high - low > 1:
        mid = (low + high) // 2
        if paired_t_power(dz, mid, alpha) >= power:
            high = mid
        else:
            low = mid
    return high


def power_statement(
    active: Sequence[float],
    random: Sequence[float],
    paper_ratio: float | None,
    *,
    alpha: float = ALPHA,
    power: float = POWER,
) -> dict[str, Any]:
    """How many seeds the observed spread needs to detect the paper's ratio: the paper's
    effect in our units ``(paper_ratio − 1) × mean(random)`` over the sample std of our paired
    differences is ``effect_dz``; ``seeds_needed`` is :func:`seeds_needed` of it and
    ``power_now`` the power of the seeds we have.

    Examples:
        >>> s = power_statement([7.0, 8.0, 8.0, 9.0, 6.0], [10.0, 12.0, 11.0, 13.0, 9.0], 0.75)
        >>> round(s["effect_dz"], 3), s["seeds_needed"]
        (-5.021, 3)
    """
    a, r = _pairs(active, random)
    n = int(a.size)
    out: dict[str, Any] = {"paper_ratio": paper_ratio, "alpha": alpha, "power": power, "n_seeds": n}
    nan = float("nan")
    if paper_ratio is None:
        return {**out, "effect_dz": nan, "seeds_needed": None, "power_now": nan,
                "note": "no ratio of the paper for this environment"}  # fmt: skip
    sd = float(np.std(a - r, ddof=1)) if n > 1 else nan
    effect = (paper_ratio - 1.0) * float(np.mean(r)) if n else nan
    if not (math.isfinite(sd) and sd > 0):
        return {**out, "effect": effect, "sd_differences": sd, "effect_dz": nan,
                "seeds_needed": None, "power_now": nan,
                "note": "not computed: needs at least 2 seeds whose differences vary"}  # fmt: skip
    dz = effect / sd
    needed = seeds_needed(dz, alpha, power)
    observed_dz = float(np.mean(a - r)) / sd
    needed_observed = seeds_needed(observed_dz, alpha, power)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        now = paired_t_power(dz, n, alpha)

    def seeds(k: int | None) -> str:
        return f"{k} seeds" if k is not None else f"more than {MAX_SEEDS:,} seeds"

    note = (
        f"with the observed spread (sd of active − random {sd:.3g}), detecting the paper's "
        f"ratio {paper_ratio:.3f} (d_z = {abs(dz):.2f}) with a paired t-test at alpha = "
        f"{alpha:g} and {power:.0%} power needs {seeds(needed)} ({n} give {now:.0%}); "
        f"the observed effect (d_z = {abs(observed_dz):.2f}) needs {seeds(needed_observed)}"
    )
    return {**out, "effect": effect, "sd_differences": sd, "effect_dz": dz,
            "seeds_needed": needed, "power_now": now, "observed_dz": observed_dz,
            "seeds_needed_observed": needed_observed, "note": note}  # fmt: skip


def significance(
    active: Sequence[float], random: Sequence[float], env: str | None = None
) -> dict[str, Any]:
    """Everything above for one environment's per-seed arm means.

    Returns:
        ``mean_ratio`` (the mean of the per-seed ratios active / random) and its bootstrap
        ``ratio_ci``; ``directions``; ``effect_size`` (Cohen's ``d_z``); ``power`` against the
        paper's ratio for ``env`` (:data:`PAPER_RATIOS`).

    Examples:
        >>> s = significance([7.0, 8.0, 8.0, 9.0, 6.0], [10.0, 12.0, 11.0, 13.0, 9.0], "drone")
        >>> round(s["mean_ratio"], 4), s["directions"]["active_lower"], s["power"]["seeds_needed"]
        (0.6906, 5, 3)
    """
    a, r = _pairs(active, random)
    ratios = a / r
    return {
        "mean_ratio": float(np.mean(ratios)) if ratios.size else float("nan"),
        "ratio_ci": bootstrap_ci(ratios),
        "directions": directions(a, r),
        "effect_size": {
            "cohens_dz": cohens_dz(a, r),
            "note": "Cohen's d_z: mean / sample std of the per-seed differences active − random",
        },
        "power": power_statement(a, r, PAPER_RATIOS.get(env) if env else None),
    }
