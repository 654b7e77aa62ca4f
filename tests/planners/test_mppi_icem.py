"""MPPI and iCEM on their own: budget, bounds, batches, seeds, arguments, weights, elite carry."""

from __future__ import annotations

import math

import pytest
import torch

from torchrl_recon.modules import LinearDeltaModel
from torchrl_recon.planners import (
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
    UncertaintyBand,
)
from torchrl_recon.planners.elite_memory import MEMORY_ROWS, EliteMemory
from torchrl_recon.planners.noise import colored_noise
from torchrl_recon.planners.planning_model import Prediction

from .conftest import integrator_cost, integrator_model, optimal_cost

H = 8
BUDGET = 1000


def _mppi(model, objective=None, **kwargs):
    args = {"num_candidates": BUDGET // 5 - 1, "iterations": 5, "noise_std": 0.1, **kwargs}
    return MPPIPlanner(model, objective or Objective(), horizon=H, **args)


def _icem(model, objective=None, **kwargs):
    args = {"num_candidates": BUDGET // 4, "num_elites": 20, "iterations": 5, **kwargs}
    return ICEMPlanner(model, objective or Objective(), horizon=H, **args)


PLANNERS = {"mppi": _mppi, "icem": _icem}


def _rows_scored(planner) -> int:
    """Candidate rows one plan of one context costs."""
    if isinstance(planner, MPPIPlanner):
        return planner.num_candidates * planner.iterations + 1
    kept = planner.num_kept * (planner.iterations - 1)
    return sum(planner.population_sizes()) + kept + 1


@pytest.mark.parametrize("kind", sorted(PLANNERS))
def test_better_than_random_shooting_at_the_same_budget(kind, context):
    """On the integrator, at <= 1000 scored sequences each, over 4 seeds: every plan costs less
    than the best of 1000 uniform sequences, and closes 99 % of the gap from the mean uniform
    sequence's cost to the closed-form optimum."""
    model = PlanningModel(integrator_model(), integrator_cost)
    best = optimal_cost(H)
    torch.manual_seed(0)
    random = float(model(*context, torch.rand(1000, H, 1) * 2 - 1).cumulative_cost.mean())
    planner = PLANNERS[kind](model)
    assert _rows_scored(planner) <= BUDGET
    for seed in range(4):
        torch.manual_seed(seed)
        shooting = RandomShootingPlanner(model, Objective(), horizon=H, num_candidates=BUDGET)
        shot = float(shooting.plan(*context).cost.sum())
        torch.manual_seed(seed)
        planned = float(PLANNERS[kind](model).plan(*context).cost.sum())
        assert best * (1 - 1e-4) <= planned < shot, (seed, planned, shot)
        assert (planned - best) / (random - best) < 0.01, (seed, planned, best)


def _far_model(low, high) -> PlanningModel:
    """A 2-D integrator that starts far from 0: the best actions lie on the bounds."""
    model = LinearDeltaModel(2, 2, window=1)
    model.weight.zero_()
    model.weight[2:4, :] = torch.eye(2)
    return PlanningModel(
        model, lambda s, a, s2: s2.pow(2).sum(-1), action_low=low, action_high=high
    )


@pytest.mark.parametrize("kind", sorted(PLANNERS))
def test_actions_stay_in_asymmetric_bounds_and_reach_them(kind):
    low, high = torch.tensor([-0.3, 0.1]), torch.tensor([0.7, 0.4])
    model = _far_model(low, high)
    batch = 3
    ctx = torch.zeros(batch, 1, 2), torch.zeros(batch, 1, 2), torch.tensor([[5.0, -5.0]] * batch)
    init = torch.full((batch, H, 2), 3.0)  # a warm start outside the box
    torch.manual_seed(0)
    for warm in (None, init):
        result = PLANNERS[kind](model).plan(*ctx, init=warm)
        assert ((result.actions >= low) & (result.actions <= high)).all()
        # s0 = 5 wants -0.3 all along, s1 = -5 wants 0.4: the plan pushes into the bounds
        first, second = result.actions[..., 0], result.actions[..., 1]
        assert (first == low[0]).any() and (second == high[1]).any()
        assert first.mean() < 0.0 and second.mean() > 0.26  # the box's middle: 0.2, 0.25


@pytest.mark.parametrize("kind", sorted(PLANNERS))
def test_a_batch_of_contexts_is_planned_in_one_call_each_for_its_own_state(kind):
    """Starts 0.5, -0.5 and 0: each row's plan drives its own state to 0 (the closed-form
    optimum from ±0.5, and nothing to do from 0), in one call."""
    model = PlanningModel(integrator_model(), integrator_cost)
    starts = torch.tensor([[0.5], [-0.5], [0.0]])
    ctx = torch.zeros(3, 4, 1), torch.zeros(3, 4, 1), starts
    calls = []
    model.register_forward_hook(lambda module, args, out: calls.append(args[3].shape))
    torch.manual_seed(0)
    planner = PLANNERS[kind](model)
    result = planner.plan(*ctx)
    assert result.actions.shape == (3, H, 1) and result.feasible.all()
    # one call per iteration (MPPI: and its final mean), every call all three rows
    assert len(calls) == planner.iterations + isinstance(planner, MPPIPlanner)
    assert all(shape[0] == 3 for shape in calls)
    cost, best = result.cost.sum(-1), optimal_cost(H)
    random = float(model(*ctx, torch.rand(3, 1000, H, 1) * 2 - 1).cumulative_cost[:2].mean())
    assert ((cost[:2] - best) / (random - best) < 0.01).all(), cost
    assert cost[2] < 0.01 * random
    assert (result.actions[0] < 0).any() and (result.actions[1] > 0).any()  # opposite pushes


@pytest.mark.parametrize("kind", sorted(PLANNERS))
def test_a_seed_or_a_generator_gives_the_same_plan(kind, context):
    model = PlanningModel(integrator_model(), integrator_cost)
    init = torch.linspace(-0.5, 0.5, H)[:, None]

    def plan(seed, **kwargs):
        torch.manual_seed(seed)
        return PLANNERS[kind](model).plan(*context, init=init, **kwargs).actions

    assert torch.equal(plan(0), plan(0))
    assert not torch.equal(plan(0), plan(1))
    a = plan(0, generator=torch.Generator().manual_seed(3))
    b = plan(1, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a, b)  # the generator, not the global RNG


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"temperature": 0.0}, "temperature must be a positive finite number, got 0.0"),
        ({"temperature": -1.0}, "temperature must be a positive finite number, got -1.0"),
        ({"temperature": math.inf}, "temperature must be a positive finite number, got inf"),
        ({"temperature": math.nan}, "temperature must be a positive finite number, got nan"),
        ({"noise_std": 0.0}, "noise_std must be a positive finite number, got 0.0"),
        ({"noise_std": -0.1}, "noise_std must be a positive finite number, got -0.1"),
        ({"num_candidates": 0}, "num_candidates must be an int >= 1, got 0"),
        ({"iterations": 0}, "iterations must be an int >= 1, got 0"),
        ({"block_rows": 0}, "block_rows must be an int >= 1, got 0"),
    ],
)
def test_mppi_argument_checks(kwargs, message):
    model = PlanningModel(integrator_model(), integrator_cost)
    with pytest.raises(ValueError, match=f"^{message}"):
        MPPIPlanner(model, Objective(), horizon=3, **kwargs)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"num_elites": 9}, r"num_elites must be in \[1, num_candidates=8\], got 9"),
        ({"population_decay": 0.9}, r"population_decay must be a finite number >= 1 \(1 = no"),
        ({"population_decay": math.inf}, "population_decay must be a finite number >= 1"),
        ({"keep_elites": -0.1}, r"keep_elites must be in \[0, 1\], got -0.1"),
        ({"keep_elites": 1.5}, r"keep_elites must be in \[0, 1\], got 1.5"),
        ({"noise_beta": -1.0}, "noise_beta must be a finite number >= 0, got -1.0"),
        ({"noise_beta": math.nan}, "noise_beta must be a finite number >= 0, got nan"),
        ({"min_std": -0.01}, "min_std must be a finite number >= 0, got -0.01"),
        ({"smoothing": 1.0}, r"smoothing must be in \[0, 1\), got 1.0"),
    ],
)
def test_icem_argument_checks(kwargs, message):
    model = PlanningModel(integrator_model(), integrator_cost)
    args = {"horizon": 3, "num_candidates": 8, "num_elites": 2, **kwargs}
    with pytest.raises(ValueError, match=f"^{message}"):
        ICEMPlanner(model, Objective(), **args)


def test_icem_accepts_the_edges_of_its_ranges(context):
    model = PlanningModel(integrator_model(), integrator_cost)
    for kwargs in (
        {"population_decay": 1.0},
        {"keep_elites": 0.0},
        {"keep_elites": 1.0},
        {"noise_beta": 0.0},
        {"min_std": 0.0},
    ):
        planner = ICEMPlanner(
            model, Objective(), horizon=3, num_candidates=8, num_elites=2, iterations=3, **kwargs
        )
        for init in (None, torch.zeros(3, 1), torch.zeros(3, 1)):
            assert planner.plan(*context, init=init).actions.shape == (3, 1), kwargs


def test_icem_population_shrinks_to_twice_the_elites():
    model = PlanningModel(integrator_model(), integrator_cost)
    planner = ICEMPlanner(
        model, Objective(), horizon=3, num_candidates=100, num_elites=30, iterations=4
    )
    assert planner.population_sizes() == [100, 80, 64, 60]  # ceil(100 / 1.25^i), >= 2 x 30
    flat = ICEMPlanner(
        model, Objective(), horizon=3, num_candidates=10, num_elites=8, population_decay=2.0
    )
    assert flat.population_sizes() == [10] * 5  # 2 x 8 elites would exceed K: K


def _prediction(score: list[float], u: list[float]) -> Prediction:
    """One batch element, candidates with cost −score (one step) and u."""
    cost = -torch.tensor(score)[None, :, None]
    return Prediction(torch.zeros(1, len(score), 1, 1), cost, torch.tensor(u)[None, :, None])


def test_mppi_weights_are_a_softmax_of_j_over_the_feasible_candidates():
    model = PlanningModel(integrator_model(), integrator_cost)
    pred = _prediction([1.0, 2.0, 4.0, 3.0], [0.0, 0.0, 5.0, 0.0])
    mppi = MPPIPlanner(model, Objective(), horizon=1, temperature=2.0)
    expected = torch.softmax(torch.tensor([1.0, 2.0, 4.0, 3.0]) / 2.0, -1)
    torch.testing.assert_close(mppi._weights(pred, None)[0], expected)
    # candidate 2 is outside the band: it gets no weight, the rest share it by J
    band = (torch.tensor([[-1.0]]), torch.tensor([[1.0]]))
    weights = mppi._weights(pred, band)[0]
    assert weights[2] == 0
    torch.testing.assert_close(weights[[0, 1, 3]], torch.softmax(torch.tensor([1.0, 2, 3]) / 2, -1))
    # a tiny temperature keeps the best; a huge one averages
    cold = MPPIPlanner(model, Objective(), horizon=1, temperature=1e-6)._weights(pred, None)[0]
    hot = MPPIPlanner(model, Objective(), horizon=1, temperature=1e6)._weights(pred, None)[0]
    assert cold.tolist() == [0.0, 0.0, 1.0, 0.0]
    torch.testing.assert_close(hot, torch.full((4,), 0.25))
    # nobody feasible: weighted towards the least violation (u = 5 → 4, u = 0 → ... all 1 off)
    far = (torch.tensor([[2.0]]), torch.tensor([[3.0]]))
    weights = mppi._weights(pred, far)[0]
    torch.testing.assert_close(weights, torch.softmax(-torch.tensor([2.0, 2.0, 2.0, 2.0]) / 2, -1))


def test_mppi_with_a_band_keeps_its_plan_inside():
    """An absolute band on Σu of a toy u = |a|: MPPI's plan (mean or sample) stays inside."""
    model = PlanningModel(integrator_model(), integrator_cost)

    class AbsAction(torch.nn.Module):
        obs_dim, action_dim, window, window_local = 1, 1, 1, True

        def score_sequence(self, x):
            return x[..., 1].abs()

    model.uncertainty = AbsAction()
    ctx = torch.zeros(4, 1), torch.zeros(4, 1), torch.full((1,), 0.5)
    torch.manual_seed(0)
    objective = Objective(band=UncertaintyBand(high=0.6))
    result = MPPIPlanner(model, objective, horizon=H, num_candidates=200, noise_std=0.1).plan(*ctx)
    assert result.feasible and float(result.uncertainty.sum()) <= 0.6 + 1e-6
    assert float(result.actions.abs().sum()) <= 0.6 + 1e-6


# ---------------------------------------------------------------- iCEM's elites across plans


def _shift(plan: torch.Tensor, steps: int) -> torch.Tensor:
    """MPCPolicy's warm start: the plan after ``steps`` executed actions, padded with its last."""
    return torch.cat([plan[..., steps:, :], plan[..., -1:, :].expand_as(plan[..., :steps, :])], -2)


def test_elite_memory_finds_rows_by_their_shifted_plan():
    memory = EliteMemory()
    plans = torch.randn(3, 5, 2)
    elites = torch.randn(3, 4, 5, 2)
    memory.remember(plans, elites)
    # rows 2 and 0, shifted by 2 and 1, and a warm start nobody made
    init = torch.stack([_shift(plans[2], 2), torch.zeros(5, 2), _shift(plans[0], 1)])
    out, found = memory.recall(init)
    assert found.tolist() == [True, False, True]
    torch.testing.assert_close(out[0], _shift(elites[2], 2), rtol=0, atol=0)
    torch.testing.assert_close(out[2], _shift(elites[0], 1), rtol=0, atol=0)
    # the rows found are consumed, row 1 is still there
    assert memory.recall(init) is None
    out, found = memory.recall(_shift(plans[1], 4)[None])
    assert found.tolist() == [True] and torch.equal(out[0], _shift(elites[1], 4))
    assert memory.plans is None


def test_elite_memory_keeps_unrecalled_rows_newest_first_and_forgets_other_shapes():
    memory = EliteMemory()
    memory.remember(torch.randn(MEMORY_ROWS, 3, 1), torch.randn(MEMORY_ROWS, 2, 3, 1))
    newest = torch.randn(2, 3, 1)
    memory.remember(newest, torch.randn(2, 2, 3, 1))
    assert len(memory.plans) == MEMORY_ROWS and torch.equal(memory.plans[:2], newest)
    memory.remember(torch.randn(1, 3, 1), torch.randn(1, 5, 3, 1))  # other elites: a fresh start
    assert len(memory.plans) == 1
    assert memory.recall(torch.randn(1, 4, 1)) is None  # another horizon
    memory.forget()
    assert memory.recall(torch.randn(1, 3, 1)) is None


def test_icem_carries_its_elites_into_the_plan_its_warm_start_continues(context):
    model = PlanningModel(integrator_model(), integrator_cost)
    batch_ctx = tuple(torch.stack([x, x]) for x in context)
    torch.manual_seed(0)
    planner = _icem(model)
    first = planner.plan(*batch_ctx)
    kept = planner.memory.elites.clone()
    assert kept.shape == (2, planner.num_kept, H, 1)
    # row 0 continues its plan after 2 steps, row 1 gets a warm start of its own
    init = torch.stack([_shift(first.actions[0], 2), torch.zeros(H, 1)])
    carried = planner._carried(init, torch.Size([2]), None)
    torch.testing.assert_close(carried[0], _shift(kept[0], 2), rtol=0, atol=0)
    assert not torch.equal(carried[1], _shift(kept[1], 2))
    assert ((carried[1] >= -1) & (carried[1] <= 1)).all()


def test_colored_noise_gets_smoother_with_beta():
    white = torch.randn(4000, 2, H // 2 + 1, generator=torch.Generator().manual_seed(0))

    def roughness(beta):  # mean squared step-to-step change of unit-variance noise
        x = colored_noise(white, H, beta)
        return float((x[:, 1:] - x[:, :-1]).pow(2).mean() / x.var())

    values = [roughness(b) for b in (0.0, 1.0, 2.0, 3.0)]
    assert values == sorted(values, reverse=True) and values[0] > 1.8 and values[-1] < 0.7
    for h in (1, 2, 7):
        w = torch.randn(5000, 2, h // 2 + 1, generator=torch.Generator().manual_seed(1))
        assert abs(float(colored_noise(w, h, 2.0).var()) - 1) < 0.1
    with pytest.raises(ValueError, match=r"white has shape \(3, 2, 4\); expected \[..., 2, 5\]"):
        colored_noise(torch.zeros(3, 2, 4), 8, 1.0)
