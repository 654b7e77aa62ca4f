"""Counts cut into batches: episodes run ``num_envs`` at a time, exploration rounds, groups of
retrainings fitted as one population."""

from __future__ import annotations


def batches(count: int, size: int | None) -> list[range]:
    """``range(count)`` in batches of ``size`` (one batch if None; the last may be smaller).

    Examples:
        >>> [list(b) for b in batches(5, 2)], batches(3, None)
        ([[0, 1], [2, 3], [4]], [range(0, 3)])
    """
    size = size or count
    return [range(i, min(i + size, count)) for i in range(0, count, size)]
