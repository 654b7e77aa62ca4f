"""Import a script of the repository (a benchmark, a docs/results helper) as a module."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_script(path: Path) -> ModuleType:
    """``path`` imported as the module named by its stem, registered in ``sys.modules`` (its
    dataclasses need it).

    Examples:
        >>> load_script(Path(__file__)).load_script.__name__
        'load_script'
    """
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
