"""Random shooting: K uniform candidates, keep the best (Nagabandi et al. 2017)."""

from __future__ import annotations

import torch

from torchrl_recon.modules.checks import check_int
from torchrl_recon.planners.base import OnInfeasible, PlannerBase
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import PlanningModel


class RandomShootingPlanner(PlannerBase):
    """Sample ``num_candidates`` uniform action sequences and return the best feasible one.

    Args:
        model: the :class:`PlanningModel`.
        objective: the :class:`Objective`.

    Keyword Args:
        horizon: H.
        num_candidates: K.
        on_infeasible: ``"fallback"`` or ``"raise"`` (see :class:`PlannerBase`).

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> planner = RandomShootingPlanner(PlanningModel(LSTMWorldModel(12, 4), drone_cost), Objective(),
        ...                                 horizon=20, num_candidates=64)
        >>> planner.plan(torch.zeros(10, 12), torch.zeros(10, 4), torch.zeros(12)).actions.shape
        torch.Size([20, 4])
    """

    def __init__(
        self,
        model: PlanningModel,
        objective: Objective,
        *,
        horizon: int,
        num_candidates: int = 1000,
        on_infeasible: OnInfeasible = "fallback",
    ) -> None:
        super().__init__(model, objective, horizon=horizon, on_infeasible=on_infeasible)
        check_int("num_candidates", num_candidates)
        self.num_candidates = num_candidates

    @torch.inference_mode()
    def _optimise(self, context_obs, context_action, observation, init, state, generator):
        candidates = self._uniform(observation.shape[:-1], self.num_candidates, generator)
        prediction = self.model(context_obs, context_action, observation, candidates, state=state)
        return candidates, prediction, self._bounds(prediction)
