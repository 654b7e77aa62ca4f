"""What the iterative sampling planners (CEM, MPPI, iCEM) share: the first batch, scoring, the
Gaussian refit and the best sample of every iteration."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from torchrl_recon.modules.checks import check_int
from torchrl_recon.planners.base import OnInfeasible, PlannerBase
from torchrl_recon.planners.cpu_threads import run_aside
from torchrl_recon.planners.objective import Objective, rank_key
from torchrl_recon.planners.planning_model import (
    PlanningModel,
    Prediction,
    check_block_rows,
    gather_candidates,
)

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


class SamplingPlanner(PlannerBase):
    """Base of the planners that sample candidate batches for several iterations.

    They share the budget arguments and checks, the first batch (uniform within the bounds; with
    a warm start ``init``, half uniform and half around ``init``), the relative band resolved
    once from the uniform part, the feasible-first ranking and the best sample of each
    iteration, among which (and whatever else a planner adds) the final choice is made.
    """

    compiles_whole_call = True  # tests/planners/test_plan_graph.py

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
        threads (``threads`` > 1 on the CPU), the draw starts now on a block thread while the
        caller ranks and refits: both are serial work between passes (a draw of K = 1000, H = 30,
        M = 3 normals takes ~0.3 ms), and what stays serial bounds the gain from more cores.
        Otherwise it is drawn when called. Nothing else draws in between, so the draws come in
        the same order either way: the same plans.
        """
        if not self.model.blocks_in_threads or torch.compiler.is_compiling():
            return lambda: noise(batch, k, generator)
        return run_aside(lambda: noise(batch, k, generator), self.model.threads).result

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
