"""The registry of experiment kinds, by name. A new kind: a module defining its ``EXPERIMENT``
(an :class:`~torchrl_recon.experiments.experiment_type.ExperimentType`), listed below, its report
(:mod:`torchrl_recon.reports.registry`) and its recipes (``experiment: <name>``)."""

from __future__ import annotations

from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments import calibrate, control, explore, online
from torchrl_recon.experiments.experiment_type import ExperimentType

EXPERIMENT_TYPES = {m.EXPERIMENT.name: m.EXPERIMENT for m in (explore, control, calibrate, online)}
"""Every experiment kind by name, in the order the CLI lists them."""


def get_type(name: str) -> ExperimentType:
    """The experiment kind ``name``; a :class:`RecipeError` names the kinds there are.

    Examples:
        >>> get_type("control").stage_list(None)
        ['random_data', 'models', 'setting_<setting>', 'random_policy']
    """
    try:
        return EXPERIMENT_TYPES[name]
    except (KeyError, TypeError):
        raise RecipeError(
            f"unknown experiment {name!r}; expected one of {sorted(EXPERIMENT_TYPES)}."
        ) from None
