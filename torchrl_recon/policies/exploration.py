"""Uncertainty-seeking exploration (paper §2.4, eq. 4) on the MPC policy."""

from __future__ import annotations

from torchrl_recon.modules.checks import check_int, check_real, check_type
from torchrl_recon.planners.base import PlannerBase
from torchrl_recon.planners.objective import Objective, UncertaintyBand
from torchrl_recon.policies.mpc import MPCPolicy


def exploration_objective(
    *, ratio: float = 1.2, cap: float | None = None, beta: float = 0.0
) -> Objective:
    """Objective of the exploration policy: α = 0, Σu in [ratio, cap] × the mean over sampled candidates.

    ``beta = 0`` takes any candidate in the band (the paper's "sample sequences whose cumulative
    uncertainty is 1.2–1.5 times the average"); ``beta = -1`` maximises Σu inside it (eq. 4 with
    the cautious cap).

    Examples:
        >>> exploration_objective(ratio=1.5, cap=3.0).band
        UncertaintyBand(low=1.5, high=3.0, kind='mean_ratio')
    """
    check_real("ratio", ratio, minimum=0, exclusive=True)
    if cap is not None:
        check_real("cap", cap)
    check_real("beta", beta)
    if beta > 0:
        raise ValueError(f"exploration seeks uncertainty: beta must be <= 0, got {beta}.")
    if cap is not None and cap < ratio:
        raise ValueError(f"cap={cap} must be at least ratio={ratio}.")
    return Objective(
        alpha=0.0, beta=beta, band=UncertaintyBand(low=ratio, high=cap, kind="mean_ratio")
    )


class ExplorationPolicy(MPCPolicy):
    """An :class:`MPCPolicy` that plans for high but capped uncertainty and executes plans open loop.

    The planner's objective must ignore reward (α = 0) and must not penalise uncertainty
    (β ≤ 0); build it with :func:`exploration_objective`. By default a whole plan is executed
    before re-planning (``replan="every_n"`` with ``replan_every = horizon``). Refit the world
    model and estimator on the grown buffer between collection rounds, and what was novel
    stops being novel (adaptive curiosity).

    Examples:
        >>> import torch
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
        >>> from torchrl_recon.planners import PlanningModel, RandomShootingPlanner
        >>> model = PlanningModel(LSTMWorldModel(12, 4, window=3), drone_cost,
        ...                       uncertainty=ReconstructionUncertainty(12, 4, window=3))
        >>> planner = RandomShootingPlanner(model, exploration_objective(ratio=1.2), horizon=10, num_candidates=64)
        >>> ExplorationPolicy(planner).replan_every
        10
    """

    def __init__(
        self,
        planner: PlannerBase,
        *,
        replan: str = "every_n",
        replan_every: int | None = None,
        **kwargs,
    ):
        check_type("planner", planner, PlannerBase, "a planner (a PlannerBase, e.g. CEMPlanner)")
        if replan_every is not None:
            check_int("replan_every", replan_every)
        objective = planner.objective
        if objective.alpha != 0 or objective.beta > 0:
            raise ValueError(
                f"ExplorationPolicy needs an objective with alpha=0 and beta<=0 (got alpha={objective.alpha}, "
                f"beta={objective.beta}); use exploration_objective()."
            )
        if planner.model.uncertainty is None:
            raise ValueError(
                "ExplorationPolicy needs a planning model with an uncertainty estimator."
            )
        super().__init__(
            planner,
            replan=replan,
            replan_every=planner.horizon if replan_every is None else replan_every,
            **kwargs,
        )
