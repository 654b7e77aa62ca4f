"""The paper's experiments (and the estimator comparison), resumable, launched from YAML recipes.

Reads top down: the CLI → :mod:`.registry` (every experiment kind) → a kind
(:mod:`.explore`, :mod:`.control`, :mod:`.estimator_comparison`: an
:class:`~.experiment_type.ExperimentType`) → its stages (``*_stages``, each taking the run's
:class:`~.context.RunContext`) → the shared builders (:mod:`.common`) and the library.

Importing this package imports nothing heavy; import the modules you use.
"""

__all__ = [
    "ExperimentType",
    "RunContext",
    "get_type",
    "load_recipe",
    "run",
]


def __getattr__(name: str):
    """The public names, imported on first use (the package itself stays light)."""
    if name == "ExperimentType":
        from torchrl_recon.experiments.experiment_type import ExperimentType

        return ExperimentType
    if name == "RunContext":
        from torchrl_recon.experiments.context import RunContext

        return RunContext
    if name == "get_type":
        from torchrl_recon.experiments.registry import get_type

        return get_type
    if name == "load_recipe":
        from torchrl_recon.experiments.recipe import load_recipe

        return load_recipe
    if name == "run":
        from torchrl_recon.experiments.runner import run

        return run
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
