"""CEMPlanner's PETS options: return_mean_elites (the final Gaussian's mean instead of the best
sample) and warm_start_uniform (the first batch's uniform share around a warm start)."""

from __future__ import annotations

import pytest
import torch

from torchrl_recon.planners import (
    CEMPlanner,
    ICEMPlanner,
    Objective,
    PlanningModel,
    UncertaintyBand,
)

from .conftest import integrator_cost, integrator_model, optimal_cost

H = 8


def _cem(model, iterations=5, **kw):
    return CEMPlanner(
        model,
        Objective(),
        horizon=H,
        num_candidates=100,
        num_elites=10,
        iterations=iterations,
        **kw,
    )


def _recording(planner):
    """``planner`` with the mean of every update kept in ``planner.means``."""
    planner.means = []
    update = planner.update

    def record(*args):
        search, best = update(*args)
        planner.means.append(search.mean)
        return search, best

    planner.update = record
    return planner


def test_returns_the_last_gaussian_mean_with_its_prediction(context):
    model = PlanningModel(integrator_model(), integrator_cost)
    planner = _recording(_cem(model, iterations=15, return_mean_elites=True))
    torch.manual_seed(0)
    result = planner.plan(*context, init=torch.zeros(H, 1))
    torch.testing.assert_close(result.actions, planner.means[-1].squeeze(-3))
    pred = model(*context, result.actions[None])
    torch.testing.assert_close(result.states, pred.states[0])
    torch.testing.assert_close(result.cost, pred.cost[0])
    assert result.feasible
    assert float(result.cost.sum()) <= 1.3 * optimal_cost(H)


def test_default_returns_a_sample_and_draws_the_same_candidates(context):
    """Off (the default) the plan is the best sample seen, not the mean; on, the same candidates
    are drawn (the extra model call comes after the last draw), so the RNG ends where it did."""
    model = PlanningModel(integrator_model(), integrator_cost)
    plain, mean = _recording(_cem(model)), _recording(_cem(model, return_mean_elites=True))
    assert plain.return_mean_elites is False
    torch.manual_seed(1)
    best = plain.plan(*context)
    after_plain = torch.rand(3)
    torch.manual_seed(1)
    averaged = mean.plan(*context)
    torch.testing.assert_close(torch.rand(3), after_plain)
    for a, b in zip(plain.means, mean.means, strict=True):
        torch.testing.assert_close(a, b)
    assert not torch.equal(best.actions, plain.means[-1].squeeze(-3))
    torch.testing.assert_close(averaged.actions, plain.means[-1].squeeze(-3))


def test_batched_plans_each_return_their_mean():
    model = PlanningModel(integrator_model(), integrator_cost)
    planner = _recording(_cem(model, return_mean_elites=True))
    torch.manual_seed(2)
    obs = torch.tensor([[0.5], [-0.5], [0.2]])
    result = planner.plan(torch.zeros(3, 4, 1), torch.zeros(3, 4, 1), obs)
    assert result.actions.shape == (3, H, 1)
    torch.testing.assert_close(result.actions, planner.means[-1].squeeze(-3))
    assert (result.actions[0, 0] < 0) and (result.actions[1, 0] > 0)  # each pushes s toward 0


def test_pick_keeps_the_mean_only_when_it_meets_the_constraints():
    planner = _cem(PlanningModel(integrator_model(), integrator_cost), return_mean_elites=True)
    objective = torch.tensor([[-5.0, -1.0, -2.0], [-5.0, -1.0, -2.0]])
    violation = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.1, 0.0]])
    # row 0: the mean is feasible, returned although a sample scored better;
    # row 1: the mean breaks a constraint, the best feasible sample is returned instead
    assert planner._pick(objective, violation).squeeze(-1).tolist() == [0, 2]


def test_flag_is_checked_and_icem_keeps_its_choice():
    model = PlanningModel(integrator_model(), integrator_cost)
    with pytest.raises(TypeError, match="return_mean_elites"):
        _cem(model, return_mean_elites=1)
    icem = ICEMPlanner(model, Objective(), horizon=H, num_candidates=50, num_elites=5)
    assert icem.return_mean_elites is False


def test_warm_start_uniform_sets_the_first_batchs_uniform_share():
    model = PlanningModel(integrator_model(), integrator_cost)
    init = torch.full((H, 1), 0.9)
    for fraction, uniform in ((0.5, 50), (0.0, 0), (1.0, 100), (0.25, 25)):
        planner = _cem(model, warm_start_uniform=fraction)
        torch.manual_seed(0)
        candidates, count = planner._first_candidates(
            torch.Size(), init, 0.01, planner._normal, None, planner.warm_start_uniform
        )
        assert candidates.shape == (100, H, 1) and count == uniform
        # the candidates after the uniform ones lie around the warm start
        if uniform < 100:
            assert (candidates[uniform:] - 0.9).abs().max() < 0.1
        if uniform:
            assert (candidates[:uniform] - 0.9).abs().max() > 0.5


def test_warm_start_uniform_zero_plans_and_is_refused_with_a_band(context):
    model = PlanningModel(integrator_model(), integrator_cost)
    torch.manual_seed(3)
    result = _cem(model, warm_start_uniform=0.0).plan(*context, init=torch.zeros(H, 1))
    assert result.feasible and result.actions.shape == (H, 1)
    with pytest.raises(ValueError, match="warm_start_uniform"):
        _cem(model, warm_start_uniform=1.5)
    band = Objective(band=UncertaintyBand(low=0.25, high=0.75, kind="quantile"))
    with pytest.raises(ValueError, match="band"):
        CEMPlanner(model, band, horizon=H, num_candidates=10, num_elites=2, warm_start_uniform=0.0)
