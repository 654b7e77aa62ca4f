"""ExplorationPolicy and exploration_objective: what they accept, refuse and default to."""

from __future__ import annotations

import pytest
import torch

from tests.normalized import fitted
from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import (
    Objective,
    PlanningModel,
    RandomShootingPlanner,
    UncertaintyBand,
)
from torchrl_recon.policies import ExplorationPolicy, exploration_objective

H = 7


def _model(uncertainty: bool = True) -> PlanningModel:
    torch.manual_seed(0)
    estimator = ReconstructionUncertainty(12, 4, window=3, hidden_size=8) if uncertainty else None
    return PlanningModel(
        fitted(LSTMWorldModel(12, 4, window=3, hidden_size=8, dense_size=8)),
        drone_cost,
        uncertainty=estimator and fitted(estimator),
    )


def _planner(objective: Objective, model: PlanningModel | None = None) -> RandomShootingPlanner:
    return RandomShootingPlanner(model or _model(), objective, horizon=H, num_candidates=8)


def test_exploration_objective_is_alpha_zero_with_a_mean_ratio_band():
    objective = exploration_objective(ratio=1.3, cap=1.6, beta=-1.0)
    assert (objective.alpha, objective.beta) == (0.0, -1.0)
    assert objective.band == UncertaintyBand(low=1.3, high=1.6, kind="mean_ratio")
    default = exploration_objective()
    assert (default.alpha, default.beta) == (0.0, 0.0)
    assert default.band == UncertaintyBand(low=1.2, high=None, kind="mean_ratio")
    assert exploration_objective(ratio=1.5, cap=1.5).band.high == 1.5  # cap == ratio is allowed


def test_exploration_objective_refuses_penalised_uncertainty_and_a_cap_below_the_ratio():
    with pytest.raises(ValueError, match=r"beta must be <= 0, got 0\.5"):
        exploration_objective(beta=0.5)
    with pytest.raises(ValueError, match=r"cap=1\.1 must be at least ratio=1\.2"):
        exploration_objective(ratio=1.2, cap=1.1)
    for kwargs, message in (
        ({"ratio": float("nan")}, r"^ratio must be a finite number > 0, got nan\.$"),
        ({"ratio": 0.0}, r"^ratio must be a finite number > 0, got 0\.0\.$"),
        ({"cap": float("nan")}, r"^cap must be a finite number, got nan\.$"),
        ({"beta": float("nan")}, r"^beta must be a finite number, got nan\.$"),
    ):
        with pytest.raises(ValueError, match=message):
            exploration_objective(**kwargs)


def test_exploration_policy_executes_whole_plans_by_default():
    policy = ExplorationPolicy(_planner(exploration_objective()))
    assert (policy.replan, policy.replan_every) == ("every_n", H)
    policy = ExplorationPolicy(_planner(exploration_objective(beta=-1.0)), replan_every=3)
    assert (policy.replan, policy.replan_every) == ("every_n", 3)
    policy = ExplorationPolicy(_planner(exploration_objective()), replan="every_step")
    assert policy.replan == "every_step"
    # keyword arguments reach MPCPolicy
    policy = ExplorationPolicy(_planner(exploration_objective()), warm_start=False, warmup_steps=5)
    assert (policy.warm_start, policy.warmup_steps) == (False, 5)


@pytest.mark.parametrize(
    ("objective", "message"),
    [
        (Objective(alpha=1.0, beta=0.0), r"alpha=0 and beta<=0 \(got alpha=1\.0, beta=0\.0\)"),
        (Objective(alpha=0.0, beta=0.5), r"alpha=0 and beta<=0 \(got alpha=0\.0, beta=0\.5\)"),
        (Objective(alpha=0.5, beta=-1.0), r"got alpha=0\.5, beta=-1\.0"),
    ],
)
def test_exploration_policy_refuses_objectives_that_use_reward_or_penalise_uncertainty(
    objective, message
):
    with pytest.raises(ValueError, match=message):
        ExplorationPolicy(_planner(objective))


def test_exploration_policy_needs_an_uncertainty_estimator():
    planner = _planner(Objective(alpha=0.0), model=_model(uncertainty=False))
    with pytest.raises(
        ValueError, match="^ExplorationPolicy needs a planning model with an uncertainty estimator"
    ):
        ExplorationPolicy(planner)
