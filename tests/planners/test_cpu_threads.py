"""``PlanningModel(threads=N)``: the row blocks of a pass on N CPU threads at once, each block one
call compiled with Inductor's C++ wrapper (no GIL); the same predictions and plans as eager."""

from __future__ import annotations

import multiprocessing
import threading
import time

import pytest
import torch

from tests.compilers import needs_cpp_compiler
from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import (
    CEMPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    base,
    executors,
)
from torchrl_recon.planners.cpu_threads import check_threads, run_aside, run_blocks


def _cost(s, a, s2):
    return s2.pow(2).sum(-1)


def _model(**kwargs) -> PlanningModel:
    torch.manual_seed(0)
    world = fitted(LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8))
    est = fitted(ReconstructionUncertainty(3, 2, window=4, hidden_size=8))
    return PlanningModel(world, _cost, uncertainty=est, **kwargs)


def _context(batch: tuple[int, ...] = ()) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(1)
    return (
        torch.randn(*batch, 4, 3, generator=g),
        torch.rand(*batch, 4, 2, generator=g) * 2 - 1,
        torch.randn(*batch, 3, generator=g),
    )


def test_run_blocks_runs_every_block_once_in_order_on_several_threads_at_one_intra_op_thread():
    seen, lock = [], threading.Lock()

    def block(i: int) -> int:
        with lock:
            seen.append(
                (
                    i,
                    threading.get_ident(),
                    torch.get_num_threads(),
                    torch.is_inference_mode_enabled(),
                )
            )
        return i * 10

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with torch.inference_mode():
            assert run_blocks(block, blocks=5, threads=2) == [0, 10, 20, 30, 40]
        assert torch.get_num_threads() == 2  # the process's count, restored
    finally:
        torch.set_num_threads(before)
    assert sorted(i for i, *_ in seen) == [0, 1, 2, 3, 4]
    assert len({ident for _, ident, *_ in seen}) == 2
    assert all(n == 1 and inference for _, _, n, inference in seen)


def test_run_blocks_can_finish_the_first_block_before_the_others_start():
    events, lock = [], threading.Lock()

    def block(i: int) -> int:
        with lock:
            events.append(("start", i))
        time.sleep(0.05)  # the GIL is free: another thread would start its block now
        with lock:
            events.append(("end", i))
        return i

    assert run_blocks(block, blocks=4, threads=2, first_alone=True) == [0, 1, 2, 3]
    assert events[:2] == [("start", 0), ("end", 0)]
    events.clear()
    run_blocks(block, blocks=4, threads=2)  # without: block 1 starts while block 0 sleeps
    assert events[:2] != [("start", 0), ("end", 0)]


def test_run_blocks_propagates_a_blocks_error():
    def block(i: int) -> int:
        if i == 3:
            raise ValueError("block 3 failed")
        return i

    with pytest.raises(ValueError, match="block 3 failed"):
        run_blocks(block, blocks=4, threads=2)


def test_run_aside_runs_on_a_block_thread_under_the_callers_modes_and_returns_its_value():
    def where() -> tuple[int, bool, bool]:
        return (
            threading.get_ident(),
            torch.is_inference_mode_enabled(),
            torch.is_grad_enabled(),
        )

    with torch.inference_mode():
        ident, inference, grad = run_aside(where, threads=2).result()
    assert ident != threading.get_ident() and inference and not grad
    with pytest.raises(ValueError, match="aside failed"):
        run_aside(lambda: (_ for _ in ()).throw(ValueError("aside failed")), 2).result()


@pytest.mark.parametrize("threads", [0, -2, 1.5, "2", None])
def test_threads_must_be_a_positive_int(threads):
    with pytest.raises((ValueError, TypeError), match="threads"):
        check_threads(threads)
    with pytest.raises((ValueError, TypeError), match="threads"):
        _model(compile=True, threads=threads)


def test_threads_without_compile_is_refused_in_one_line_that_says_why():
    with pytest.raises(ValueError, match=r"threads=2 .* GIL .* pass compile=True too"):
        _model(threads=2)


@needs_cpp_compiler
def test_threads_predict_what_one_eager_thread_does(compile_backend):
    eager, threaded = _model(), _model(compile=True, threads=2)
    assert threaded.executor.blocks_in_threads(threaded)
    assert not eager.executor.blocks_in_threads(eager)
    ctx = _context((2,))  # a batch of 2 contexts (one compiled shape: the plans' below)
    g = torch.Generator().manual_seed(2)
    actions = torch.rand(2, 15, 2, 2, generator=g) * 2 - 1  # 15 candidates: a padded block
    with torch.inference_mode():
        a, b = eager(*ctx, actions), threaded(*ctx, actions)
    for x, y in ((a.states, b.states), (a.cost, b.cost), (a.uncertainty, b.uncertainty)):
        assert y.shape == x.shape
        torch.testing.assert_close(y, x, rtol=1e-5, atol=1e-6)


@needs_cpp_compiler
def test_threads_predict_what_one_eager_thread_does_for_a_world_model_of_members(compile_backend):
    """The blocks' joined prediction has the members' mean states, not one per member."""
    torch.manual_seed(0)
    members = [
        fitted(LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8)) for _ in range(2)
    ]
    world = LSTMWorldModel.from_members(members)
    eager = PlanningModel(world, _cost)
    threaded = PlanningModel(world, _cost, compile=True, threads=2)
    actions = torch.rand(7, 2, 2) * 2 - 1  # 7 candidates: a padded block
    with torch.inference_mode():
        a, b = eager(*_context(), actions), threaded(*_context(), actions)
    assert b.states.shape == a.states.shape == (7, 2, 3) and b.uncertainty is None
    torch.testing.assert_close(b.states, a.states, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(b.cost, a.cost, rtol=1e-5, atol=1e-6)


@needs_cpp_compiler
@pytest.mark.parametrize(  # the draw aside is the shared sampling loop's: CEM in make test
    "planner_class",
    [CEMPlanner, *(pytest.param(c, marks=pytest.mark.slow) for c in (MPPIPlanner, ICEMPlanner))],
)
def test_with_threads_the_sampling_planners_draw_the_next_noise_aside_and_plan_the_same(
    planner_class, monkeypatch, compile_backend
):
    """With threads the planner compiles its pass, not its whole call. The next iteration's
    noise is drawn on a block thread while the last one is ranked; the generator gives the same
    draws in the same order, so the same plans as one eager thread, and nothing more (its next
    draw after the plan is the same too)."""
    draws = []
    draw = base.PlannerBase._draw_shape

    def recording(self, sample, shape, generator):
        draws.append(threading.current_thread() is not threading.main_thread())
        return draw(self, sample, shape, generator)

    def whole_call(*args, **kwargs):
        raise AssertionError("with threads the planner compiles its pass, not its whole call")

    monkeypatch.setattr(base.PlannerBase, "_draw_shape", recording)
    monkeypatch.setattr(executors, "compiled_plan", whole_call)
    ctx = _context((2,))  # the compiled shapes of the prediction test above (15: a padded block)
    plans, after, aside = [], [], []
    for model in (_model(), _model(compile=True, threads=2)):
        draws.clear()
        planner = planner_class(
            model,
            Objective(beta=0.1),
            horizon=2,
            num_candidates=15,
            iterations=3,
            **({} if planner_class is MPPIPlanner else {"num_elites": 4}),
        )
        g = torch.Generator().manual_seed(3)
        plans.append(planner.plan(*ctx, generator=g))
        after.append(torch.rand(4, generator=g))
        aside.append(list(draws))
    # eager: every draw on the caller; threaded: the first batch there, the next two aside
    assert aside == [[False] * 3, [False, True, True]]
    torch.testing.assert_close(plans[1].actions, plans[0].actions, rtol=0, atol=1e-6)
    torch.testing.assert_close(plans[1].objective, plans[0].objective, rtol=1e-5, atol=1e-6)
    assert torch.equal(after[1], after[0])


@needs_cpp_compiler
def test_the_threaded_pass_is_compiled_with_the_cpp_wrapper_that_releases_the_gil(monkeypatch):
    calls = []
    monkeypatch.setattr(
        executors.torch, "compile", lambda fn, **kw: calls.append(kw) or fn, raising=True
    )
    executors.threaded_pass.__wrapped__(lambda: None, "max-autotune")  # past its cache
    (kwargs,) = calls
    assert kwargs["fullgraph"] is True and kwargs["options"]["cpp_wrapper"] is True
    assert kwargs["options"]["max_autotune"] is True
    assert "triton.cudagraphs" not in kwargs["options"]


def _blocks_in_child() -> None:
    assert run_blocks(lambda i: i + 1, blocks=3, threads=2) == [1, 2, 3]


def test_a_forked_child_runs_blocks_on_threads_of_its_own():
    assert run_blocks(lambda i: i, blocks=2, threads=2) == [0, 1]  # the parent's pool exists
    child = multiprocessing.get_context("fork").Process(target=_blocks_in_child)
    child.start()
    child.join(timeout=20)
    if child.exitcode is None:
        child.kill()
    assert child.exitcode == 0  # None: it hung on the parent's pool, which has no threads here
