"""Random shooting: K uniform candidates, keep the best (Nagabandi et al. 2017)."""

from __future__ import annotations

from torchrl_recon.modules.checks import check_int
from torchrl_recon.planners.base import OnInfeasible, PlannerBase
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import PlanningModel, check_block_rows, without_grad


class RandomShootingPlanner(PlannerBase):
    """Sample ``num_candidates`` uniform action sequences and return the best feasible one.

    Args:
        model: the :class:`PlanningModel`.
        objective: the :class:`Objective`.

    Keyword Args:
        horizon: H (steps planned ahead).
        num_candidates: K (candidate sequences).
        block_rows: evaluate the ``B·K`` candidate rows in blocks of about this many (see
            :class:`~torchrl_recon.planners.CEMPlanner`). "auto" (default): 1024 on the CPU, one pass on a GPU; None: one pass.
        on_infeasible: ``"fallback"`` or ``"raise"`` (see :class:`PlannerBase`).

    Examples:
        >>> import torch
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> world_model = LSTMWorldModel(12, 4)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> planner = RandomShootingPlanner(PlanningModel(world_model, drone_cost), Objective(),
        ...                                 horizon=20, num_candidates=64)
        >>> planner.plan(torch.zeros(10, 12), torch.zeros(10, 4), torch.zeros(12)).actions.shape
        torch.Size([20, 4])
    """

    compiles_whole_call = True  # tests/planners/test_plan_graph.py

    def __init__(
        self,
        model: PlanningModel,
        objective: Objective,
        *,
        horizon: int,
        num_candidates: int = 1000,
        block_rows: int | str | None = "auto",
        on_infeasible: OnInfeasible = "fallback",
    ) -> None:
        super().__init__(model, objective, horizon=horizon, on_infeasible=on_infeasible)
        check_int("num_candidates", num_candidates)
        check_block_rows(block_rows)  # resolved for the candidates' device at each call
        self.num_candidates, self.block_rows = num_candidates, block_rows

    @without_grad
    def _optimise(self, context_obs, context_action, observation, init, state, generator):
        candidates = self._uniform(observation.shape[:-1], self.num_candidates, generator)
        prediction = self.model(
            context_obs,
            context_action,
            observation,
            candidates,
            state=state,
            block_rows=self.block_rows,
        )
        return candidates, prediction, self._bounds(prediction)
