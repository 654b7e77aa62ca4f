"""``PlanningModel(compile=...)``: the one-block pass under ``torch.compile``, the same
predictions up to float rounding; refused up front where it cannot run."""

from __future__ import annotations

import copy

import pytest
import torch

from tests.compilers import needs_cpp_compiler
from tests.fitting import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel


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
    plan = CEMPlanner(
        compiled, Objective(beta=0.1), horizon=6, num_candidates=16, num_elites=4, iterations=2
    )  # planning_compile compiles the whole plan: one graph (tests/planners/test_plan_graph.py)
    result = plan.plan(*inputs[:3])
    assert result.actions.shape == (6, 2) and result.actions.abs().max() <= 1
    twin = copy.deepcopy(compiled)  # its own weights: the compiled code takes the model
    with torch.no_grad():
        twin.world_model.head.bias.add_(1.0)
        moved, again = twin(*inputs), compiled(*inputs)
    torch.testing.assert_close(again.states, b.states)
    assert not torch.allclose(moved.states, b.states)


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
