"""``planning_compile`` for every plan a user makes: a relative band, iCEM's warm start, any
batch size, an unfitted model, and several calls in a row whose graph outputs a CUDA graph's
next replay would overwrite. Each compiled plan is compared with eager's plan from the same RNG
state, bitwise: Dynamo's ``eager`` backend runs the same ATen ops (the Inductor build of a whole
plan, eager's to 1e-5, is in test_compiled_planning.py). The compiled rollout is checked as
functionalisation leaves it (ATen ops counted, nothing built). The CUDA test
(``reduce-overhead``: CUDA graphs, a fall-back to eager refused) skips without a GPU."""

from __future__ import annotations

import dataclasses
import functools
import warnings

import pytest
import torch
from torch._dynamo.backends.common import aot_autograd

import torchrl_recon.planners.executors as executors
from tests.compilers import needs_cpp_compiler
from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    InfeasiblePlanWarning,
    MPPIPlanner,
    Objective,
    PlanningModel,
    UncertaintyBand,
)
from torchrl_recon.planners.executors import compiled_plan, plan_graphs
from torchrl_recon.policies.exploration import exploration_objective

H = 4
NEEDS_CUDA = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is False)"
)
FIELDS = ("actions", "states", "cost", "uncertainty", "objective", "feasible")


def _networks(device: str = "cpu", *, fit: bool = True):
    torch.manual_seed(0)
    world = LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8)
    est = ReconstructionUncertainty(3, 2, window=4, hidden_size=8)
    if fit:
        world, est = fitted(world), fitted(est)
    return world.to(device), est.to(device)


def _twins(device: str = "cpu", compile: bool | str = True):
    """An eager planning model and a compiled one on the same networks."""
    world, est = _networks(device)
    cost = lambda s, a, s2: s2.pow(2).sum(-1)  # noqa: E731
    eager = PlanningModel(world, cost, uncertainty=est)
    return eager, PlanningModel(world, cost, uncertainty=est, compile=compile)


def _context(batch: int = 2, device: str = "cpu") -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(batch)
    ctx = (
        torch.randn(batch, 4, 3, generator=g),
        torch.rand(batch, 4, 2, generator=g) * 2 - 1,
        torch.randn(batch, 3, generator=g),
    )
    return tuple(x.to(device) for x in ctx)


PLANNERS = {
    "cem": lambda m, o: CEMPlanner(m, o, horizon=H, num_candidates=12, iterations=2, num_elites=3),
    "mppi": lambda m, o: MPPIPlanner(m, o, horizon=H, num_candidates=12, iterations=2),
    "icem": lambda m, o: ICEMPlanner(
        m, o, horizon=H, num_candidates=12, iterations=2, num_elites=3
    ),
}


def _shift(plan: torch.Tensor) -> torch.Tensor:
    """MPCPolicy's warm start: the plan after one executed action, padded with its last."""
    return torch.cat([plan[..., 1:, :], plan[..., -1:, :]], -2)


def _same(compiled, eager, tol: float = 0.0) -> None:
    for name in FIELDS:
        torch.testing.assert_close(
            getattr(compiled, name), getattr(eager, name), rtol=tol, atol=tol, msg=name
        )


@pytest.fixture
def traced(monkeypatch):
    """Planners compile their whole call with Dynamo's ``eager`` backend; the graphs each
    compiled are counted (``traced.graphs``)."""
    graphs: list = []

    def counting(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    monkeypatch.setattr(
        executors, "compiled_plan", functools.partial(compiled_plan, backend=counting)
    )
    counting.graphs = graphs
    return counting


def _mpc_steps(planner, ctx, steps: int, seed: int = 7) -> list:
    """``steps`` plans as an MPC loop makes them: the first cold, then each warm-started from
    the previous plan shifted by one step."""
    plans, init = [], None
    for step in range(steps):
        torch.manual_seed(seed + step)
        plans.append(planner.plan(*ctx, init=init))
        init = _shift(plans[-1].actions)
    return plans


def _two_loops(planner, steps: int) -> list:
    """``steps`` plans of two MPC loops by turns (two contexts of two envs each, as a policy
    re-plans some rows and then others): each loop's first plan cold, its later ones
    warm-started from its previous plan, so a plan's kept elites wait through the other
    loop's plan before they are recalled."""
    contexts = (_context(), tuple(x.flip(0) + 0.5 for x in _context()))
    plans, inits = [], [None, None]
    for step in range(steps):
        torch.manual_seed(11 + step)
        plans.append(planner.plan(*contexts[step % 2], init=inits[step % 2]))
        inits[step % 2] = _shift(plans[-1].actions)
    return plans


def test_relative_bands_resolve_in_one_graph_as_eagerly():
    """The exploration policy's band (``mean_ratio``) and a quantile band resolve without a
    host read (one graph, ``fullgraph=True``), eager's bounds; a NaN u in one row's reference
    is left out of that row's statistic only."""
    reference = torch.tensor([[1.0, 2.0, float("nan"), 3.0], [1.0, 2.0, 3.0, 4.0]])
    for band in (
        exploration_objective(ratio=0.5, cap=2.0).band,
        UncertaintyBand(0.25, 0.75, kind="quantile"),
    ):
        graph = torch.compile(band.resolve, fullgraph=True, backend="eager")
        for got, want in zip(graph(reference), band.resolve(reference), strict=True):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
    low, high = exploration_objective(ratio=0.5, cap=2.0).band.resolve(reference)
    assert low.flatten().tolist() == [1.0, 1.25] and high.flatten().tolist() == [4.0, 5.0]


@needs_cpp_compiler
def test_icem_mpc_steps_with_a_relative_band_plan_in_one_graph_each_as_eager(traced):
    """Exploration's band and iCEM's elite memory (read before the graph, written after it):
    six plans of two MPC loops by turns (cold, then warm starts that recall the kept elites)
    are eager's plans bitwise, from two graphs (cold, warm); the memory is eager's."""
    eager, compiled = _twins()
    objective = exploration_objective(ratio=1.1, cap=3.0, beta=-0.1)
    ours, theirs = (PLANNERS["icem"](m, objective) for m in (compiled, eager))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InfeasiblePlanWarning)
        got, want = _two_loops(ours, 6), _two_loops(theirs, 6)
    for a, b in zip(got, want, strict=True):
        _same(a, b)
    assert len(traced.graphs) == 2
    torch.testing.assert_close(ours.memory.elites, theirs.memory.elites, rtol=0, atol=0)
    assert ours._recall(_shift(got[-1].actions))[1].all()  # the last plan's elites are found


@needs_cpp_compiler
def test_every_batch_size_plans_with_two_graphs_of_the_planners_own(traced):
    """Batches of 1 to 10 envs in any order plan eager's plans with two graphs (one env, and
    one of a dynamic batch for the rest), no recompile limit reached; each planner and mode
    compiles into a cache of its own."""
    eager, compiled = _twins()
    ours, theirs = (PLANNERS["cem"](m, Objective(beta=0.1)) for m in (compiled, eager))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no recompile limit reached, no fall-back
        for batch in (1, 2, 3, 5, 8, 10, 1, 4):
            torch.manual_seed(batch)
            expected = theirs.plan(*_context(batch))
            torch.manual_seed(batch)
            _same(ours.plan(*_context(batch)), expected)
    assert len(traced.graphs) == 2
    other = PLANNERS["cem"](compiled, Objective(beta=0.1))
    pairs = ((ours, "default"), (other, "default"), (ours, "reduce-overhead"))
    codes = [plan_graphs(p).graph(p, m).compiled.__code__ for p, m in pairs]
    entries = [len(torch._C._dynamo.eval_frame._debug_get_cache_entry_list(c)) for c in codes]
    assert len(set(map(id, codes))) == 3 and entries == [2, 0, 0]


@needs_cpp_compiler
def test_an_unfitted_model_is_refused_before_the_first_compiled_call(traced):
    world, est = _networks(fit=False)
    model = PlanningModel(world, lambda s, a, s2: s2.pow(2).sum(-1), compile=True)
    planner = PLANNERS["cem"](model, Objective())
    with pytest.raises(ValueError, match=r"^the world model's normalisation \(obs_norm") as error:
        planner.plan(*_context())
    assert "\n" not in str(error.value) and traced.graphs == []


@needs_cpp_compiler
def test_a_plan_that_cannot_be_one_graph_is_refused_in_one_line(traced):
    """A cost that reads the host inside the graph (a data-dependent branch): one line naming
    the planner, torch.compile's first line and the way out, not Dynamo's whole trace."""
    world, est = _networks()

    def cost(s, a, s2):
        return s2.pow(2).sum(-1) * (2.0 if bool(s2.sum() > 0) else 1.0)

    planner = PLANNERS["cem"](PlanningModel(world, cost, compile=True), Objective())
    with pytest.raises(RuntimeError, match=r"^planning_compile: CEMPlanner's plan could not") as e:
        planner.plan(*_context())
    assert "\n" not in str(e.value) and "planning_compile=false" in str(e.value)


class _IntoBuffer(torch.autograd.Function):
    """``x`` copied into ``buffer``, returned as a view of it; the gradient goes to ``x``."""

    @staticmethod
    def forward(ctx, x, buffer):
        return buffer.copy_(x).view_as(buffer)

    @staticmethod
    def backward(ctx, grad):
        return grad, None


def _replaying(fn, *args, **kwargs):
    """``fn`` as a CUDA graph returns its outputs: in memory of the graph's own, which its next
    call overwrites (emulated on the CPU: each output is copied into a buffer kept per output
    slot and shape; autograd flows through the copy)."""
    buffers: dict = {}

    def keep(slot, x):
        if not isinstance(x, torch.Tensor):
            return x
        key = (slot, tuple(x.shape), x.dtype)
        if key not in buffers:
            buffers[key] = torch.empty_like(x, requires_grad=False)
        return _IntoBuffer.apply(x, buffers[key])

    def kept(slot, x):  # a Prediction, a PlanOutput: each tensor of each field, nested
        if dataclasses.is_dataclass(x):
            fields = dataclasses.fields(x)
            return dataclasses.replace(
                x, **{f.name: kept(f"{slot}.{f.name}", getattr(x, f.name)) for f in fields}
            )
        return keep(slot, x)

    @functools.wraps(fn)
    def call(*a, **kw):
        return kept("out", fn(*a, **kw))

    return call


@pytest.mark.parametrize("kind", [*sorted(PLANNERS), "gradient"])
def test_plans_in_a_row_keep_nothing_a_replay_overwrites(kind, monkeypatch):
    """Six plans in a row, of two MPC loops by turns, whose compiled graphs hand back outputs
    that the next call overwrites, as a CUDA graph's replay does (the whole call's graph and the
    planning model's pass, emulated without compiling): every plan is eager's, so nothing a
    planner keeps between calls (iCEM's elites) or reads after a later pass (the gradient
    planner's samples of every step) is left in a graph's memory."""
    monkeypatch.setattr(executors, "compiled_plan", _replaying)
    monkeypatch.setattr(executors, "compiled_pass", functools.cache(_replaying))
    eager, compiled = _twins()
    if kind == "gradient":
        make = lambda m: GradientPlanner(m, Objective(beta=0.1), horizon=H, restarts=3, steps=3)  # noqa: E731
    else:
        make = lambda m: PLANNERS[kind](m, Objective(beta=0.1))  # noqa: E731
    got, want = _two_loops(make(compiled), 6), _two_loops(make(eager), 6)
    for a, b in zip(got, want, strict=True):
        _same(a, b)


def _traced_rollout_ops(world, horizon: int) -> dict:
    """The ATen ops (name → count) of ``world``'s no-grad rollout of ``horizon`` steps as
    ``torch.compile`` sees it after functionalisation (nothing built), checked against eager."""
    obs, actions = torch.randn(5, 3), torch.rand(5, horizon, 2)
    state = world.warmup(torch.randn(5, 4, 3), torch.randn(5, 4, 2))
    counts: dict = {}

    def count(gm, example_inputs):
        for node in gm.graph.nodes:
            if node.op == "call_function":
                name = getattr(node.target, "__name__", str(node.target)).split(".")[0]
                counts[name] = counts.get(name, 0) + 1
        return gm.forward

    def rollout(a):
        return world.rollout(obs, a, state)

    with torch.no_grad(), torch._dynamo.config.patch(allow_rnn=True):  # reads the LSTM's weights
        compiled = torch.compile(rollout, backend=aot_autograd(fw_compiler=count), fullgraph=True)
        torch.testing.assert_close(compiled(actions), rollout(actions), rtol=0, atol=0)
    return counts


def test_the_traced_rollout_rewrites_no_buffer_and_runs_three_matmuls_a_step():
    """The no-grad rollout as ``torch.compile`` sees it: eager's states bitwise, three matmuls
    a step (the gates, the dense layer, the state), no scatter into a buffer (a write into a
    view of a preallocated slab became a copy of the whole slab per step) and at most 23 ATen
    nodes a step (31 before)."""
    world, _ = _networks()
    short, long = _traced_rollout_ops(world, 2), _traced_rollout_ops(world, 6)
    per_step = {op: (long.get(op, 0) - short.get(op, 0)) / 4 for op in long}
    assert per_step.get("mm", 0) + per_step.get("addmm", 0) == 3, per_step
    assert not {"slice_scatter", "select_scatter", "copy", "copy_"} & set(long), long
    assert sum(per_step.values()) <= 23, per_step


@NEEDS_CUDA
@pytest.mark.parametrize("kind", [*sorted(PLANNERS), "gradient"])
def test_cuda_graph_plans_in_a_row_are_eagers(kind, monkeypatch):
    """On a GPU under ``reduce-overhead`` with ``TORCHINDUCTOR_CUDAGRAPH_OR_ERROR=1`` (a graph
    that cannot be a CUDA graph is an error, not a silent eager run): five MPC steps in a row,
    each replaying the CUDA graphs of the steps before, plan what eager does to float rounding
    (``fallback_random``: eager's random numbers)."""
    monkeypatch.setenv("TORCHINDUCTOR_CUDAGRAPH_OR_ERROR", "1")
    eager, compiled = _twins("cuda", compile="reduce-overhead")
    if kind == "gradient":
        make = lambda m: GradientPlanner(m, Objective(beta=0.1), horizon=H, restarts=3, steps=3)  # noqa: E731
    else:
        make = lambda m: PLANNERS[kind](m, Objective(beta=0.1))  # noqa: E731
    ctx = _context(2, "cuda")
    with torch._inductor.config.patch({"triton.cudagraph_or_error": True, "fallback_random": True}):
        got = _mpc_steps(make(compiled), ctx, 5)
    want = _mpc_steps(make(eager), ctx, 5)
    for a, b in zip(got, want, strict=True):
        _same(a, b, tol=1e-4)
