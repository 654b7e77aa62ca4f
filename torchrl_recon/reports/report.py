"""What a kind's report is: one :class:`Report` holds how its results are summarised across
seeds, shown as tables and figures, and logged."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Results = Mapping[str, Any]
Figures = list[tuple[str, "Figure"]]
"""Figures as (file name, figure) pairs."""


@dataclass(frozen=True)
class Report:
    """The report of one experiment kind.

    Attributes:
        name: the experiment kind (the results' ``experiment`` value).
        summarize_env: the across-seeds summary of one env's results.
        result_table: the text table of one results dict.
        summary_table: the text table of one :func:`~.summary.summarize` output.
        headline: the results' numbers logged as scalars (``results/<key>``).
        figures: the figures of one results dict.
        summary_figures: the figures of a summary, ``(summary, results)``.
        outcome: the headline numbers of a results dict when run as a child of another.
    """

    name: str
    summarize_env: Callable[[list[dict[str, Any]]], dict[str, Any]]
    result_table: Callable[[Results], str]
    summary_table: Callable[[Results], str]
    headline: Callable[[Results], dict[str, float]]
    figures: Callable[[Results], Figures] = lambda results: []
    summary_figures: Callable[[Results, list[Results]], Figures] = lambda s, r: []
    outcome: Callable[[Results], dict[str, Any]] | None = None

    @classmethod
    def of_module(cls, module: ModuleType, name: str) -> Report:
        """The report a module defines: each field it defines by name (``headline``, ...).

        Examples:
            >>> from torchrl_recon.reports import online
            >>> Report.of_module(online, "online").outcome is None
            True
        """
        found = {f.name: getattr(module, f.name) for f in fields(cls) if hasattr(module, f.name)}
        return cls(**{**found, "name": name})
