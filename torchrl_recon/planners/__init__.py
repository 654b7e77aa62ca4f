"""Batched MPC planners on one rollout engine, with uncertainty in the objective.

The package exports what a user calls: the planners, the engine they run on, the objective and
its band, the plan's result and errors, the relative β, and ``make_planner``. The rest is
public in its own module: the search state of the sampling loop (``planners.sampling``,
``planners.cem``, ``planners.base``), the registry (``planners.registry``), the bounds, β and
noise helpers (``planners.bounds``, ``planners.beta``, ``planners.noise``), the engine's
helpers (``planners.planning_model``), the speed paths (``planners.executors`` and the row-block
thread pool it uses, ``planners.elite_memory``) and the TorchRL adapters
(``planners.torchrl_models``, ``planners.model_env``).
"""

from __future__ import annotations

import importlib
import sys
import warnings

from torchrl_recon.planners.base import (
    InfeasiblePlanError,
    InfeasiblePlanWarning,
    PlannerBase,
    PlanResult,
)
from torchrl_recon.planners.beta import relative_beta
from torchrl_recon.planners.cem import CEMPlanner
from torchrl_recon.planners.executors import MOVED_FROM_PLANNERS
from torchrl_recon.planners.gradient import GradientPlanner
from torchrl_recon.planners.icem import ICEMPlanner
from torchrl_recon.planners.mppi import MPPIPlanner
from torchrl_recon.planners.objective import Objective, UncertaintyBand
from torchrl_recon.planners.planning_model import PlanningModel, Prediction
from torchrl_recon.planners.registry import make_planner
from torchrl_recon.planners.sampling import SamplingPlanner
from torchrl_recon.planners.shooting import RandomShootingPlanner

__all__ = [
    "CEMPlanner",
    "GradientPlanner",
    "ICEMPlanner",
    "InfeasiblePlanError",
    "InfeasiblePlanWarning",
    "MPPIPlanner",
    "Objective",
    "PlanResult",
    "PlannerBase",
    "PlanningModel",
    "Prediction",
    "RandomShootingPlanner",
    "SamplingPlanner",
    "UncertaintyBand",
    "make_planner",
    "relative_beta",
]

# Names this package exported before, and the module each is public in now (the speed paths'
# names: MOVED_FROM_PLANNERS). Importing one from here still works for one release, with a
# DeprecationWarning naming that module.
_MOVED = {
    "base": ("PlanFlags", "PlanOutput"),
    "beta": ("cost_to_u_ratio", "window_uncertainty"),
    "bounds": ("bounds_from_spec", "check_bounds_match"),
    "cem": ("Gaussian",),
    "elite_memory": ("EliteMemory",),
    "model_env": ("WorldModelPlanningEnv",),
    "noise": ("colored_noise",),
    "planning_model": ("TerminationFn", "check_step_fn"),
    "registry": ("PLANNERS", "check_planner_kwargs", "get_planner_class"),
    "sampling": ("Iteration",),
    "torchrl_models": (
        "BatchedWorldModelEnv",
        "CONTEXT_ACTION",
        "CONTEXT_OBS",
        "LSTMWorldModelModule",
        "TorchRLWorldModelAdapter",
    ),
}
_HOMES = {
    name: module
    for moved in (_MOVED, MOVED_FROM_PLANNERS)
    for module, names in moved.items()
    for name in names
}


def __getattr__(name: str):
    """A name this package no longer exports, from its module, with one DeprecationWarning.

    ``from torchrl_recon.planners import name`` asks twice: the import system first checks
    that the package has ``name`` (``hasattr`` in importlib's ``_handle_fromlist``), then the
    importing line reads it. Only the read warns, so the warning names the user's line.
    """
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    home = f"{__name__}.{_HOMES[name]}"
    value = getattr(importlib.import_module(home), name)
    caller = sys._getframe(1).f_code
    if caller.co_name != "_handle_fromlist" or "importlib" not in caller.co_filename:
        warnings.warn(
            f"{__name__}.{name} is deprecated; import it from {home}",
            DeprecationWarning,
            stacklevel=2,
        )
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
