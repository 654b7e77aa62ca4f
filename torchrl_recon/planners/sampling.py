"""What the iterative sampling planners (CEM, MPPI, iCEM) share: one sampling loop (the first
batch, scoring, the reference bounds, the best sample of every iteration), the Gaussian refit
and the checks; each planner supplies how it samples and how it updates."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from torchrl_recon.modules.checks import check_int
from torchrl_recon.planners.base import OnInfeasible, PlannerBase
from torchrl_recon.planners.objective import Objective, rank_key
from torchrl_recon.planners.planning_model import (
    PlanningModel,
    Prediction,
    check_block_rows,
    gather_candidates,
    without_grad,
)

__all__ = ["Iteration", "SamplingPlanner"]

WARM_START_STD = 0.25
"""Spread of the first batch's candidates around a warm start ``init``, as a fraction of the
action range (CEM's and iCEM's; MPPI uses its ``noise_std``)."""

Noise = Callable[[torch.Size, int, "torch.Generator | None"], torch.Tensor]
"""``noise(batch, k, generator)`` → unit-variance noise ``[*B, k, H, M]``."""


def check_num_elites(num_elites: int, num_candidates: int) -> None:
    """Refuse ``num_elites`` that is not an int in ``[1, num_candidates]``.

    Examples:
        >>> check_num_elites(2.5, 8)
        Traceback (most recent call last):
        ...
        TypeError: num_elites must be an int in [1, num_candidates=8], got 2.5.
    """
    if isinstance(num_elites, bool) or not isinstance(num_elites, int):
        raise TypeError(
            f"num_elites must be an int in [1, num_candidates={num_candidates}], got {num_elites!r}."
        )
    if not 1 <= num_elites <= num_candidates:
        raise ValueError(
            f"num_elites must be in [1, num_candidates={num_candidates}], got {num_elites}."
        )


def check_smoothing(smoothing: float) -> None:
    """Refuse a smoothing (momentum) outside ``[0, 1)``."""
    if not 0.0 <= smoothing < 1.0:
        raise ValueError(f"smoothing must be in [0, 1), got {smoothing}.")


def check_positive(name: str, value: float) -> None:
    """Refuse anything but a positive finite number.

    Examples:
        >>> check_positive("temperature", 0.0)
        Traceback (most recent call last):
        ...
        ValueError: temperature must be a positive finite number, got 0.0.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}.")


def refit_gaussian(
    elites: torch.Tensor,
    mean: torch.Tensor | None,
    std: torch.Tensor | None,
    smoothing: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The elites' mean and std ``[*B, 1, H, M]``, mixed with the previous ones by ``smoothing``.

    ``mean ← smoothing·mean + (1 − smoothing)·elite_mean`` (likewise std); without a previous
    Gaussian (``mean=None``), the elites' own.
    """
    new_mean, new_std = elites.mean(-3, keepdim=True), elites.std(-3, keepdim=True, correction=0)
    if mean is None:
        return new_mean, new_std
    return (
        smoothing * mean + (1 - smoothing) * new_mean,
        smoothing * std + (1 - smoothing) * new_std,
    )


class BestSeen:
    """The candidates the final choice is made among (one or more per iteration), with their
    predictions; concatenated once at the end."""

    def __init__(self) -> None:
        self.candidates: list[torch.Tensor] = []
        self.predictions: list[Prediction] = []

    def add(self, candidates: torch.Tensor, prediction: Prediction, index: torch.Tensor) -> None:
        """Keep candidates ``index`` ``[*B, k]`` of ``candidates`` ``[*B, K, H, M]``."""
        self.candidates.append(gather_candidates(candidates, index))
        self.predictions.append(prediction.take(index))

    def result(self) -> tuple[torch.Tensor, Prediction]:
        """All kept candidates ``[*B, k_total, H, M]`` and their prediction."""
        return torch.cat(self.candidates, -3), Prediction.concat(self.predictions)


@dataclass
class Iteration:
    """Where the sampling loop is, as a planner's :meth:`SamplingPlanner.sample` sees it.

    Attributes:
        index: 0 … ``iterations − 1``.
        last: True in the last iteration.
        first_batch: in the first iteration only, the first batch ``[*B, K, H, M]`` the loop
            drew (uniform within the bounds; with a warm start, a share around it); else None.
        noise: in later iterations only, unit-variance noise ``[*B, K_i, H, M]`` the loop drew
            with the planner's :meth:`~SamplingPlanner.noise` (K_i: its
            :meth:`~SamplingPlanner.population_sizes`); else None.
        batch: the batch dims ``*B``.
        init: the warm start ``[*B, H, M]``, or None.
        generator: the plan's ``generator`` (draw any more random numbers from it), or None.
        carry: what the planner's ``_recall`` found for this plan, or None.

    Examples:
        >>> step = Iteration(0, False, torch.zeros(4, 3, 1), None, torch.Size(), None, None, None)
        >>> step.first_batch.shape, step.noise
        (torch.Size([4, 3, 1]), None)
    """

    index: int
    last: bool
    first_batch: torch.Tensor | None
    noise: torch.Tensor | None
    batch: torch.Size
    init: torch.Tensor | None
    generator: torch.Generator | None
    carry: Any


class SamplingPlanner(PlannerBase):
    """Base of the planners that sample candidate batches for several iterations.

    They all run one loop (``_optimise``). Each iteration it samples the candidates
    (:meth:`sample`), scores them in one call to the planning model, draws the next
    iteration's noise (:meth:`noise`), resolves a relative band once from the uniform part of
    the first batch, updates the planner's search state (:meth:`update`) and keeps the sample
    :meth:`update` names as the iteration's best; after the last, :meth:`finish` may add
    candidates, and the final choice is made among them. They share the budget arguments and
    checks, the first batch (uniform within the bounds; with a warm start ``init``,
    ``warm_start_uniform`` of it uniform and the rest around ``init``) and the feasible-first
    ranking.

    A new sampling planner writes :meth:`sample` and :meth:`update`; :meth:`start` (the search
    state before the first update), :meth:`noise`, :meth:`population_sizes`,
    ``warm_start_std``, :meth:`finish` and :meth:`keep` have defaults. The search state is
    whatever :meth:`start` and :meth:`update` return (a tensor, a dataclass of tensors). The
    loop is one graph when compiled: ``sample`` and ``update`` must not branch on tensor values
    or read them on the host.

    Examples:
        A random search around the best candidate of the last iteration:

        >>> class AroundBest(SamplingPlanner):
        ...     def sample(self, best, step):
        ...         if step.first_batch is not None:
        ...             return step.first_batch
        ...         return self._clamp(best + 0.1 * self._span * step.noise)
        ...
        ...     def update(self, best, candidates, prediction, bounds):
        ...         index = self._rank(prediction, bounds).argmax(-1, keepdim=True)  # [*B, 1]
        ...         return gather_candidates(candidates, index), index
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> world_model = LSTMWorldModel(12, 4)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> planner = AroundBest(PlanningModel(world_model, drone_cost), Objective(), horizon=20,
        ...                      num_candidates=64, iterations=3, block_rows=None,
        ...                      on_infeasible="fallback")
        >>> planner.plan(torch.zeros(10, 12), torch.zeros(10, 4), torch.zeros(12)).actions.shape
        torch.Size([20, 4])
    """

    compiles_whole_call = True  # tests/planners/test_plan_graph.py

    warm_start_uniform: float = 0.5
    """The share of the first batch drawn uniformly when the plan has a warm start (the rest
    around it)."""

    def __init__(
        self,
        model: PlanningModel,
        objective: Objective,
        *,
        horizon: int,
        num_candidates: int,
        iterations: int,
        block_rows: int | str | None,
        on_infeasible: OnInfeasible,
    ) -> None:
        super().__init__(model, objective, horizon=horizon, on_infeasible=on_infeasible)
        check_int("num_candidates", num_candidates)
        check_block_rows(block_rows)  # resolved for the candidates' device at each call
        check_int("iterations", iterations)
        self.num_candidates, self.iterations, self.block_rows = (
            num_candidates,
            iterations,
            block_rows,
        )

    @property
    def warm_start_std(self) -> float:
        """Spread of the first batch's candidates around a warm start ``init``, as a fraction
        of the action range (``WARM_START_STD``, 0.25)."""
        return WARM_START_STD

    def noise(
        self, batch: torch.Size, k: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Unit-variance noise ``[*B, k, H, M]``, drawn for every iteration after the first
        (``step.noise`` in :meth:`sample`) and for the first batch's candidates around a warm
        start; white Gaussian by default."""
        return self._normal(batch, k, generator)

    def population_sizes(self) -> list[int]:
        """K_i, the number of noise draws of every iteration (``num_candidates`` each by
        default)."""
        return [self.num_candidates] * self.iterations

    def start(self, batch: torch.Size, init: torch.Tensor | None) -> Any:
        """The search state before the first :meth:`update` (None by default)."""
        return None

    def sample(self, search: Any, step: Iteration) -> torch.Tensor:
        """The candidates ``[*B, K', H, M]`` of iteration ``step``, from the search state
        ``search``: in the first iteration at least ``step.first_batch`` (it leads, for the
        reference bounds), in later ones from ``step.noise``.

        Examples:
            CEM's: ``step.first_batch`` first, then ``clamp(mean + std · noise)``.
        """
        raise NotImplementedError

    def update(
        self,
        search: Any,
        candidates: torch.Tensor,
        prediction: Prediction,
        bounds: tuple[torch.Tensor, torch.Tensor] | None,
    ) -> tuple[Any, torch.Tensor]:
        """The search state after scoring ``candidates`` (their :class:`Prediction`; the band's
        ``bounds`` or None), and the index ``[*B, 1]`` of the candidate the final choice is
        made among (the iteration's best).

        Examples:
            MPPI's: the mean Σ w·a with w = softmax(J / λ), and the best-ranked candidate.
        """
        raise NotImplementedError

    def finish(
        self,
        search: Any,
        candidates: torch.Tensor,
        prediction: Prediction,
        evaluate: Callable[[torch.Tensor], Prediction],
    ) -> tuple[torch.Tensor, Prediction]:
        """The candidates the final choice is made among and their prediction, from every
        iteration's best (``candidates``, ``prediction``) and the last search state; by default
        those. ``evaluate(actions)`` scores more, e.g. MPPI's final mean."""
        return candidates, prediction

    def keep(self, search: Any) -> torch.Tensor | None:
        """What the planner keeps for its next call (``_remember`` gets it), from the last
        search state: iCEM's last elites; None by default."""
        return None

    @without_grad
    def _optimise(
        self, context_obs, context_action, observation, init, state, generator, carry=None
    ):
        """The sampling loop every sampling planner runs (see the class docstring): the
        candidates the final choice is made among, their prediction, the band's bounds and
        what the planner keeps."""
        batch = observation.shape[:-1]
        sizes = self.population_sizes()

        def evaluate(candidates: torch.Tensor) -> Prediction:
            return self._evaluate(context_obs, context_action, observation, candidates, state)

        search = self.start(batch, init)
        seen, bounds, next_noise = BestSeen(), None, None
        for i in range(self.iterations):
            first = noise = None
            if i == 0:
                first, uniform = self._first_candidates(
                    batch, init, self.warm_start_std, self.noise, generator, self.warm_start_uniform
                )
            else:
                noise = next_noise()
            step = Iteration(
                i, i == self.iterations - 1, first, noise, batch, init, generator, carry
            )
            candidates = self.sample(search, step)
            prediction = evaluate(candidates)
            if i + 1 < self.iterations:  # drawn after each pass (see _noise_later)
                next_noise = self._noise_later(self.noise, batch, sizes[i + 1], generator)
            if i == 0:
                bounds = self._reference_bounds(prediction, uniform, batch)
            search, best = self.update(search, candidates, prediction, bounds)
            seen.add(candidates, prediction, best)
        candidates, prediction = self.finish(search, *seen.result(), evaluate)
        return candidates, prediction, bounds, self.keep(search)

    @property
    def _span(self) -> torch.Tensor:
        """The action range ``high − low``, ``[M]``."""
        return self.model.action_high - self.model.action_low

    def _first_candidates(
        self,
        batch: torch.Size,
        init: torch.Tensor | None,
        around_std: float,
        noise: Noise,
        generator: torch.Generator | None,
        uniform_fraction: float = 0.5,
    ) -> tuple[torch.Tensor, int]:
        """The first iteration's ``num_candidates`` candidates and how many lead them uniformly.

        Without ``init``: all uniform within the bounds. With ``init`` ``[*B, H, M]``: a
        ``uniform_fraction`` uniform (the reference of relative bands; half by default), the
        rest ``init + around_std·range·noise``, clipped to the bounds.
        """
        if init is None:
            return self._uniform(batch, self.num_candidates, generator), self.num_candidates
        half = int(self.num_candidates * (1 - uniform_fraction))  # K // 2 at 0.5
        uniform = self._uniform(batch, self.num_candidates - half, generator)
        spread = around_std * self._span * noise(batch, half, generator)
        around = self._clamp(init.unsqueeze(-3) + spread)
        return torch.cat([uniform, around], -3), self.num_candidates - half

    def _noise_later(
        self, noise: Noise, batch: torch.Size, k: int, generator: torch.Generator | None
    ) -> Callable[[], torch.Tensor]:
        """The next iteration's ``noise(batch, k, generator)``, as a call that returns it.

        Call it right after an iteration's pass. When the planning model runs its row blocks on
        threads (``threads`` > 1 on the CPU), :meth:`PlanningModel.later` starts the draw now on a
        block thread while the caller ranks and refits: both are serial work between passes (a draw of K = 1000, H = 30,
        M = 3 normals takes ~0.3 ms), and what stays serial bounds the gain from more cores.
        Otherwise it is drawn when called. Nothing else draws in between, so the draws come in
        the same order either way: the same plans.
        """
        return self.model.later(lambda: noise(batch, k, generator))

    def _evaluate(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        candidates: torch.Tensor,
        state,
    ) -> Prediction:
        """The planning model's prediction of ``candidates``, in row blocks of ``block_rows``."""
        return self.model(
            context_obs,
            context_action,
            observation,
            candidates,
            state=state,
            block_rows=self.block_rows,
        )

    def _reference_bounds(
        self, prediction: Prediction, uniform: int, batch: torch.Size
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The band's bounds from the first ``uniform`` candidates of the first batch (or None)."""
        if self.objective.band is None:
            return None
        reference = torch.arange(uniform, device=prediction.cost.device)
        return self._bounds(prediction.take(reference.expand(*batch, -1)))

    def _rank(self, prediction: Prediction, bounds) -> torch.Tensor:
        """The feasible-first key of every candidate, ``[*B, K]`` (see :func:`rank_key`)."""
        return rank_key(
            self.objective.score(prediction), self.objective.violation(prediction, bounds)
        )
