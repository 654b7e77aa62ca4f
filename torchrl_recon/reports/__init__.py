"""Results read back: each kind's :class:`Report` (summary across seeds, tables, figures,
headline numbers), the checks of a ``results.json`` and ``torchrl-recon summarize``.

Examples:
    >>> from torchrl_recon.reports import get_report
    >>> get_report("explore").name
    'explore'
"""

from torchrl_recon.reports.registry import REPORTS, get_report
from torchrl_recon.reports.report import Report
from torchrl_recon.reports.results_check import check_results
from torchrl_recon.reports.summary import (
    find_results,
    format_table,
    read_results,
    save_figures,
    save_summary,
    summarize,
    summarize_by_kind,
)

__all__ = [
    "REPORTS",
    "Report",
    "check_results",
    "find_results",
    "format_table",
    "get_report",
    "read_results",
    "save_figures",
    "save_summary",
    "summarize",
    "summarize_by_kind",
]
