from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    InfeasiblePlanError,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
    UncertaintyBand,
)

from .conftest import integrator_cost, integrator_model, optimal_cost

H = 8


def _planners(model, objective, budget: int = 1000):
    return {
        "shooting": RandomShootingPlanner(model, objective, horizon=H, num_candidates=budget),
        "cem": CEMPlanner(
            model, objective, horizon=H, num_candidates=budget // 5, num_elites=20, iterations=5
        ),
        "gradient": GradientPlanner(
            model, objective, horizon=H, restarts=4, steps=budget // 4 - 1, lr=0.05
        ),
        # 5 x 200 candidates and the final mean
        "mppi": MPPIPlanner(
            model, objective, horizon=H, num_candidates=budget // 5, iterations=5, noise_std=0.1
        ),
        # 250 + 200 + 160 + 128 + 103 candidates, 6 kept elites in 4 iterations and the mean
        "icem": ICEMPlanner(
            model, objective, horizon=H, num_candidates=budget // 4, num_elites=20, iterations=5
        ),
    }


# The sampling planners that take a warm start, a band and a batch as CEM does, with the
# arguments of a small budget (K candidates, a few elites).
SAMPLING = {
    "cem": lambda model, objective, k, **kw: CEMPlanner(
        model, objective, horizon=H, num_candidates=k, num_elites=max(1, k // 10), **kw
    ),
    "mppi": lambda model, objective, k, **kw: MPPIPlanner(
        model, objective, horizon=H, num_candidates=k, **kw
    ),
    "icem": lambda model, objective, k, **kw: ICEMPlanner(
        model, objective, horizon=H, num_candidates=k, num_elites=max(1, k // 10), **kw
    ),
}


def test_each_optimiser_approaches_the_closed_form_optimum(context):
    """Gap = (planner cost − optimum) / (mean cost of uniform random sequences − optimum), equal budget of 1000 rollouts."""
    torch.manual_seed(0)
    best = optimal_cost(H)
    model = PlanningModel(integrator_model(), integrator_cost)
    random_cost = float(model(*context, torch.rand(1000, H, 1) * 2 - 1).cumulative_cost.mean())
    gaps = {
        name: (float(p.plan(*context).cost.sum()) - best) / (random_cost - best)
        for name, p in _planners(model, Objective()).items()
    }
    print("optimum", best, "random", random_cost, "gaps", gaps)
    assert all(gap >= -1e-4 for gap in gaps.values())  # nobody beats the closed-form optimum
    assert gaps["gradient"] < 0.005
    assert gaps["cem"] < 0.01
    assert gaps["shooting"] < 0.25
    assert gaps["mppi"] < 0.05 and gaps["icem"] < 0.01
    assert all(gaps[name] < gaps["shooting"] for name in ("cem", "gradient", "mppi", "icem"))


def test_cem_converges_near_the_closed_form_optimum(context):
    """With enough iterations CEM's cost is within 20 % of the optimum (mean of 4 seeds; each
    within 30 %). Smoothing that kept 90 % of the old mean or std instead of 10 % stays ~2-10x away."""
    best = optimal_cost(H)
    model = PlanningModel(integrator_model(), integrator_cost)
    ratios = []
    for seed in range(4):
        torch.manual_seed(seed)
        planner = CEMPlanner(
            model, Objective(), horizon=H, num_candidates=100, num_elites=10, iterations=15
        )
        result = planner.plan(*context)
        ratios.append(float(result.cost.sum()) / best)
    print("CEM cost / optimum:", ratios)
    assert all(r >= 1 - 1e-4 for r in ratios)  # nobody beats the closed-form optimum
    assert all(r <= 1.3 for r in ratios), ratios
    assert sum(ratios) / len(ratios) <= 1.2, ratios


def test_plan_result_is_consistent_with_the_model(context):
    torch.manual_seed(0)
    model = PlanningModel(integrator_model(), integrator_cost)
    result = CEMPlanner(model, Objective(), horizon=H, num_candidates=50, num_elites=5).plan(
        *context
    )
    pred = model(*context, result.actions[None])
    torch.testing.assert_close(pred.states[0], result.states)
    torch.testing.assert_close(pred.cost[0], result.cost)
    torch.testing.assert_close(result.objective, -result.cost.sum())
    assert result.feasible


def _ae_model(seed: int = 0):
    torch.manual_seed(seed)
    world = fitted(LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8))
    est = ReconstructionUncertainty(3, 2, window=4, hidden_size=8)
    est.fit_normalization(torch.randn(100, 3), torch.rand(100, 2) * 0.2)
    return PlanningModel(world, lambda s, a, s2: s2.pow(2).sum(-1), uncertainty=est)


@pytest.mark.parametrize("kind", ["shooting", *SAMPLING])
def test_beta_lowers_the_chosen_plans_uncertainty(kind):
    model = _ae_model()
    ctx = torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3)

    def build(objective):
        if kind == "shooting":
            return RandomShootingPlanner(model, objective, horizon=H, num_candidates=200)
        return SAMPLING[kind](model, objective, 200)

    u = {}
    for beta in (0.0, 10.0):
        torch.manual_seed(1)
        u[beta] = float(build(Objective(beta=beta)).plan(*ctx).uncertainty.sum())
    assert u[10.0] < u[0.0]


def test_gradient_with_beta_lowers_uncertainty():
    model = _ae_model()
    ctx = torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3)
    u = {}
    for beta in (0.0, 10.0):
        torch.manual_seed(1)
        u[beta] = float(
            GradientPlanner(model, Objective(beta=beta), horizon=H, restarts=4, steps=20)
            .plan(*ctx)
            .uncertainty.sum()
        )
    assert u[10.0] < u[0.0]


@pytest.mark.parametrize(
    "kind, low, high", [("quantile", 0.4, 0.6), ("mean_ratio", 1.1, 1.3), ("absolute", None, None)]
)
def test_band_is_respected(kind, low, high):
    model = _ae_model()
    ctx = torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3)
    if kind == "absolute":  # an absolute band in the middle of what uniform candidates reach
        torch.manual_seed(2)
        with torch.no_grad():
            ref = model(*ctx, torch.rand(300, H, 2) * 2 - 1).cumulative_uncertainty
        low, high = float(ref.quantile(0.3)), float(ref.quantile(0.5))
    band = UncertaintyBand(low=low, high=high, kind=kind)
    torch.manual_seed(3)
    planner = RandomShootingPlanner(model, Objective(band=band), horizon=H, num_candidates=300)
    result = planner.plan(*ctx)
    torch.manual_seed(3)
    reference = model(*ctx, planner._uniform(torch.Size([]), 300)).cumulative_uncertainty
    lo, hi = band.resolve(reference)
    assert result.feasible
    assert lo.item() - 1e-5 <= float(result.uncertainty.sum()) <= hi.item() + 1e-5


@pytest.mark.parametrize("kind", [*SAMPLING, "gradient"])
def test_relative_band_with_warm_start_is_resolved_on_uniform_candidates(kind):
    model = _ae_model()
    ctx = torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3)
    band = UncertaintyBand(low=0.4, high=0.6, kind="quantile")
    torch.manual_seed(4)
    if kind == "gradient":
        planner = GradientPlanner(model, Objective(band=band), horizon=H, restarts=32, steps=2)
    else:
        planner = SAMPLING[kind](model, Objective(band=band), 200)
    result = planner.plan(*ctx, init=torch.zeros(H, 2))
    torch.manual_seed(5)
    reference = model(*ctx, torch.rand(2000, H, 2) * 2 - 1).cumulative_uncertainty
    assert result.feasible
    # The chosen sequence sits in the middle of what uniform sequences reach, not of what the warm start reaches.
    assert reference.quantile(0.3) <= result.uncertainty.sum() <= reference.quantile(0.7)


@pytest.mark.parametrize("kind", ["absolute", "quantile", "mean_ratio"])
def test_one_sided_bands_resolve_to_infinite_other_sides(kind):
    reference = torch.tensor([[1.0, 2.0, 3.0, 6.0], [2.0, 2.0, 2.0, 2.0]])
    value = {"absolute": 2.5, "quantile": 0.5, "mean_ratio": 1.5}[kind]
    expected = {
        "absolute": [[2.5], [2.5]],
        "quantile": [[2.5], [2.0]],
        "mean_ratio": [[4.5], [3.0]],
    }[kind]
    low, high = UncertaintyBand(low=value, kind=kind).resolve(reference)
    assert low.tolist() == expected and high.tolist() == [[float("inf")]] * 2
    low, high = UncertaintyBand(high=value, kind=kind).resolve(reference)
    assert low.tolist() == [[-float("inf")]] * 2 and high.tolist() == expected


def test_quantile_bands_take_bounds_in_zero_one_only():
    assert UncertaintyBand(low=0.0, high=1.0, kind="quantile").high == 1.0
    for low, high in ((-0.1, 0.5), (0.5, 1.1)):
        with pytest.raises(ValueError, match=r"quantile band bounds must lie in \[0, 1\]"):
            UncertaintyBand(low=low, high=high, kind="quantile")
    assert UncertaintyBand(low=2.0, high=5.0).high == 5.0  # absolute bands are not limited
    with pytest.raises(ValueError, match="band kind must be"):
        UncertaintyBand(low=1.0, kind="ratio")


def test_no_feasible_candidate_is_reported_or_raised():
    model = _ae_model()
    ctx = torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3)
    band = UncertaintyBand(low=1e6, high=2e6)
    with pytest.warns(RuntimeWarning, match=r"No candidate met the constraints.* for 1 of 1 batch"):
        result = RandomShootingPlanner(
            model, Objective(band=band), horizon=H, num_candidates=50
        ).plan(*ctx)
    assert not result.feasible
    for raising in (
        RandomShootingPlanner(
            model, Objective(band=band), horizon=H, num_candidates=50, on_infeasible="raise"
        ),
        *(
            build(model, Objective(band=band), 20, iterations=2, on_infeasible="raise")
            for build in SAMPLING.values()
        ),
    ):
        with pytest.raises(InfeasiblePlanError, match="No candidate"):
            raising.plan(*ctx)


def test_cost_threshold_is_respected(context):
    torch.manual_seed(0)
    model = PlanningModel(integrator_model(), integrator_cost)
    ref = model(*context, torch.rand(500, H, 1) * 2 - 1).cumulative_cost
    threshold = float(ref.quantile(0.5))
    objective = Objective(alpha=0.0, beta=0.0, cost_threshold=threshold)
    result = RandomShootingPlanner(model, objective, horizon=H, num_candidates=200).plan(*context)
    assert result.feasible and float(result.cost.sum()) <= threshold


@pytest.mark.parametrize("batch", [(), (3,)])
def test_batched_contexts(batch):
    model = _ae_model()
    ctx = torch.zeros(*batch, 4, 3), torch.zeros(*batch, 4, 2), torch.zeros(*batch, 3)
    for planner in (
        RandomShootingPlanner(model, Objective(beta=1.0), horizon=H, num_candidates=20),
        *(build(model, Objective(beta=1.0), 20, iterations=2) for build in SAMPLING.values()),
        GradientPlanner(model, Objective(beta=1.0), horizon=H, restarts=2, steps=2),
    ):
        result = planner.plan(*ctx)
        assert result.actions.shape == (*batch, H, 2)
        assert result.uncertainty.shape == (*batch, H)
        assert result.feasible.shape == batch
        assert (result.actions.abs() <= 1).all()


def test_bad_input_is_a_clear_error():
    model = _ae_model()
    with pytest.raises(ValueError, match="finite"):
        PlanningModel(model.world_model, integrator_cost, action_low=-float("inf"))
    with pytest.raises(ValueError, match="horizon"):
        RandomShootingPlanner(model, Objective(), horizon=0)
    with pytest.raises(ValueError, match="^num_candidates must be an int >= 1, got 0"):
        RandomShootingPlanner(model, Objective(), horizon=3, num_candidates=0)
    with pytest.raises(ValueError, match="no estimator"):
        RandomShootingPlanner(
            PlanningModel(model.world_model, integrator_cost), Objective(beta=1.0), horizon=3
        )
    planner = RandomShootingPlanner(model, Objective(), horizon=3, num_candidates=4)
    with pytest.raises(ValueError, match="window=4"):
        planner.plan(torch.zeros(2, 3), torch.zeros(2, 2), torch.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        planner.plan(torch.zeros(4, 3), torch.zeros(4, 2), torch.tensor([0.0, float("nan"), 0.0]))
    with pytest.raises(ValueError, match="band low"):
        UncertaintyBand(low=2.0, high=1.0)
    for planner_cls in (CEMPlanner, ICEMPlanner):
        with pytest.raises(ValueError, match="num_elites"):
            planner_cls(model, Objective(), horizon=3, num_candidates=4, num_elites=5)
    with pytest.raises(ValueError, match="^temperature must be a positive finite number, got 0"):
        MPPIPlanner(model, Objective(), horizon=3, temperature=0)
    with pytest.raises(ValueError, match="on_infeasible must be 'fallback' or 'raise', got 'skip'"):
        RandomShootingPlanner(model, Objective(), horizon=3, on_infeasible="skip")
    with pytest.raises(ValueError, match=r"init has shape \(2, 2\); expected \(3, 2\)"):
        planner.plan(torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3), init=torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"init has shape \(3, 2\); expected \(5, 3, 2\)"):
        planner.plan(
            torch.zeros(5, 4, 3), torch.zeros(5, 4, 2), torch.zeros(5, 3), init=torch.zeros(3, 2)
        )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"num_candidates": 0}, "num_candidates must be an int >= 1, got 0"),
        ({"iterations": 0}, "iterations must be an int >= 1, got 0"),
        ({"num_elites": 0}, r"num_elites must be in \[1, num_candidates=8\], got 0"),
        ({"num_elites": 9}, r"num_elites must be in \[1, num_candidates=8\], got 9"),
        ({"smoothing": 1.0}, r"smoothing must be in \[0, 1\), got 1.0"),
        ({"smoothing": -0.1}, r"smoothing must be in \[0, 1\), got -0.1"),
    ],
)
@pytest.mark.parametrize("planner_cls", [CEMPlanner, ICEMPlanner])
def test_cem_argument_checks(planner_cls, kwargs, message):
    """CEM's arguments, and iCEM's that are CEM's (MPPI's and iCEM's own: test_mppi_icem.py)."""
    model = PlanningModel(integrator_model(), integrator_cost)
    args = {"horizon": 3, "num_candidates": 8, "num_elites": 2, **kwargs}
    with pytest.raises(ValueError, match=f"^{message}"):
        planner_cls(model, Objective(), **args)


def test_defaults_are_the_documented_ones():
    """docs/planning.md lists these defaults."""
    model = PlanningModel(integrator_model(), integrator_cost)
    cem = CEMPlanner(model, Objective(), horizon=3)
    assert (cem.num_candidates, cem.iterations, cem.num_elites) == (1000, 5, 100)
    assert (cem.smoothing, cem.min_std, cem.on_infeasible) == (0.1, 0.02, "fallback")
    shooting = RandomShootingPlanner(model, Objective(), horizon=3)
    assert (shooting.num_candidates, shooting.on_infeasible) == (1000, "fallback")
    assert cem.block_rows == shooting.block_rows == "auto"
    mppi = MPPIPlanner(model, Objective(), horizon=3)
    assert (mppi.num_candidates, mppi.iterations, mppi.temperature, mppi.noise_std) == (
        1000,
        5,
        1.0,
        0.25,
    )
    assert (mppi.block_rows, mppi.on_infeasible) == ("auto", "fallback")
    icem = ICEMPlanner(model, Objective(), horizon=3)
    assert (icem.num_candidates, icem.iterations, icem.num_elites) == (1000, 5, 100)
    assert (icem.population_decay, icem.keep_elites, icem.noise_beta) == (1.25, 0.3, 2.0)
    assert (icem.smoothing, icem.min_std, icem.block_rows) == (0.1, 0.02, "auto")
    assert icem.population_sizes() == [1000, 800, 640, 512, 410]


@pytest.mark.parametrize("planner_cls", [CEMPlanner, ICEMPlanner])
def test_cem_accepts_the_edges_of_its_ranges(planner_cls, context):
    model = PlanningModel(integrator_model(), integrator_cost)
    for kwargs in (
        {"num_elites": 1},
        {"num_elites": 8},
        {"num_elites": 2, "smoothing": 0.0},
        {"num_elites": 2, "smoothing": 0.99},
    ):
        planner = planner_cls(
            model, Objective(), horizon=3, num_candidates=8, iterations=2, **kwargs
        )
        assert planner.plan(*context).actions.shape == (3, 1), kwargs


if __name__ == "__main__":
    pytest.main([__file__, "-q", "-s"])


def test_gradient_planner_refuses_a_constant_objective():
    from torchrl_recon.envs.drone import drone_cost
    from torchrl_recon.modules import LSTMWorldModel
    from torchrl_recon.planners import GradientPlanner, Objective, PlanningModel

    model = PlanningModel(LSTMWorldModel(12, 4), drone_cost)
    with pytest.raises(ValueError, match="alpha or beta must be non-zero"):
        GradientPlanner(model, Objective(alpha=0.0, beta=0.0), horizon=5)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"alpha": float("nan")}, ValueError, "alpha must be a finite number, got nan."),
        ({"beta": float("inf")}, ValueError, "beta must be a finite number, got inf."),
        ({"beta": "0.1"}, TypeError, "beta must be a number, got '0.1'."),
        ({"cost_threshold": float("nan")}, ValueError, "cost_threshold must be a finite number"),
        (
            {"band": (0.1, 0.5)},
            TypeError,
            "band must be an UncertaintyBand or None, got (0.1, 0.5)",
        ),
    ],
)
def test_objective_refuses_weights_that_are_not_finite_numbers(kwargs, error, message):
    with pytest.raises(error, match=re.escape(message)):
        Objective(**kwargs)


def test_objective_takes_numpy_and_int_weights_and_bands_take_infinite_bounds():
    assert Objective(alpha=1, beta=np.float32(0.5)).needs_uncertainty
    assert UncertaintyBand(low=-math.inf, high=1.0).low == -math.inf
    with pytest.raises(ValueError, match="band high must be a number, not NaN, got nan"):
        UncertaintyBand(high=float("nan"))


def test_a_context_of_another_dtype_is_refused_naming_it():
    planner = RandomShootingPlanner(_ae_model(), Objective(), horizon=3, num_candidates=4)
    ctx = torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3)
    with pytest.raises(
        ValueError,
        match=r"^observation has dtype torch.int64 but the planning model computes in torch.float32; pass observation.to\(torch.float32\).$",
    ):
        planner.plan(*ctx[:2], ctx[2].long())
    with pytest.raises(ValueError, match=r"^context_obs has dtype torch.float64 but"):
        planner.plan(ctx[0].double(), *ctx[1:])
    assert planner.plan(*ctx).actions.shape == (3, 2)


def _nan_where_first_action_above_half(obs, action, next_obs):
    """``‖a‖²``, NaN wherever the first action exceeds 0.5: a cost undefined in a region."""
    cost = action.pow(2).sum(-1) + 0 * next_obs.sum(-1)
    return cost.masked_fill(action[..., 0] > 0.5, float("nan"))


NAN_PLANNERS = {
    "shooting": (RandomShootingPlanner, {"num_candidates": 200}),
    "cem": (CEMPlanner, {"num_candidates": 200, "num_elites": 20, "iterations": 3}),
    "icem": (ICEMPlanner, {"num_candidates": 200, "num_elites": 20, "iterations": 3}),
    "mppi": (MPPIPlanner, {"num_candidates": 200, "iterations": 3}),
    "gradient": (GradientPlanner, {"restarts": 8, "steps": 5}),
}


@pytest.mark.parametrize("kind", list(NAN_PLANNERS))
def test_a_candidate_whose_predicted_cost_is_nan_is_never_chosen(kind):
    """topk and argmax take NaN for the largest value: every planner chose such candidates."""
    torch.manual_seed(0)
    world = LSTMWorldModel(3, 2, window=4)
    world.fit_normalization(torch.randn(50, 3), torch.rand(50, 2) * 2 - 1, torch.randn(50, 3))
    model = PlanningModel(world, _nan_where_first_action_above_half)
    cls, kwargs = NAN_PLANNERS[kind]
    result = cls(model, Objective(), horizon=5, **kwargs).plan(
        torch.randn(4, 3), torch.rand(4, 2) * 2 - 1, torch.randn(3)
    )
    assert result.actions[:, 0].max() <= 0.5 and torch.isfinite(result.objective).all()


def test_every_candidate_nan_is_one_clear_error():
    world = fitted(LSTMWorldModel(3, 2, window=4))
    model = PlanningModel(world, lambda o, a, n: a.sum(-1) * float("nan"))
    planner = RandomShootingPlanner(model, Objective(), horizon=3, num_candidates=8)
    with pytest.raises(
        FloatingPointError,
        match=r"^every candidate's predicted objective is NaN for 1 of 1 batch element\(s\) \(cost NaN: True",
    ):
        planner.plan(torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3))


@pytest.mark.parametrize(
    ("kind", "low", "high"), [("quantile", 0.25, 0.75), ("mean_ratio", 1.0, 1.5)]
)
def test_a_relative_band_leaves_nan_reference_u_out(kind, low, high):
    """One NaN u among the reference candidates made the bounds NaN: every candidate infeasible."""
    band = UncertaintyBand(low=low, high=high, kind=kind)
    reference = torch.arange(5.0).repeat(2, 1)
    with_nan = reference.clone()
    with_nan[0, 4] = float("nan")
    clean = [bound.squeeze(-1).tolist() for bound in band.resolve(reference)]
    bounds = [bound.squeeze(-1).tolist() for bound in band.resolve(with_nan)]
    left_out = [bound.squeeze(-1).tolist() for bound in band.resolve(reference[:, :4])]
    assert [b[0] for b in bounds] == [b[0] for b in left_out]  # row 0: as without the NaN
    assert [b[1] for b in bounds] == [b[1] for b in clean]  # row 1: unchanged


def test_a_plan_in_a_band_avoids_candidates_whose_u_is_nan():
    """u = |a|, NaN wherever the action exceeds 0.5: the band resolves from the others and the
    plan never takes a NaN-u candidate."""
    model = PlanningModel(integrator_model(), integrator_cost)

    class AbsActionNaNAbove(torch.nn.Module):
        obs_dim, action_dim, window, window_local = 1, 1, 1, True

        def score_sequence(self, x):
            u = x[..., 1].abs()
            return u.masked_fill(u > 0.5, float("nan"))

    model.uncertainty = AbsActionNaNAbove()
    objective = Objective(alpha=0.0, band=UncertaintyBand(low=0.5, high=1.5, kind="mean_ratio"))
    torch.manual_seed(0)
    planner = CEMPlanner(model, objective, horizon=4, num_candidates=200, num_elites=20)
    result = planner.plan(torch.zeros(4, 1), torch.zeros(4, 1), torch.full((1,), 0.5))
    assert bool(result.feasible) and torch.isfinite(result.uncertainty).all()
    assert float(result.actions.abs().max()) <= 0.5
