"""How planning runs fast: ``torch.compile`` and CPU row-block threads, around the eager core.

:class:`~torchrl_recon.planners.planning_model.PlanningModel` and the planners are written as
their eager algorithm: the model's pass rolls out, costs and scores a block of candidates, and
a planner's ``plan_graph`` is its whole call. ``PlanningModel(compile=..., threads=...)`` picks
one executor here (:func:`executor_for`); the model's pass and the planners' ``plan`` run
through it:

- :class:`Eager` (the default): as written.
- :class:`Compiled` (``compile``): the one-block pass under ``torch.compile``
  (``compiled_pass``) and a sampling planner's whole call as one graph
  (``compiled_plan``), Dynamo's errors turned into one line.
- :class:`Threaded` (``compile`` and ``threads`` above 1): on the CPU, the pass's row blocks
  on ``threads`` threads at once (``planners.cpu_threads``), each block one call compiled with
  Inductor's C++ wrapper, which runs without the GIL (:func:`threaded_pass`); with autograd or
  on another device, as :class:`Compiled`.
"""

from __future__ import annotations

import functools
import types
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from torchrl_recon.devices import check_compile_support
from torchrl_recon.modules.checks import in_graph
from torchrl_recon.planners.cpu_threads import check_threads, run_aside, run_blocks

if TYPE_CHECKING:
    from torchrl_recon.planners.base import PlannerBase, PlanOutput
    from torchrl_recon.planners.planning_model import PlanningModel, Prediction

__all__ = [
    "COMPILE_MODES",
    "Compiled",
    "Eager",
    "Threaded",
    "compile_mode",
    "executor_for",
    "threaded_pass",
]

COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
"""``torch.compile``'s modes, for ``PlanningModel(compile=...)``."""

MOVED_FROM_PLANNERS = {
    "cpu_threads": ("run_aside", "run_blocks"),
    "executors": ("COMPILE_MODES", "compile_mode", "threaded_pass"),
}
"""The speed names ``torchrl_recon.planners`` exported before, by the module each is public in
now: the package still gives them, with a DeprecationWarning naming that module."""


def compile_mode(compile: object) -> str | None:
    """The ``torch.compile`` mode that a ``compile`` switch asks for: None for False, ``"default"``
    for True, else one of :data:`COMPILE_MODES`.

    Examples:
        >>> compile_mode(False), compile_mode(True), compile_mode("reduce-overhead")
        (None, 'default', 'reduce-overhead')
        >>> compile_mode("fast")
        Traceback (most recent call last):
        ...
        ValueError: compile must be True, False or one of ['default', 'reduce-overhead', 'max-autotune', 'max-autotune-no-cudagraphs'], got 'fast'.
    """
    if compile is True or compile is False:
        return "default" if compile else None
    if isinstance(compile, str) and compile in COMPILE_MODES:
        return compile
    raise ValueError(
        f"compile must be True, False or one of {list(COMPILE_MODES)}, got {compile!r}."
    )


def executor_for(compile: object, threads: object, device: torch.device) -> Eager:
    """The executor of ``PlanningModel(compile=compile, threads=threads)`` on ``device``: the
    one place a planning model's speed path is chosen.

    Raises:
        ValueError: an unknown ``compile`` mode, ``threads`` not a positive int, or
            ``threads`` above 1 without ``compile``.
        CompilerNotFoundError: ``compile`` on a CPU without a C++ compiler.

    Examples:
        >>> executor_for(False, 1, torch.device("cpu"))
        Eager()
        >>> executor_for(False, 2, torch.device("cpu"))
        Traceback (most recent call last):
        ...
        ValueError: threads=2 runs the row blocks in parallel only as compiled calls (eager ops hold Python's GIL between kernels: slower than one thread); pass compile=True too, or threads=1.
    """
    mode = compile_mode(compile)
    if mode is not None:
        check_compile_support(device)
    count = check_threads(threads)
    if count > 1 and mode is None:
        raise ValueError(
            f"threads={threads} runs the row blocks in parallel only as compiled calls "
            "(eager ops hold Python's GIL between kernels: slower than one thread); pass "
            "compile=True too, or threads=1."
        )
    if mode is None:
        return Eager()
    return Compiled(mode) if count == 1 else Threaded(mode, count)


class Eager:
    """Runs a planning model's pass and a planner's whole call as written: no compile, one
    thread. :class:`Compiled` and :class:`Threaded` change how, never what.

    Examples:
        >>> Eager().compile_mode, Eager().threads, Eager().later(None, lambda: 42)()
        (None, 1, 42)
    """

    compile_mode: str | None = None
    """The ``torch.compile`` mode of the pass (None: eager)."""
    threads: int = 1
    """The threads a pass's row blocks run on."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    def predict(
        self,
        model: PlanningModel,
        context: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        actions: torch.Tensor,
        state: tuple[torch.Tensor, ...] | None,
        block_rows: int | None,
    ) -> Prediction:
        """``model``'s prediction for candidates ``actions``: its blocks of about
        ``block_rows`` rows one after another, each block this executor's :meth:`pass_for`."""
        return model._in_blocks(self.pass_for(model), context, actions, state, block_rows)

    def pass_for(self, model: PlanningModel) -> Callable[..., Prediction]:
        """The one-block pass ``model``'s blocks run, ``pass(model, *context, actions, state,
        with_u=...)``: its eager ``_predict``."""
        return type(model)._predict

    def later(self, model: PlanningModel, fn: Callable[[], torch.Tensor]) -> Callable:
        """``fn`` itself: it runs when called (:meth:`Threaded.later` starts it now)."""
        return fn

    def blocks_in_threads(self, model: PlanningModel) -> bool:
        """Whether a pass without autograd runs ``model``'s row blocks on threads: never."""
        return False

    def plan(
        self,
        planner: PlannerBase,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        init: torch.Tensor | None,
        generator: torch.Generator | None,
        carry: tuple[torch.Tensor, ...] | None,
    ) -> PlanOutput:
        """``planner``'s whole call, ``plan_graph``, run eagerly."""
        return planner.plan_graph(context_obs, context_action, observation, init, generator, carry)


class Compiled(Eager):
    """:class:`Eager` with the pass under ``torch.compile`` of ``mode`` (one of
    :data:`COMPILE_MODES`), and a planner that is one graph (``compiles_whole_call``: the
    sampling planners) compiled whole, a graph per planner and mode.

    Examples:
        >>> Compiled("reduce-overhead")
        Compiled('reduce-overhead')
    """

    def __init__(self, mode: str) -> None:
        self.compile_mode = mode

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.compile_mode!r})"

    def pass_for(self, model: PlanningModel) -> Callable[..., Prediction]:
        """The compiled pass, or the eager one inside a plan's graph (which inlines it)."""
        if in_graph():
            return type(model)._predict
        return compiled_pass(type(model)._predict, self.compile_mode)

    def whole(self, planner: PlannerBase) -> bool:
        """Whether ``planner``'s whole call compiles as one graph: where it is one."""
        return planner.compiles_whole_call

    def plan(
        self,
        planner: PlannerBase,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        init: torch.Tensor | None,
        generator: torch.Generator | None,
        carry: tuple[torch.Tensor, ...] | None,
    ) -> PlanOutput:
        """``planner``'s ``plan_graph`` as one compiled graph, its outputs copied out of the
        graph's memory (a CUDA graph's next replay overwrites them), the batch dims dynamic;
        eager (its pass compiled) for a planner that is not one graph or a call with a
        ``generator`` (the graph draws from the global RNG), and past Dynamo's recompile
        limit (with one warning).

        Raises:
            RuntimeError: the plan is not one graph, in one line (Dynamo's trace chained).
        """
        args = (context_obs, context_action, observation, init, generator, carry)
        if generator is not None or not self.whole(planner):
            return planner.plan_graph(*args)
        carried = () if carry is None else carry
        batch = observation.ndim - 1
        mark_batch_dynamic(batch, context_obs, context_action, observation, init, *carried)
        kept = plan_graphs(planner)
        try:
            out = kept.graph(planner, self.compile_mode)(planner, *args)
        except torch._dynamo.exc.FailOnRecompileLimitHit:
            if not kept.warned:
                kept.warned = True
                warnings.warn(
                    f"planning_compile: this {type(planner).__name__} has compiled as many "
                    f"graphs as torch._dynamo's recompile_limit "
                    f"({torch._dynamo.config.recompile_limit}) allows; a call of another shape "
                    f"(here observation {tuple(observation.shape)}) runs uncompiled but for "
                    "the planning model's pass.",
                    RuntimeWarning,
                    stacklevel=3,
                )
            return planner.plan_graph(*args)
        except torch._dynamo.exc.TorchDynamoException as error:  # its message: a whole trace
            raise RuntimeError(
                f"planning_compile: {type(planner).__name__}'s plan could not be compiled as "
                f"one graph ({type(error).__name__}: {str(error).strip().splitlines()[0]}); "
                "plan without it (planning_compile=false, PlanningModel(compile=False)) and "
                "report it; the CLI's --debug prints torch.compile's trace."
            ) from error
        return out.copied()


class Threaded(Compiled):
    """:class:`Compiled` whose pass, on the CPU and without autograd, runs its row blocks on
    ``threads`` threads at once, one core each; a planner then compiles only this pass, not
    its whole call. Each block is one :func:`threaded_pass` call, which releases the GIL.

    Examples:
        >>> Threaded("default", 2)
        Threaded('default', threads=2)
    """

    def __init__(self, mode: str, threads: int) -> None:
        super().__init__(mode)
        self.threads = threads
        self.shapes: set[tuple] = set()  # the block shapes run in threads so far

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.compile_mode!r}, threads={self.threads})"

    def blocks_in_threads(self, model: PlanningModel) -> bool:
        """Whether a pass without autograd runs ``model``'s row blocks on threads: on the CPU."""
        return model.action_low.device.type == "cpu"

    def whole(self, planner: PlannerBase) -> bool:
        """As :meth:`Compiled.whole`, but never while the pass runs its blocks on threads."""
        return super().whole(planner) and not self.blocks_in_threads(planner.model)

    def later(self, model: PlanningModel, fn: Callable[[], torch.Tensor]) -> Callable:
        """``fn`` started now on a block thread where the pass runs its blocks on threads (the
        serial work before the call overlaps it); ``.result`` waits for it."""
        if not self.blocks_in_threads(model) or in_graph():
            return fn
        return run_aside(fn, self.threads).result

    def predict(
        self,
        model: PlanningModel,
        context: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        actions: torch.Tensor,
        state: tuple[torch.Tensor, ...] | None,
        block_rows: int | None,
    ) -> Prediction:
        """:meth:`Eager.predict`, its blocks on threads where :meth:`blocks_in_threads` and
        without autograd: a multiple of ``threads`` blocks of equal size (each at most
        ``block_rows`` rows where it can be), the last padded with copies of its last candidate
        so every block has the compiled shape.

        Each block thread also copies its block's prediction into its rows of one prediction
        made beforehand (``copy_`` releases the GIL), so joining the blocks is no serial
        ``torch.cat`` on the calling thread: what stays serial between passes bounds the gain
        from more cores."""
        if not self.blocks_in_threads(model) or torch.is_grad_enabled() or in_graph():
            return super().predict(model, context, actions, state, block_rows)
        with_u = model._row_independent_u
        batch_rows, k = int(context[2].shape[:-1].numel()), actions.shape[-3]
        rows_per_block = block_rows or batch_rows * k
        blocks = -(-batch_rows * k // rows_per_block)  # blocks the rows need, at least
        blocks = min(k, -(-blocks // self.threads) * self.threads)
        chunk = -(-k // blocks)
        blocks = -(-k // chunk)
        padded = actions
        if chunk * blocks > k:
            last = actions[..., -1:, :, :]
            pad = last.expand(*last.shape[:-3], chunk * blocks - k, *last.shape[-2:])
            padded = torch.cat([actions, pad], -3)
        parts = padded.split(chunk, dim=-3)
        joined = model._empty_prediction(padded, with_u)
        predict = threaded_pass(type(model)._predict, self.compile_mode)

        def block(i: int) -> None:
            part = predict(model, *context, parts[i].contiguous(), state, with_u=with_u)
            rows = slice(i * chunk, (i + 1) * chunk)
            joined.states[..., rows, :, :].copy_(part.states)
            joined.cost[..., rows, :].copy_(part.cost)
            if joined.uncertainty is not None:
                joined.uncertainty[..., rows, :].copy_(part.uncertainty)

        shapes = (*(tuple(x.shape) for x in (*context, parts[0])), with_u)
        first_alone = shapes not in self.shapes  # it compiles, once
        run_blocks(block, len(parts), self.threads, first_alone=first_alone)
        self.shapes.add(shapes)
        return model._scored(joined.first(k), context, actions, with_u)


@functools.cache
def compiled_pass(fn: Callable, mode: str) -> Callable:
    """``torch.compile(fn, mode=mode)``, made once per function and mode: every planning model
    (and every copy of one) shares the compiled code, which takes the model as an argument."""
    return torch.compile(fn, mode=mode)


@functools.cache
def threaded_pass(fn: Callable, mode: str) -> Callable:
    """``torch.compile(fn)`` with Inductor's C++ wrapper and ``mode``'s options (one of
    :data:`COMPILE_MODES`), one graph (``fullgraph=True``), made once per function and mode.

    The C++ wrapper releases the GIL for the whole compiled call (Inductor's
    ``cpp_wrapper_cpu``), which is what lets :class:`Threaded` run a pass's blocks in
    parallel (``PlanningModel(threads=...)``). Called with Dynamo's ``allow_rnn`` on, as
    ``compiled_plan``.

    Examples:
        >>> threaded_pass(abs, "fast")
        Traceback (most recent call last):
        ...
        ValueError: mode must be one of ['default', 'reduce-overhead', 'max-autotune', 'max-autotune-no-cudagraphs'], got 'fast'.
    """
    if not isinstance(mode, str) or mode not in COMPILE_MODES:
        raise ValueError(f"mode must be one of {list(COMPILE_MODES)}, got {mode!r}.")
    options = {**torch._inductor.list_mode_options(mode), "cpp_wrapper": True}
    options.pop("triton.cudagraphs", None)  # a CPU pass: no CUDA graphs
    return _allowing_rnn(fn, torch.compile(fn, fullgraph=True, options=options))


def compiled_plan(fn: Callable, mode: str, backend: str | Callable = "inductor") -> Callable:
    """``torch.compile(fn, mode=mode, fullgraph=True)``: a planner's whole call as one graph
    (a graph break is an error, not a slow path); it takes the planner as an argument.

    Each call makes a new compiled function with a Dynamo cache of its own: Dynamo keeps the
    graphs it compiled, and counts them against ``torch._dynamo.config.recompile_limit`` (8),
    per code object, so the function is compiled from a copy of ``fn``'s code
    (``own_code``). ``PlanGraphs`` calls this once per planner and mode: every
    planner instance and mode has its own graphs, and one planner's shapes never use up
    another's recompiles. Called with Dynamo's ``allow_rnn`` on: the world model's context
    warm-up is an ``nn.LSTM``, which Dynamo otherwise refuses to trace (its own error names the
    switch ``torch._dynamo.config.allow_rnn``; there is no public one)."""
    own = own_code(fn)
    compiled = torch.compile(
        own, mode=None if backend != "inductor" else mode, fullgraph=True, backend=backend
    )
    call = _allowing_rnn(fn, compiled)
    call.compiled = own  # what Dynamo compiles: its code object holds the graphs
    return call


@dataclass
class PlanGraphs:
    """What :class:`Compiled` compiled for one planner: its whole call's graph per mode, and
    whether it warned of the recompile limit. Kept on the planner (``_plan_graphs``); a copy
    or a pickle of the planner leaves it behind and compiles its own.

    Examples:
        >>> PlanGraphs()
        PlanGraphs(graphs={}, warned=False)
    """

    graphs: dict[str, Callable] = field(default_factory=dict)
    warned: bool = False

    def graph(self, planner: PlannerBase, mode: str) -> Callable:
        """``planner``'s compiled ``plan_graph`` for ``mode``, made at its first call."""
        if mode not in self.graphs:
            self.graphs[mode] = compiled_plan(type(planner).plan_graph, mode)
        return self.graphs[mode]


def plan_graphs(planner: PlannerBase) -> PlanGraphs:
    """The ``PlanGraphs`` of ``planner``, made at its first compiled call."""
    return planner.__dict__.setdefault("_plan_graphs", PlanGraphs())


def own_code(fn: Callable) -> Callable:
    """A copy of function ``fn`` with a code object of its own (the same bytecode), so that
    ``torch.compile`` keeps a separate cache of graphs for it.

    Examples:
        >>> def double(x):
        ...     return 2 * x
        >>> twin = own_code(double)
        >>> twin(3), twin.__code__ is double.__code__, twin.__name__
        (6, False, 'double')
    """
    code = fn.__code__.replace()  # a new code object
    twin = types.FunctionType(code, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    twin.__kwdefaults__ = fn.__kwdefaults__
    twin.__qualname__, twin.__doc__, twin.__module__ = fn.__qualname__, fn.__doc__, fn.__module__
    return twin


def mark_batch_dynamic(batch_dims: int, *tensors: torch.Tensor | None) -> None:
    """Mark the leading ``batch_dims`` dims of each tensor (None skipped) dynamic for
    ``torch.compile`` (``torch._dynamo.maybe_mark_dynamic``): a compiled plan's graph then
    serves every batch size of 2 or more (a dim of size 1 stays static: Dynamo specialises
    sizes 0 and 1, so a batch of one has a graph of its own)."""
    for x in tensors:
        if x is None:
            continue
        for dim in range(batch_dims):
            torch._dynamo.maybe_mark_dynamic(x, dim)


def _allowing_rnn(fn: Callable, compiled: Callable) -> Callable:
    """``compiled`` (``fn`` under ``torch.compile``) called with Dynamo's ``allow_rnn`` on."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        with torch._dynamo.config.patch(allow_rnn=True):
            return compiled(*args, **kwargs)

    return call
