"""Candidates evaluated in row blocks give the one-pass result (same draws, float rounding only).

Blocking splits the ``B·K`` candidate rows into several batched passes. Each row's rollout,
cost and u depend on that row alone, so the numbers are those of one pass; only the matrix
products' kernels may differ with the number of rows (a different split of the same sums), which
moves results by float32 rounding. Hence ``assert_close`` with float32 tolerances, not ``equal``.
"""

from __future__ import annotations

import pytest
import torch

from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, MCDropoutUncertainty, ReconstructionUncertainty
from torchrl_recon.planners import (
    CEMPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
    UncertaintyBand,
)
from torchrl_recon.planners.planning_model import BLOCK_ROWS, resolve_block_rows

H, B = 12, 3


def _model(estimator=ReconstructionUncertainty) -> PlanningModel:
    torch.manual_seed(0)
    world = fitted(LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8))
    est = estimator(3, 2, window=4, hidden_size=8)
    est.fit_normalization(torch.randn(100, 3), torch.rand(100, 2) * 0.2)
    return PlanningModel(world, lambda s, a, s2: s2.pow(2).sum(-1), uncertainty=est)


def _context(batch: int = B) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(1)
    return (
        torch.randn(batch, 4, 3, generator=g),
        torch.rand(batch, 4, 2, generator=g) * 2 - 1,
        torch.randn(batch, 3, generator=g),
    )


def _assert_predictions_close(a, b) -> None:
    torch.testing.assert_close(a.states, b.states)
    torch.testing.assert_close(a.cost, b.cost)
    torch.testing.assert_close(a.uncertainty, b.uncertainty)


@pytest.mark.parametrize("block_rows", [1, 4, 7, 3 * 10])
def test_planning_model_blocks_match_one_pass(block_rows):
    """Blocks of 1, 1 (4 // 3), 2 (with a ragged last block) and all 10 candidates per env."""
    model, ctx = _model(), _context()
    actions = torch.rand(B, 10, H, 2) * 2 - 1
    with torch.no_grad():
        whole = model(*ctx, actions)
        blocked = model(*ctx, actions, block_rows=block_rows)
    assert blocked.states.shape == (B, 10, H, 3)
    _assert_predictions_close(blocked, whole)


def test_mc_dropout_scores_every_block_with_the_same_masks():
    """MC dropout draws its masks per call: blocks of the rollout, but u in one call."""
    model, ctx = _model(MCDropoutUncertainty), _context()
    actions = torch.rand(B, 10, H, 2) * 2 - 1
    with torch.no_grad():
        torch.manual_seed(3)
        whole = model(*ctx, actions)
        torch.manual_seed(3)
        blocked = model(*ctx, actions, block_rows=4)
    _assert_predictions_close(blocked, whole)


def test_u_under_autograd_in_row_blocks_matches_each_env_on_its_own():
    """3 envs x 30 candidates x 50 steps = 4500 windows: two row blocks under autograd (one
    env's 1500 windows: one). u and the gradient of J w.r.t. the actions match per-env calls."""
    model, ctx = _model(), _context()
    actions = (torch.rand(B, 30, 50, 2) * 2 - 1).requires_grad_(True)
    objective = Objective(beta=0.5)
    batched = model(*ctx, actions)
    (grad,) = torch.autograd.grad(objective.score(batched).sum(), actions)
    for i in range(B):
        one = model(*(x[i] for x in ctx), actions[i])
        (grad_i,) = torch.autograd.grad(objective.score(one).sum(), actions)
        torch.testing.assert_close(batched.uncertainty[i], one.uncertainty)
        torch.testing.assert_close(grad[i], grad_i[i])


@pytest.mark.parametrize(
    "objective",
    [Objective(beta=0.5), Objective(band=UncertaintyBand(low=0.2, high=0.8, kind="quantile"))],
)
@pytest.mark.parametrize("kind", ["cem", "mppi", "icem", "shooting"])
def test_blocked_planners_match_unblocked_for_the_same_draws(kind, objective):
    model, ctx = _model(), _context()
    init = torch.rand(B, H, 2) * 2 - 1

    def plan(block_rows):
        budget = dict(horizon=H, num_candidates=40, iterations=3, block_rows=block_rows)
        if kind == "cem":
            planner = CEMPlanner(model, objective, num_elites=5, **budget)
        elif kind == "mppi":
            planner = MPPIPlanner(model, objective, **budget)
        elif kind == "icem":
            planner = ICEMPlanner(model, objective, num_elites=5, **budget)
        else:
            planner = RandomShootingPlanner(
                model, objective, horizon=H, num_candidates=40, block_rows=block_rows
            )
        return planner.plan(*ctx, init=init, generator=torch.Generator().manual_seed(7))

    whole, blocked = plan(None), plan(16)  # 16 rows: blocks of 5 candidates x 3 envs
    # MPPI's mean is a smooth function of every score (softmax weights), so the rounding of the
    # scores reaches its plan (~1e-5 here), where the other planners' choices only select.
    tol = {"rtol": 1e-3, "atol": 1e-3} if kind == "mppi" else {}
    torch.testing.assert_close(blocked.actions, whole.actions, **tol)
    torch.testing.assert_close(blocked.states, whole.states, **tol)
    torch.testing.assert_close(blocked.objective, whole.objective, **tol)
    torch.testing.assert_close(blocked.uncertainty, whole.uncertainty, **tol)
    assert torch.equal(blocked.feasible, whole.feasible)


def test_block_rows_must_be_a_positive_int():
    model = _model()
    for planner_cls in (CEMPlanner, ICEMPlanner):
        with pytest.raises(ValueError, match="^block_rows must be an int >= 1, got 0"):
            planner_cls(model, Objective(), horizon=H, num_candidates=8, num_elites=2, block_rows=0)
    with pytest.raises(ValueError, match="^block_rows must be an int >= 1, got 0"):
        MPPIPlanner(model, Objective(), horizon=H, num_candidates=8, block_rows=0)
    with pytest.raises(ValueError, match="^block_rows must be an int >= 1, got 2.5"):
        RandomShootingPlanner(model, Objective(), horizon=H, block_rows=2.5)
    actions = torch.rand(B, 4, H, 2)
    with pytest.raises(ValueError, match="^block_rows must be an int >= 1, got -1"):
        model(*_context(), actions, block_rows=-1)


def test_default_block_is_cache_sized_on_the_cpu_and_one_pass_on_a_gpu(monkeypatch):
    """``block_rows="auto"`` (every sampling planner's default) holds one env's K = 1000 (the
    recipes') in one pass on the CPU and splits 10 envs into blocks of 102 candidates; on a GPU
    every row goes in one pass (a pass there is bound by launches, not cache)."""
    model = _model()
    planner = CEMPlanner(model, Objective(), horizon=H)
    assert planner.block_rows == "auto"
    for other in (RandomShootingPlanner, MPPIPlanner, ICEMPlanner):
        assert other(model, Objective(), horizon=H).block_rows == "auto"
    assert resolve_block_rows("auto", torch.device("cpu")) == BLOCK_ROWS >= 1000
    assert resolve_block_rows("auto", torch.device("cuda")) is None
    assert resolve_block_rows("auto", torch.device("cuda", 1)) is None
    assert resolve_block_rows(64, torch.device("cuda")) == 64  # a user's choice is kept
    passes = []
    predict = PlanningModel._predict

    def counted(self, *args, **kwargs):
        passes.append(args[3].shape[-3])  # the candidates of this pass
        return predict(self, *args, **kwargs)

    monkeypatch.setattr(PlanningModel, "_predict", counted)
    model(*_context(1), torch.rand(1, 1000, H, 2), block_rows="auto")
    model(*_context(10), torch.rand(10, 1000, H, 2), block_rows="auto")
    assert passes == [1000] + [102] * 9 + [82]
    with pytest.raises(ValueError, match="^block_rows must be a positive int, None"):
        CEMPlanner(model, Objective(), horizon=H, block_rows="all")
