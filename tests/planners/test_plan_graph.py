"""A planner's whole call is one graph: ``torch.compile(plan_graph, fullgraph=True)`` traces it
with no graph break (so a CUDA graph can replay it), gives eager's plan from the same RNG state,
and the checks that need the host read its flags after the call, with the same messages.

Traced with the ``eager`` backend (Dynamo's tracing, no C++ build: seconds, so ``make test``
guards against a new graph break); Inductor's own build is in test_compiled_planning.py."""

from __future__ import annotations

import pytest
import torch

from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlannerBase,
    PlanningModel,
    RandomShootingPlanner,
    UncertaintyBand,
)
from torchrl_recon.planners.base import PlanOutput
from torchrl_recon.planners.executors import compiled_plan
from torchrl_recon.planners.planning_model import gather_candidates
from torchrl_recon.planners.sampling import SamplingPlanner

H = 4


def _model(cost=None) -> PlanningModel:
    torch.manual_seed(0)
    world = fitted(LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8))
    est = fitted(ReconstructionUncertainty(3, 2, window=4, hidden_size=8))
    return PlanningModel(world, cost or (lambda s, a, s2: s2.pow(2).sum(-1)), uncertainty=est)


def _context() -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(1)
    return (
        torch.randn(2, 4, 3, generator=g),
        torch.rand(2, 4, 2, generator=g) * 2 - 1,
        torch.randn(2, 3, generator=g),
    )


PLANNERS = {
    "cem": lambda m, o: CEMPlanner(m, o, horizon=H, num_candidates=12, iterations=2, num_elites=3),
    "mppi": lambda m, o: MPPIPlanner(m, o, horizon=H, num_candidates=12, iterations=2),
    "icem": lambda m, o: ICEMPlanner(
        m, o, horizon=H, num_candidates=12, iterations=2, num_elites=3
    ),
    "shooting": lambda m, o: RandomShootingPlanner(m, o, horizon=H, num_candidates=12),
}


# All four in make test-all (22 s of tracing); make test traces CEM's and iCEM's whole plans as
# one graph, bitwise eager, in test_compiled_plans.py (every batch size; MPC steps with a band).
@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(PLANNERS))
def test_the_whole_plan_is_one_graph_and_plans_what_eager_does(kind):
    planner = PLANNERS[kind](_model(), Objective(beta=0.1))
    ctx = _context()
    torch.manual_seed(5)
    eager = planner.plan(*ctx)
    graph = compiled_plan(type(planner).plan_graph, "default", "eager")  # fullgraph=True
    torch.manual_seed(5)
    traced = planner._checked(graph(planner, *ctx, None, None))
    for name in ("actions", "states", "cost", "uncertainty", "objective", "feasible"):
        torch.testing.assert_close(getattr(traced, name), getattr(eager, name), rtol=0, atol=0)


def test_the_host_checks_read_the_graphs_flags_with_the_same_messages():
    nan_cost = _model(cost=lambda s, a, s2: s2.sum(-1) * float("nan"))
    planner = PLANNERS["cem"](nan_cost, Objective())
    graph = compiled_plan(type(planner).plan_graph, "default", "eager")
    with pytest.raises(
        FloatingPointError,
        match="every candidate's predicted objective is NaN for 2 of 2 batch element",
    ):
        planner._checked(graph(planner, *_context(), None, None))
    band = Objective(beta=0.1, band=UncertaintyBand(1e6, 2e6))  # no u reaches it
    strict = CEMPlanner(
        _model(),
        band,
        horizon=H,
        num_candidates=12,
        iterations=2,
        num_elites=3,
        on_infeasible="raise",
    )
    graph = compiled_plan(type(strict).plan_graph, "default", "eager")
    with pytest.raises(Exception, match="No candidate met the constraints"):
        strict._checked(graph(strict, *_context(), None, None))


def test_planning_compile_compiles_the_whole_call_of_the_sampling_planners_only():
    model = _model()
    assert all(PLANNERS[k](model, Objective()).compiles_whole_call for k in PLANNERS)
    assert not GradientPlanner.compiles_whole_call and not PlannerBase.compiles_whole_call


class _AroundBest(SamplingPlanner):
    """A sampling planner of its own: two methods, and the shared loop."""

    def sample(self, best, step):
        if step.first_batch is not None:
            return step.first_batch
        return self._clamp(best + 0.1 * self._span * step.noise)

    def update(self, best, candidates, prediction, bounds):
        index = self._rank(prediction, bounds).argmax(-1, keepdim=True)
        return gather_candidates(candidates, index), index


@pytest.mark.slow  # 7 s of tracing; CEM's and iCEM's whole-plan graphs run the same loop
def test_a_sampling_planner_of_two_methods_is_one_graph_too():
    band = Objective(beta=0.1, band=UncertaintyBand(low=0.25, high=0.75, kind="quantile"))
    planner = _AroundBest(
        _model(), band, horizon=H, num_candidates=12, iterations=3, block_rows=None,
        on_infeasible="fallback",
    )  # fmt: skip
    ctx, init = _context(), torch.zeros(2, H, 2)
    torch.manual_seed(5)
    eager = planner.plan(*ctx, init=init)
    graph = compiled_plan(type(planner).plan_graph, "default", "eager")  # fullgraph=True
    torch.manual_seed(5)
    out = graph(planner, *ctx, init, None)
    assert isinstance(out, PlanOutput) and out.kept is None
    traced = planner._checked(out)
    for name in ("actions", "states", "cost", "uncertainty", "objective", "feasible"):
        torch.testing.assert_close(getattr(traced, name), getattr(eager, name), rtol=0, atol=0)
    # a plan for each row, inside the band
    assert eager.actions.shape == (2, H, 2) and eager.feasible.all()
