"""The paper's experiments (and the calibrate and online ones), resumable, run from YAML recipes.

Reads top down: the CLI → ``registry`` (every kind) → a kind (``explore``, ...) → its
stages (each taking the run's :class:`RunContext`) → the builders they share (``recipe_env``,
``recipe_models``, ``recipe_planning``, ``random_data``, ``fit_stages``, ...).
Importing this package imports nothing heavy: the names below load on first use.
"""

import importlib

_HOMES = {"ExperimentType": "experiment_type", "RecipeLoader": "context", "RunContext": "context"}
_HOMES.update(get_type="registry", load_recipe="recipe", run="runner")
__all__ = list(_HOMES)


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_HOMES[name]}"), name)
