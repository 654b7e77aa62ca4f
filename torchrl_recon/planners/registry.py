"""The planners a recipe can name: ``kind`` is a key of :data:`PLANNERS` or ``module:Class``.

Adding a shipped planner: its module, one line in :data:`PLANNERS`, and its tests. A user's own
planner needs no line here: a recipe names it as ``my_planners:MyPlanner`` (a subclass of
:class:`~torchrl_recon.planners.PlannerBase` in a module on ``PYTHONPATH``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torchrl_recon.planners.base import PlannerBase
from torchrl_recon.planners.cem import CEMPlanner
from torchrl_recon.planners.gradient import GradientPlanner
from torchrl_recon.planners.icem import ICEMPlanner
from torchrl_recon.planners.mppi import MPPIPlanner
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import PlanningModel
from torchrl_recon.planners.shooting import RandomShootingPlanner
from torchrl_recon.plugins import check_keywords, resolve_class

__all__ = ["PLANNERS", "check_planner_kwargs", "get_planner_class", "make_planner"]

PLANNERS: dict[str, type[PlannerBase]] = {
    "shooting": RandomShootingPlanner,
    "cem": CEMPlanner,
    "icem": ICEMPlanner,
    "mppi": MPPIPlanner,
    "gradient": GradientPlanner,
}
"""The shipped planners by the name a recipe's ``planner.kind`` gives them."""


def get_planner_class(kind: str) -> type[PlannerBase]:
    """The planner class ``kind`` names: a key of :data:`PLANNERS` or ``module:Class``.

    Raises:
        ValueError: one line: unknown name, a class that cannot be imported, or one that is
            not a :class:`PlannerBase`.

    Examples:
        >>> get_planner_class("cem").__name__
        'CEMPlanner'
        >>> get_planner_class("torchrl_recon.planners:GradientPlanner").__name__
        'GradientPlanner'
        >>> get_planner_class("mpc")
        Traceback (most recent call last):
        ...
        ValueError: unknown planner 'mpc'; expected one of ['cem', 'gradient', 'icem', 'mppi', 'shooting'] or 'module:Class' (a subclass of torchrl_recon.planners.base.PlannerBase in a module on PYTHONPATH).
    """
    return resolve_class(kind, PLANNERS, PlannerBase, "planner")


def check_planner_kwargs(cls: type[PlannerBase], kwargs: Mapping[str, Any]) -> None:
    """Check that ``cls(model, objective, **kwargs)`` binds (see
    ``torchrl_recon.plugins.check_keywords``).

    Raises:
        TypeError: one line naming the keywords at fault and those ``cls`` accepts.
    """
    if not (isinstance(cls, type) and issubclass(cls, PlannerBase)):
        raise TypeError(
            f"cls must be a PlannerBase subclass (get_planner_class(kind)), got {cls!r}."
        )
    check_keywords(cls, kwargs, positional=2)


def make_planner(
    kind: str, model: PlanningModel, objective: Objective, **kwargs: Any
) -> PlannerBase:
    """Build the planner ``kind`` names as ``Class(model, objective, **kwargs)``.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> model = PlanningModel(LSTMWorldModel(12, 4), drone_cost)
        >>> planner = make_planner("cem", model, Objective(), horizon=5, num_elites=10)
        >>> type(planner).__name__, planner.horizon, planner.num_elites
        ('CEMPlanner', 5, 10)
    """
    cls = get_planner_class(kind)
    check_planner_kwargs(cls, kwargs)
    return cls(model, objective, **kwargs)
