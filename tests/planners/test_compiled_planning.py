"""``PlanningModel(compile=...)``: the one-block pass under ``torch.compile``, the same
predictions up to float rounding; a plan's whole call built by Inductor, eager's plan; refused
up front where it cannot run (more compiled-plan cases, traced without Inductor, in
test_compiled_plans.py)."""

from __future__ import annotations

import copy
import warnings

import pytest
import torch

from tests.compilers import needs_cpp_compiler
from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import ICEMPlanner, InfeasiblePlanWarning, PlanningModel
from torchrl_recon.policies.exploration import exploration_objective


def _cost(s, a, s2):
    return s2.pow(2).sum(-1)


def _networks() -> tuple[LSTMWorldModel, ReconstructionUncertainty]:
    torch.manual_seed(0)
    world = fitted(LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8))
    est = ReconstructionUncertainty(3, 2, window=4, hidden_size=8)
    est.fit_normalization(torch.randn(100, 3), torch.rand(100, 2) * 0.2)
    return world, est


def _inputs() -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(1)
    return (
        torch.randn(4, 3, generator=g),
        torch.rand(4, 2, generator=g) * 2 - 1,
        torch.randn(3, generator=g),
        torch.rand(16, 6, 2, generator=g) * 2 - 1,
    )


@pytest.mark.slow  # 15 s of Inductor; test_plan_graph holds the compiled whole plan to eager
@needs_cpp_compiler
def test_a_compiled_pass_predicts_what_the_eager_one_does_and_copies_keep_their_weights():
    world, est = _networks()
    eager = PlanningModel(world, _cost, uncertainty=est)
    compiled = PlanningModel(world, _cost, uncertainty=est, compile=True)
    assert compiled.compile_mode == "default" and eager.compile_mode is None
    inputs = _inputs()
    with torch.no_grad():
        a, b = eager(*inputs), compiled(*inputs)
    for x, y in ((a.states, b.states), (a.cost, b.cost), (a.uncertainty, b.uncertainty)):
        torch.testing.assert_close(y, x, rtol=1e-5, atol=1e-6)
    twin = copy.deepcopy(compiled)  # its own weights: the compiled code takes the model
    with torch.no_grad():
        twin.world_model.head.bias.add_(1.0)
        moved, again = twin(*inputs), compiled(*inputs)
    torch.testing.assert_close(again.states, b.states)
    assert not torch.allclose(moved.states, b.states)


def _shift(plan: torch.Tensor) -> torch.Tensor:
    """MPCPolicy's warm start: the plan after one executed action, padded with its last."""
    return torch.cat([plan[..., 1:, :], plan[..., -1:, :]], -2)


# In make test-all: Inductor's build takes ~45 s with a cold cache (a fresh machine); make test
# traces the same warm-started iCEM plans of an exploration band in one graph each, bitwise
# eager (test_compiled_plans.py::test_icem_mpc_steps_with_a_relative_band_plan_in_one_graph_each_as_eager).
@pytest.mark.slow
@needs_cpp_compiler
def test_an_inductor_built_plan_is_eagers_with_a_band_and_a_warm_start():
    """The whole call built by Inductor, at tiny sizes (what only Inductor shows: its lowering
    of the band's mean, the colored noise's FFT, the fused rollout, the elites carried in, a
    dynamic batch): warm-started iCEM plans of an exploration band, twice in a row, are eager's
    to float rounding (1e-5) with eager's random numbers (``fallback_random``)."""
    world, est = _networks()
    objective = exploration_objective(ratio=1.1, cap=4.0, beta=-0.1)
    ours, theirs = (
        ICEMPlanner(
            PlanningModel(world, _cost, uncertainty=est, compile=compile),
            objective,
            horizon=2,
            num_candidates=8,
            iterations=1,
            num_elites=2,
        )
        for compile in (True, False)
    )
    g = torch.Generator().manual_seed(2)
    ctx = (torch.randn(3, 4, 3, generator=g), torch.rand(3, 4, 2, generator=g), torch.randn(3, 3))
    torch.manual_seed(0)
    first = theirs.plan(*ctx)
    elites = theirs.memory.elites.clone()
    with warnings.catch_warnings(), torch._inductor.config.patch(fallback_random=True):
        warnings.simplefilter("ignore", InfeasiblePlanWarning)
        for _ in range(2):
            for planner in (ours, theirs):
                planner.memory.remember(first.actions, elites)
            torch.manual_seed(1)
            expected = theirs.plan(*ctx, init=_shift(first.actions))
            torch.manual_seed(1)
            got = ours.plan(*ctx, init=_shift(first.actions))
            for name in ("actions", "states", "cost", "uncertainty", "objective", "feasible"):
                want = getattr(expected, name)
                torch.testing.assert_close(getattr(got, name), want, rtol=1e-5, atol=1e-5)
            assert ours._recall(_shift(got.actions))[1].all()  # its kept elites, remembered


def test_compile_asks_for_a_mode_torch_compile_has():
    world, _ = _networks()
    with pytest.raises(ValueError, match=r"compile must be True, False or one of .*got 'fast'"):
        PlanningModel(world, _cost, compile="fast")


def test_compile_without_a_cpp_compiler_is_refused_when_built(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler++")
    world, _ = _networks()
    with pytest.raises(RuntimeError, match=r"'no-such-compiler\+\+' is not on PATH"):
        PlanningModel(world, _cost, compile="reduce-overhead")
    assert PlanningModel(world, _cost).compile_mode is None  # eager needs no compiler
