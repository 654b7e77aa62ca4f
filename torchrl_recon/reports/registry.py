"""The report of each experiment kind, by name. A new kind: a module defining its ``REPORT``,
listed below (its runner is in :mod:`torchrl_recon.experiments.registry`)."""

from __future__ import annotations

from typing import Any

from torchrl_recon.reports import calibrate, control, explore, online
from torchrl_recon.reports.report import Report

REPORTS: dict[str, Report] = {
    r.name: r for r in (explore.REPORT, control.REPORT, calibrate.REPORT, online.REPORT)
}
"""Every kind's report by name."""


def get_report(name: Any) -> Report:
    """The report of the experiment kind ``name``; a ValueError names the kinds there are.

    Examples:
        >>> get_report("online").name
        'online'
    """
    try:
        return REPORTS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"Unknown experiment kind {name!r} in results; expected one of {sorted(REPORTS)}."
        ) from None
