"""Speed is a wrapper, not a branch: ``PlanningModel(compile=..., threads=...)`` picks one
executor (``planners.executors``) and its pass and the planners' calls run through it; the rest
of the planners is the eager algorithm and spells none of compile's or the threads' names."""

from __future__ import annotations

import copy
import re
import runpy
from pathlib import Path

import pytest
import torch

from tests.compilers import needs_cpp_compiler
from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel, executors
from torchrl_recon.planners.executors import Compiled, Eager, Threaded

PLANNERS_DIR = Path(executors.__file__).parent
# the spellings issue 59 counts (benchmarks/code_shape.py), read from there
SPELLINGS = runpy.run_path(str(Path(__file__).parents[2] / "benchmarks" / "code_shape.py"))[
    "SPELLINGS"
]
THREADS = SPELLINGS["files that spell CPU row-block threads"][0]
COMPILE = SPELLINGS["files that spell torch.compile or its helpers"][0]


def _cost(s, a, s2):
    return s2.pow(2).sum(-1)


def _model(**kwargs) -> PlanningModel:
    torch.manual_seed(0)
    world = fitted(LSTMWorldModel(3, 2, window=2, hidden_size=8, dense_size=8))
    est = fitted(ReconstructionUncertainty(3, 2, window=2, hidden_size=8))
    return PlanningModel(world, _cost, uncertainty=est, **kwargs)


def _context() -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(1)
    return torch.randn(2, 3, generator=g), torch.rand(2, 2, generator=g), torch.randn(3)


def test_an_eager_model_runs_through_the_eager_executor():
    model = _model()
    assert type(model.executor) is Eager
    assert (model.compile_mode, model.threads) == (None, 1)
    assert not model.executor.blocks_in_threads(model)


@needs_cpp_compiler  # the switch checks for one when the model is built (nothing compiles)
def test_compile_and_threads_choose_the_executor_once_and_copies_keep_it():
    compiled, threaded = _model(compile="max-autotune"), _model(compile=True, threads=2)
    assert type(compiled.executor) is Compiled and compiled.compile_mode == "max-autotune"
    assert type(threaded.executor) is Threaded
    assert (threaded.compile_mode, threaded.threads) == ("default", 2)
    assert threaded.executor.blocks_in_threads(threaded)
    twin = copy.deepcopy(threaded)
    assert repr(twin.executor) == "Threaded('default', threads=2)"
    assert twin.executor is not threaded.executor  # its own compiled block shapes


class _Recording(Eager):
    """The eager executor, recording what runs through it."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def predict(self, model, context, actions, state, block_rows):
        self.calls.append("predict")
        return super().predict(model, context, actions, state, block_rows)

    def plan(self, planner, *args):
        self.calls.append("plan")
        return super().plan(planner, *args)


def test_the_pass_and_the_plan_run_through_the_models_executor():
    model = _model()
    model.executor = recording = _Recording()
    planner = CEMPlanner(
        model, Objective(beta=0.1), horizon=3, num_candidates=8, iterations=2, num_elites=4
    )
    planner.plan(*_context())
    assert recording.calls == ["plan", "predict", "predict"]  # one pass per iteration


def test_only_the_executor_spells_compile_and_only_it_and_its_pool_the_threads():
    """planning_model.py spells ``compile_mode`` alone: its property and the re-export that
    ``experiments.config`` imports."""
    spelling = {
        path.name: (re.findall(THREADS, text), re.findall(COMPILE, text))
        for path in sorted(PLANNERS_DIR.glob("*.py"))
        for text in [path.read_text()]
    }
    threads = {name for name, (found, _) in spelling.items() if found}
    compiles = {name for name, (_, found) in spelling.items() if found}
    assert threads == {"executors.py", "cpu_threads.py"}
    assert compiles == {"executors.py", "planning_model.py"}
    assert set(spelling["planning_model.py"][1]) == {"compile_mode"}


@pytest.mark.parametrize("compile", ["fast", 2])
def test_an_unknown_compile_switch_is_refused_in_one_line(compile):
    with pytest.raises(ValueError, match=r"^compile must be True, False or one of \[") as e:
        _model(compile=compile)
    assert "\n" not in str(e.value)
