"""The paper's experiments (and the calibrate and online ones), resumable, run from YAML recipes.

Reads top down: the CLI → :mod:`.registry` (every kind) → a kind (:mod:`.explore`, ...) → its
stages (``*_stages``, each taking the run's :class:`~.context.RunContext`) → :mod:`.common`.
Importing this package imports nothing heavy: the names below load on first use.
"""

import importlib

_HOMES = {"ExperimentType": "experiment_type", "RunContext": "context", "get_type": "registry"}
_HOMES.update(load_recipe="recipe", run="runner")
__all__ = list(_HOMES)


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_HOMES[name]}"), name)
