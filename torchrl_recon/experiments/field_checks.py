"""Value checks declared next to the schema field they guard (``count(1)``, ``positive(3e-3)``,
``checked(0.1, in_open_unit)``; every float finite unless its field says otherwise; a
dataclass's ``more_errors(key)`` for checks across its fields), and :func:`schema_errors`, the walk
that runs them all on a merged recipe. Choices are ``Enum`` fields, refused by the merge."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from enum import Enum
from typing import Any

from omegaconf import DictConfig, OmegaConf

Check = Callable[[Any], "str | None"]
"""A field's check: what the value should be when it is refused, None when it fits."""


class Choice(str, Enum):
    """A choice of a recipe key: written as its plain string in YAML and ``config.yaml``,
    equal to it, and shown as it everywhere (``str``, ``repr``, f-strings, JSON)."""

    def __str__(self) -> str:
        return self.value

    def __repr__(self) -> str:
        return repr(self.value)


def choice(name: str, values: str | list[str], module: str) -> Any:
    """A :class:`Choice` ``Enum`` called ``name`` of ``values`` (a space-separated string).

    Examples:
        >>> choice("Mode", "fast slow", __name__).fast
        'fast'
    """
    values = values.split() if isinstance(values, str) else values
    return Choice(name, [(v, v) for v in values], module=module)


def checked(default: Any = dataclasses.MISSING, check: Check | None = None, **kw: Any) -> Any:
    """A dataclass field whose value (when not None) must pass ``check``; ``finite=False``
    lets its floats be infinite (another check handles them); ``factory`` gives a mutable
    default."""
    metadata = {"check": check, "finite": kw.pop("finite", True)}
    factory = kw.pop("factory", dataclasses.MISSING)
    return dataclasses.field(default=default, default_factory=factory, metadata=metadata)


def at_least(low: float, why: str = "") -> Check:
    """``value >= low``."""
    return lambda v: None if v >= low else f">= {low}{why}"


def above(low: float, why: str = "") -> Check:
    """``value > low``."""
    return lambda v: None if v > low else f"> {low}{why}"


def count(default: Any, low: int = 1) -> Any:
    """An integer field of at least ``low`` (1 by default)."""
    return checked(default, at_least(low))


def positive(default: Any) -> Any:
    """A number field above 0."""
    return checked(default, above(0))


def schema_errors(cfg: DictConfig) -> list[str]:
    """Every problem the schema's own checks find in a merged, resolved recipe, one message
    each, naming the full key (``'settings[1].band.high'``).

    Examples:
        >>> from torchrl_recon.experiments.config import ExploreConfig
        >>> cfg = OmegaConf.structured(ExploreConfig(output_dir="out"))
        >>> cfg.guided.ratio, cfg.training.world_model.steps = float("nan"), 0
        >>> schema_errors(cfg)
        ["'training.world_model.steps' must be >= 1, got 0", "'guided.ratio' must be a finite number, got nan"]
    """
    errors: list[str] = []
    _walk(OmegaConf.to_object(cfg), "", errors)
    return errors


def _walk(obj: Any, key: str, errors: list[str]) -> None:
    if isinstance(obj, list):
        for i, item in enumerate(obj):
            _walk(item, f"{key}[{i}]", errors)
        return
    if not dataclasses.is_dataclass(obj):
        return
    for f in dataclasses.fields(obj):
        value, sub = getattr(obj, f.name), f"{key}.{f.name}" if key else f.name
        bad = nonfinite(value, sub) if f.metadata.get("finite", True) else []
        errors.extend(finite_error(k, v) for k, v in bad)
        check = f.metadata.get("check")
        if check is not None and value is not None and not bad:
            expected = check(value)
            if expected:
                errors.append(f"'{sub}' must be {expected}, got {value!r}")
        _walk(value, sub, errors)
    for sub, text in getattr(obj, "more_errors", lambda key: ())(key):
        errors.append(f"'{key}.{sub}'{text}" if sub else f"'{key}'{text}")


def nonfinite(value: Any, key: str) -> list[tuple[str, float]]:
    """``(key, value)`` of every NaN or ±inf in a plain value: dicts and lists at any depth (a
    dataclass, and a list of them, is walked by its own fields).

    Examples:
        >>> nonfinite({"a": [1.0, float("inf")], "b": float("nan")}, "x")
        [('x.a[1]', inf), ('x.b', nan)]
    """
    if isinstance(value, float):
        return [] if math.isfinite(value) else [(key, value)]
    if isinstance(value, dict):
        items = [(f"{key}.{k}" if key else str(k), v) for k, v in value.items()]
    elif isinstance(value, list) and not any(dataclasses.is_dataclass(v) for v in value):
        items = [(f"{key}[{i}]", v) for i, v in enumerate(value)]
    else:
        return []
    return [bad for k, v in items for bad in nonfinite(v, k)]


def finite_error(key: str, value: float) -> str:
    """The message of a NaN or infinite ``value`` at ``key``."""
    return f"'{key}' must be a finite number, got {value}"


def finite(*values: Any) -> bool:
    """No value is a NaN or infinite float (for ``more_errors``: a non-finite value is
    reported once, by the walk)."""
    return not any(isinstance(v, float) and not math.isfinite(v) for v in values)
