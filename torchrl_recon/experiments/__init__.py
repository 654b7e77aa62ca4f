"""The paper's experiments (and the calibrate experiment), resumable, launched from YAML recipes.

Reads top down: the CLI → :mod:`.registry` (every experiment kind) → a kind (:mod:`.explore`,
:mod:`.control`, :mod:`.calibrate`: an :class:`~.experiment_type.ExperimentType`) → its stages
(``*_stages``, each taking the run's :class:`~.context.RunContext`) → the shared builders
(:mod:`.common`) and the library.

Importing this package imports nothing heavy: the public names below load on first use.
"""

import importlib

_HOMES = {
    "ExperimentType": "experiment_type",
    "RunContext": "context",
    "get_type": "registry",
    "load_recipe": "recipe",
    "run": "runner",
}
__all__ = list(_HOMES)


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_HOMES[name]}"), name)
