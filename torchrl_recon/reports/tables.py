"""Plain-text tables: number formatting and column alignment shared by the experiment kinds."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any


def fmt(x: Any, digits: int = 4) -> str:
    """A number with ``digits`` significant digits (scientific when tiny or huge), ``-`` for None.

    Examples:
        >>> fmt(0.123456), fmt(1e-5), fmt(None), fmt(float("nan")), fmt("x")
        ('0.1235', '1.000e-05', '-', 'nan', 'x')
    """
    if x is None:
        return "-"
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(v):
        return "nan"
    if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
        return f"{v:.{max(digits - 1, 1)}e}"
    return f"{v:.{digits}g}"


def pm(mean: Any, std: Any) -> str:
    """``mean ± std``, each by :func:`fmt`."""
    return f"{fmt(mean)} ± {fmt(std)}"


def render(header: Sequence[str], rows: Sequence[Sequence[str]], title: str | None = None) -> str:
    """Columns aligned under ``header`` and a rule, below ``title`` if given.

    Examples:
        >>> render(["a", "b"], [["1", "2"]], title="t").splitlines()
        ['t', 'a  b', '----', '1  2']
    """
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows, strict=True)]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    out = [line, "-" * len(line)]
    out += ["  ".join(str(c).ljust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(([title] if title is not None else []) + out)
