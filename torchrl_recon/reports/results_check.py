"""Results are data too: ``summarize`` refuses a ``results.json`` with a number that is not
finite where its kind does not write NaN on purpose, or that disagrees with the numbers it
repeats; one :class:`~torchrl_recon.errors.DamagedFileError` names the file, key and numbers.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator, Mapping
from fnmatch import fnmatchcase
from typing import Any

from torchrl_recon.errors import DamagedFileError

MEAN_REL_TOL = 1e-5
"""Relative tolerance of a recorded mean against the mean of its values: explore's arm means
are taken in float32 (about 1e-7 relative), so 1e-5 allows that and nothing a hand would write."""

RATIO_REL_TOL = 1e-9
"""Relative tolerance of a recorded ratio against the quotient of the recorded means."""

NAN_ALLOWED: dict[str, str] = {
    "explore": "test.statistic test.p_value data.active_feasible_fraction arms.*.std",
    "control": "settings.*.episodes* settings.*.mean.* settings.*.std.* trajectory_example.*",
    "calibrate": "estimators.* timing.*",
}
"""Per experiment kind, the keys (:func:`fnmatch.fnmatchcase` patterns) where NaN is a result;
infinity is never one: explore's test and its std from one retraining, its feasible fraction
with no plan made; control's metrics of an episode without a planned step (its means are
checked against the episodes) and its trajectory example; calibrate's metrics that could not be
computed on the data drawn, and its timings."""


def numbers(value: Any, key: str = "") -> Iterator[tuple[str, float]]:
    """Every float below ``value`` with its key as one would write it.

    Examples:
        >>> list(numbers({"arms": {"active": {"mse": [1, 2.0]}}}))
        [('arms.active.mse[1]', 2.0)]
    """
    if isinstance(value, Mapping):
        for k, v in value.items():
            yield from numbers(v, f"{key}.{k}" if key else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from numbers(v, f"{key}[{i}]")
    elif isinstance(value, float):  # bools and ints are always finite
        yield key, value


def _fail(source: str, what: str) -> None:
    remedy = "re-run the experiment to write it again, or leave that run directory out"
    raise DamagedFileError(f"{source}: {what}; {remedy}.")


def check_finite(results: Mapping[str, Any], source: str) -> None:
    """No infinity anywhere, and NaN only at the kind's :data:`NAN_ALLOWED` key paths.

    Examples:
        >>> check_finite({"experiment": "explore", "ratio": float("inf")}, "r.json")
        Traceback (most recent call last):
        ...
        torchrl_recon.errors.DamagedFileError: r.json: ratio is inf, not a finite number; ...
    """
    allowed = NAN_ALLOWED.get(str(results.get("experiment")), "").split()
    for key, value in numbers(results):
        nan_allowed = math.isnan(value) and any(fnmatchcase(key, p) for p in allowed)
        if not math.isfinite(value) and not nan_allowed:
            _fail(source, f"{key} is {value}, not a finite number")


def _agrees(source: str, name: str, recorded: Any, expected: float, why: str, rel_tol: float):
    """Fail unless ``recorded`` is a number close to ``expected`` (NaN where that is NaN)."""
    ok = isinstance(recorded, (int, float)) and (
        math.isnan(recorded)
        if math.isnan(expected)
        else math.isclose(recorded, expected, rel_tol=rel_tol, abs_tol=1e-300)
    )
    if not ok:
        _fail(source, f"{name} is {recorded!r}, but {why} is {expected!r}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _mean(values: list[float]) -> float:
    return math.fsum(values) / len(values) if values else float("nan")


def _get(results: Mapping[str, Any], path: tuple[str, ...], source: str) -> Any:
    value: Any = results
    for k in path:
        if not isinstance(value, Mapping) or k not in value:
            _fail(source, f"it has no {'.'.join(path)}")
        value = value[k]
    return value


def check_explore(results: Mapping[str, Any], source: str) -> None:
    """Each arm's ``mean`` equals the mean of its ``mse`` values (float32 rounding allowed);
    ``ratio``, where recorded, equals ``active mean / random mean``; the arms' std is finite
    from 2 values."""
    means = {}
    for arm in ("random", "active"):
        values = _get(results, ("arms", arm, "mse"), source)
        if not (isinstance(values, list) and values) or not all(map(_is_number, values)):
            _fail(source, f"arms.{arm}.mse is not a list of numbers")
        mean, n = _get(results, ("arms", arm, "mean"), source), len(values)
        why = f"the mean of its {n} per-retraining values (arms.{arm}.mse)"
        _agrees(source, f"arms.{arm}.mean", mean, _mean(values), why, MEAN_REL_TOL)
        std = results["arms"][arm].get("std")
        if n > 1 and isinstance(std, float) and math.isnan(std):
            _fail(source, f"arms.{arm}.std is nan with {n} per-retraining values")
        means[arm] = float(mean)
    if "ratio" in results:  # else summarize computes the ratio from the means
        expected = means["active"] / means["random"] if means["random"] else float("nan")
        why = "arms.active.mean / arms.random.mean"
        _agrees(source, "ratio", results["ratio"], expected, why, RATIO_REL_TOL)


def check_control(results: Mapping[str, Any], source: str) -> None:
    """Each setting's ``mean`` of each metric equals the mean over its episodes' finite values
    (NaN when there is none)."""
    settings = _get(results, ("settings",), source)
    if not isinstance(settings, Mapping):
        _fail(source, "settings is not a mapping of setting names")
    for name, s in settings.items():
        episodes = s.get("episodes") if isinstance(s, Mapping) else None
        if not isinstance(episodes, list) or not isinstance(s.get("mean"), Mapping):
            _fail(source, f"settings.{name} has no episodes and mean")
        for metric, mean in s["mean"].items():
            values = [
                float(e[metric])
                for e in episodes
                if isinstance(e, Mapping) and isinstance(e.get(metric), (int, float))
            ]
            expected = _mean([v for v in values if not math.isnan(v)])
            why = f"the mean over its {len(values)} episodes"
            _agrees(source, f"settings.{name}.mean.{metric}", mean, expected, why, MEAN_REL_TOL)


KIND_CHECKS: dict[str, Callable[[Mapping[str, Any], str], None]] = {
    "explore": check_explore,
    "control": check_control,
}
"""The consistency checks of each kind beyond :func:`check_finite` (calibrate has none)."""


def check_results(results: Mapping[str, Any], path: str | os.PathLike[str]) -> None:
    """Refuse a ``results.json`` whose numbers are not finite where they must be, or disagree:
    one :class:`~torchrl_recon.errors.DamagedFileError` naming the file, the key and the numbers.

    Examples:
        >>> arm = {"mse": [1.0, 3.0], "mean": 2.0, "std": 1.4}
        >>> ok = {"experiment": "explore", "arms": {"random": arm, "active": arm}, "ratio": 1.0}
        >>> check_results(ok, "seed0/results.json")
        >>> check_results({**ok, "ratio": 0.5}, "seed0/results.json")
        Traceback (most recent call last):
        ...
        torchrl_recon.errors.DamagedFileError: seed0/results.json: ratio is 0.5, but ...
    """
    source = os.fspath(path)
    check_finite(results, source)
    if check := KIND_CHECKS.get(str(results.get("experiment"))):
        check(results, source)
