"""Fixtures of the experiment tests: the scripts under docs/results, imported by file name."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest

from tests.scripts import load_script

RESULTS_SCRIPTS = Path(__file__).resolve().parents[2] / "docs" / "results"


@pytest.fixture
def results_script():
    """``results_script("control_tables")`` imports ``docs/results/control_tables.py``."""

    def load(name: str) -> ModuleType:
        return load_script(RESULTS_SCRIPTS / f"{name}.py")

    return load
