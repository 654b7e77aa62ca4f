"""Fixtures of the experiment tests: the scripts under docs/results, imported by file name."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

RESULTS_SCRIPTS = Path(__file__).resolve().parents[2] / "docs" / "results"


@pytest.fixture
def results_script():
    """``results_script("control_tables")`` imports ``docs/results/control_tables.py``."""

    def load(name: str) -> ModuleType:
        spec = importlib.util.spec_from_file_location(name, RESULTS_SCRIPTS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
