"""What every planner shares: the plan result, constraint handling and the final choice."""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from torchrl_recon.modules.checks import check_int, check_type
from torchrl_recon.planners.objective import Objective, rank_key
from torchrl_recon.planners.planning_model import (
    PlanningModel,
    Prediction,
    gather_candidates,
    inputs_checked,
)

__all__ = [
    "InfeasiblePlanError",
    "InfeasiblePlanWarning",
    "PlanFlags",
    "PlanOutput",
    "PlanResult",
    "PlannerBase",
]

OnInfeasible = Literal["fallback", "raise"]


class InfeasiblePlanWarning(RuntimeWarning):
    """No candidate met the constraints; the least-violating one was returned (``feasible=False``)."""


class InfeasiblePlanError(RuntimeError):
    """No candidate satisfied the uncertainty band / cost threshold (with ``on_infeasible="raise"``)."""


@dataclass
class PlanResult:
    """The chosen action sequence and what the model predicts for it.

    Attributes:
        actions: ``[*B, H, M]``.
        states: predicted s_{t+1..t+H}, ``[*B, H, N]``.
        cost: per-step predicted cost, ``[*B, H]``.
        uncertainty: per-step u, ``[*B, H]`` or None.
        objective: J of the chosen sequence, ``[*B]``.
        feasible: ``[*B]`` bool; False means no candidate met the constraints and the least
            violating one was returned (the documented fallback).
    """

    actions: torch.Tensor
    states: torch.Tensor
    cost: torch.Tensor
    uncertainty: torch.Tensor | None
    objective: torch.Tensor
    feasible: torch.Tensor


@dataclass
class PlanFlags:
    """What :meth:`PlannerBase.plan` reads on the host after a plan's graph, to raise or warn.

    Attributes:
        undefined: ``[*B, 1]`` bool: the chosen candidate's objective or violation is NaN,
            which happens only when every candidate's is (NaN ranks last).
        cost_nan: ``[]`` bool: every predicted cost is NaN.
        u_nan: ``[]`` bool: every u is NaN; None without an estimator.
    """

    undefined: torch.Tensor
    cost_nan: torch.Tensor
    u_nan: torch.Tensor | None


@dataclass
class PlanOutput:
    """What :meth:`PlannerBase.plan_graph` returns: the plan, its flags, and what the planner
    keeps for its next call.

    Attributes:
        result: the chosen plan, as :meth:`PlannerBase.plan` returns it once the flags are read.
        flags: the :class:`PlanFlags` the host checks read.
        kept: what the planner keeps for its next call (iCEM's last elites), handed to
            ``_remember`` after the checks; None for most planners.

    Examples:
        >>> t, f = torch.zeros(2, 3, 1), torch.tensor([True, True])
        >>> result = PlanResult(t, t, t[..., 0], None, torch.zeros(2), f)
        >>> flags = PlanFlags(torch.zeros(2, 1, dtype=torch.bool), torch.tensor(False), None)
        >>> out = PlanOutput(result, flags)
        >>> out.copied().result.actions is t, out.copied().flags.u_nan is None
        (False, True)
    """

    result: PlanResult
    flags: PlanFlags
    kept: torch.Tensor | None = None

    def copied(self) -> PlanOutput:
        """A copy of every tensor in it, out of a compiled graph's memory (a CUDA graph's next
        replay overwrites its outputs)."""
        return _copied(self)


def _copied(x):
    """``x`` with every tensor in it (a dataclass's fields, nested) cloned."""
    if isinstance(x, torch.Tensor):
        return x.clone()
    if dataclasses.is_dataclass(x):
        fields = {f.name: _copied(getattr(x, f.name)) for f in dataclasses.fields(x)}
        return dataclasses.replace(x, **fields)
    return x


class PlannerBase(nn.Module):
    """Optimise action sequences over a :class:`PlanningModel` for an :class:`Objective`.

    Subclasses implement ``_optimise``, returning candidates ``[*B, K, H, M]`` with their
    prediction; the base class picks the best feasible one. An iterative sampling planner
    subclasses :class:`SamplingPlanner` instead, which runs the loop and asks for two methods,
    ``sample`` and ``update``. When no candidate is feasible
    the planner falls back to the least-violating candidate and reports ``feasible=False``
    (``on_infeasible="fallback"``, with an :class:`InfeasiblePlanWarning`), or raises :class:`InfeasiblePlanError`
    (``on_infeasible="raise"``).

    Candidates are made on the device and dtype of the planning model (its action bounds):
    move the planner, or the :class:`PlanningModel`, with ``.to(device)`` and pass the context
    on that device.
    """

    def __init__(
        self,
        model: PlanningModel,
        objective: Objective,
        *,
        horizon: int,
        on_infeasible: OnInfeasible = "fallback",
    ) -> None:
        super().__init__()
        check_type("model", model, PlanningModel, "a PlanningModel")
        check_type("objective", objective, Objective, "an Objective")
        check_int("horizon", horizon)
        if objective.needs_uncertainty and model.uncertainty is None:
            raise ValueError(
                "The objective uses uncertainty (beta != 0 or a band) but the planning model has no estimator."
            )
        if on_infeasible not in ("fallback", "raise"):
            raise ValueError(f"on_infeasible must be 'fallback' or 'raise', got {on_infeasible!r}.")
        self.model, self.objective, self.horizon, self.on_infeasible = (
            model,
            objective,
            horizon,
            on_infeasible,
        )

    def _draw(
        self, sample, batch: torch.Size, k: int, generator: torch.Generator | None
    ) -> torch.Tensor:
        """``sample`` (``torch.rand`` or ``torch.randn``) of shape ``[*B, k, H, M]`` (see
        :meth:`_draw_shape`)."""
        return self._draw_shape(sample, (*batch, k, self.horizon, self.model.action_dim), generator)

    def _draw_shape(
        self, sample, shape: tuple[int, ...], generator: torch.Generator | None
    ) -> torch.Tensor:
        """``sample`` (``torch.rand`` or ``torch.randn``) of ``shape`` on the model's device and
        dtype: from the global RNG of that device, or from ``generator`` on its own device, then
        moved."""
        like = self.model.action_low
        if generator is None:
            return sample(shape, dtype=like.dtype, device=like.device)
        drawn = sample(shape, generator=generator, dtype=like.dtype, device=generator.device)
        return drawn.to(like.device)

    def _uniform(
        self, batch: torch.Size, k: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        low, high = self.model.action_low, self.model.action_high
        return low + (high - low) * self._draw(torch.rand, batch, k, generator)

    def _normal(
        self, batch: torch.Size, k: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        return self._draw(torch.randn, batch, k, generator)

    def _clamp(self, actions: torch.Tensor) -> torch.Tensor:
        """``actions`` ``[..., H, M]`` clipped to the bounds (one pass: ``maximum(minimum(...))``'s
        values). The bounds are laid out as ``[H, M]`` first: with an innermost dimension of
        ``M`` (a handful of actions) the clamp runs unvectorised, ~4× slower on the CPU at
        K = 1000, H = 30, M = 3 (94 against 21 µs), and it runs between passes, on one core."""
        shape = actions.shape[-2:]
        low = self.model.action_low.expand(shape).contiguous()
        high = self.model.action_high.expand(shape).contiguous()
        return torch.clamp(actions, low, high)

    def _bounds(self, prediction: Prediction) -> tuple[torch.Tensor, torch.Tensor] | None:
        band = self.objective.band
        return None if band is None else band.resolve(prediction.cumulative_uncertainty)

    def plan(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        *,
        init: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> PlanResult:
        """Plan from a real context ``[*B, T, N]``, ``[*B, T, M]`` and state ``[*B, N]``.

        All on the planning model's device; the result is on it too.

        Keyword Args:
            init: optional warm start ``[*B, H, M]`` (e.g. the previous plan shifted by one step).
            generator: draw the random candidates from this generator (on its own device, then
                moved to the model's), e.g. a CPU ``torch.Generator`` for the same candidates
                on every device. Default: the global RNG of the model's device.

        The planning model's executor runs the whole call, :meth:`plan_graph`
        (:mod:`~torchrl_recon.planners.executors`). With its ``compile`` (a recipe's
        ``planning_compile``) the call runs as one compiled graph (``fullgraph=True``; with
        ``"reduce-overhead"`` on a GPU, a CUDA graph) and its flags are read after it; a call
        with a ``generator`` runs uncompiled (the graph draws from the global RNG). Inductor
        draws its own random numbers unless ``torch._inductor.config.fallback_random`` is set,
        so a compiled plan's candidates differ from eager's for the same seed. With the
        planning model's ``threads`` above 1 on the CPU, only its pass is compiled, and its
        row blocks run on that many threads (:class:`PlanningModel`).

        Everything that needs the host runs outside the graph, as it does uncompiled: the
        input checks, the fitted-normalisation check and ``_recall`` (what the planner
        remembers of its earlier plans, e.g. iCEM's elites) before it, the flags' checks and
        ``_remember`` after it. Each planner compiles its own graphs, one cache per planner and
        mode (``executors.compiled_plan``), with the batch dims ``*B`` dynamic: a batch
        of one and a batch of several are two graphs, every other batch size reuses the
        latter (``docs/planning.md`` lists what recompiles).
        """
        self.model.check_context(context_obs, context_action, observation)
        if init is not None:
            self._check_init(init, observation)
        if generator is not None:
            check_type("generator", generator, torch.Generator, "a torch.Generator or None")
        self.model.check_fitted()  # here, not in the graph: a compiled graph skips it
        carry = self._recall(init)
        with inputs_checked():  # checked above: the passes read no input values on the host
            out = self.model.executor.plan(
                self, context_obs, context_action, observation, init, generator, carry
            )
        result = self._checked(out)
        self._remember(result, out.kept)
        return result

    def _check_init(self, init: torch.Tensor, observation: torch.Tensor) -> None:
        """Refuse a warm start that is not a finite ``[*B, H, M]`` tensor of the model's dtype."""
        check_type("init", init, torch.Tensor, "a tensor [*B, H, M] or None")
        expected = (*observation.shape[:-1], self.horizon, self.model.action_dim)
        if init.shape != expected:
            raise ValueError(f"init has shape {tuple(init.shape)}; expected {expected}.")
        self.model.check_placed("init", init)

    def __getstate__(self) -> dict:
        """A copy or a pickle leaves the executor's compiled graphs behind (the copy compiles
        its own)."""
        state = super().__getstate__()
        state.pop("_plan_graphs", None)
        return state

    def _recall(self, init: torch.Tensor | None):
        """What the planner carries into this call from earlier ones, read before the graph
        (it may need the host): tensors with the batch dims first, or None (the default:
        nothing). It reaches :meth:`_optimise` as ``carry``."""
        return None

    def _remember(self, result: PlanResult, kept: torch.Tensor | None) -> None:
        """Keep ``kept`` (:attr:`PlanOutput.kept`, what :meth:`_optimise` returned to keep,
        copied out of a compiled graph's memory) for later calls, once the plan passed its
        checks; nothing by default."""

    compiles_whole_call: bool = False
    """Whether ``planning_compile`` (the planning model's ``compile``) compiles :meth:`plan_graph`
    whole (``fullgraph=True``): True for the sampling planners (tested graph-break-free);
    False (a planner of one's own, the gradient planner): only the planning model's pass."""

    def plan_graph(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        init: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        carry: tuple[torch.Tensor, ...] | None = None,
    ) -> PlanOutput:
        """The whole planning call as tensor operations with no host synchronisation, so that
        it is one graph (compiled with ``fullgraph=True``; with ``mode="reduce-overhead"``
        on a GPU, one CUDA graph replayed per call): the warm-up on the context, every
        iteration's sampling, rollout, cost, u, ranking and refit, and the final choice.
        Returns a :class:`PlanOutput`: the chosen plan (:class:`PlanResult`), the
        :class:`PlanFlags` that :meth:`plan` reads on the host afterwards, and what the planner
        keeps for its next call (or None). :meth:`plan` checks its inputs first and raises or
        warns from the flags after (the same messages as uncompiled). ``carry``: what
        ``_recall`` found for this call."""
        state = self.model.warmup(context_obs, context_action)  # once per plan
        more = {} if carry is None else {"carry": carry}
        candidates, prediction, bounds, *kept = self._optimise(
            context_obs, context_action, observation, init, state, generator, **more
        )
        objective = self.objective.score(prediction)
        violation = self.objective.violation(prediction, bounds)
        best = self._pick(objective, violation)  # [*B, 1]
        best_objective, best_violation = objective.gather(-1, best), violation.gather(-1, best)
        u = prediction.uncertainty
        chosen, dim = prediction.take(best), best.ndim - 1
        result = PlanResult(
            actions=gather_candidates(candidates, best).squeeze(dim),
            states=chosen.states.squeeze(dim),
            cost=chosen.cost.squeeze(dim),
            uncertainty=None if chosen.uncertainty is None else chosen.uncertainty.squeeze(dim),
            objective=best_objective.squeeze(-1),
            feasible=(best_violation <= 0).squeeze(-1),
        )
        flags = PlanFlags(
            undefined=best_objective.isnan() | best_violation.isnan(),
            cost_nan=prediction.cost.isnan().all(),
            u_nan=None if u is None else u.isnan().all(),
        )
        return PlanOutput(result, flags, kept[0] if kept else None)

    def _optimise(self, context_obs, context_action, observation, init, state, generator):
        """Candidates ``[*B, K, H, M]``, their :class:`Prediction` and the band's bounds (or
        None); optionally a fourth item, what the planner keeps for its next call (handed to
        :meth:`_remember` after the plan). Gets ``carry=`` too when :meth:`_recall` returned
        something."""
        raise NotImplementedError

    def _pick(self, objective: torch.Tensor, violation: torch.Tensor) -> torch.Tensor:
        """The index ``[*B, 1]`` of the candidate returned: the best feasible one by J, else the
        least-violating one (:func:`rank_key`)."""
        return rank_key(objective, violation).argmax(-1, keepdim=True)

    def _checked(self, out: PlanOutput) -> PlanResult:
        """The :class:`PlanResult` of :meth:`plan_graph`'s output, once its flags are read: a
        NaN objective raises, an infeasible plan warns (or raises with ``on_infeasible="raise"``).
        ``out.kept`` (what the planner keeps) is not part of the result: :meth:`plan` hands it
        to :meth:`_remember`."""
        flags, feasible = out.flags, out.result.feasible
        undefined, cost_nan, u_nan = flags.undefined, flags.cost_nan, flags.u_nan
        if undefined.any():  # NaN ranks last: the best is NaN only when every candidate is
            raise FloatingPointError(
                f"every candidate's predicted objective is NaN for {int(undefined.sum())} of "
                f"{undefined.numel()} batch element(s) (cost NaN: {bool(cost_nan)}, uncertainty "
                f"NaN: {u_nan is not None and bool(u_nan)}); the world model, the cost function or "
                "the estimator gives NaN from this context (a diverged fit, or a cost undefined "
                "at these states)."
            )
        if not feasible.all():
            message = (
                f"No candidate met the constraints (band {self.objective.band}, cost_threshold "
                f"{self.objective.cost_threshold}) for {int((~feasible).sum())} of {feasible.numel()} batch "
                "element(s); returning the least-violating candidate (feasible=False)."
            )
            if self.on_infeasible == "raise":
                raise InfeasiblePlanError(message)
            warnings.warn(message, InfeasiblePlanWarning, stacklevel=3)
        return out.result
