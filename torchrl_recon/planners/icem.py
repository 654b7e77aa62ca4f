"""Improved cross-entropy method (iCEM) over action sequences, on the shared planning model."""

from __future__ import annotations

import math

import torch

from torchrl_recon.modules.checks import in_graph
from torchrl_recon.planners.base import OnInfeasible, PlanResult
from torchrl_recon.planners.cem import CEMPlanner, Gaussian
from torchrl_recon.planners.elite_memory import EliteMemory
from torchrl_recon.planners.noise import colored_noise
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import PlanningModel
from torchrl_recon.planners.sampling import WARM_START_STD, Iteration


class ICEMPlanner(CEMPlanner):
    """iCEM: CEM with colored noise, elites kept across iterations and time steps, and a
    shrinking population; returns the best sample seen.

    Pinneri et al. 2020, "Sample-efficient Cross-Entropy Method for Real-time Planning" (CoRL),
    as mbrl-lib's ``ICEMOptimizer``. A :class:`CEMPlanner` with CEM's arguments and these
    additions; candidates are scored by the same batched
    :class:`Objective` as :class:`CEMPlanner`'s (u term, uncertainty bands, cost threshold),
    ranked feasible-first, and every batch element ``*B`` is planned in the same calls.

    Iteration i scores ``[*B, K_i + extra, H, M]`` candidates (K × H × A per batch element) in
    one call to the planning model:

    * K_i = max(⌈K / population_decay^i⌉, 2·num_elites), at most K: the population shrinks;
    * the first iteration draws CEM's first batch (uniform; with a warm start ``init``, half
      uniform, which also resolves relative bands, and half ``init`` + 0.25·range·colored
      noise). With ``init``, ⌈keep_elites·num_elites⌉ more candidates are the elites this
      planner kept from the plan that ``init`` continues, shifted as ``init`` is (see
      :class:`EliteMemory`; e.g. :class:`~torchrl_recon.policies.MPCPolicy`'s warm start),
      or, for rows it does not continue, more draws around ``init``;
    * later ones draw ``mean + std·colored noise`` (power spectrum ∝ 1/f^``noise_beta`` along
      the horizon, :func:`colored_noise`), clipped to the bounds, plus the best
      ⌈keep_elites·num_elites⌉ elites of the previous iteration; the last adds the mean;
    * ``mean ← smoothing·mean + (1 − smoothing)·elite_mean`` (likewise std, floored at
      ``min_std``·range), from mean = ``init`` clipped (or the middle of the bounds) and std =
      0.25·range.

    The budget is Σ_i K_i plus the kept elites and the mean, at most K × iterations +
    ⌈keep_elites·num_elites⌉ × iterations + 1 rows per batch element.

    Args:
        model: the :class:`PlanningModel`.
        objective: the :class:`Objective`.

    Keyword Args:
        horizon: H (steps planned ahead).
        num_candidates: K, the first iteration's population.
        iterations: number of iterations.
        num_elites: elites per iteration (at most ``num_candidates``).
        population_decay: γ >= 1 of K_i = K / γ^i (1: no decay).
        keep_elites: fraction in [0, 1] of the elites kept into the next iteration and the next
            plan (0: none).
        noise_beta: exponent β >= 0 of the colored noise (0: white noise as CEM's).
        smoothing: momentum α in [0, 1) of the mean/std update.
        min_std: floor on the standard deviation, as a fraction of the action range.
        block_rows: evaluate candidate rows in blocks of about this many (see
            :class:`CEMPlanner`). "auto" (default): 1024 on the CPU, one pass on a GPU; None: one pass.
        on_infeasible: ``"fallback"`` or ``"raise"`` (see :class:`PlannerBase`).

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> world_model = LSTMWorldModel(12, 4)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> planner = ICEMPlanner(PlanningModel(world_model, drone_cost), Objective(),
        ...                       horizon=20, num_candidates=64, num_elites=8, iterations=3)
        >>> planner.population_sizes()
        [64, 52, 41]
        >>> planner.plan(torch.zeros(10, 12), torch.zeros(10, 4), torch.zeros(12)).actions.shape
        torch.Size([20, 4])
    """

    def __init__(
        self,
        model: PlanningModel,
        objective: Objective,
        *,
        horizon: int,
        num_candidates: int = 1000,
        iterations: int = 5,
        num_elites: int = 100,
        population_decay: float = 1.25,
        keep_elites: float = 0.3,
        noise_beta: float = 2.0,
        smoothing: float = 0.1,
        min_std: float = 0.02,
        block_rows: int | str | None = "auto",
        on_infeasible: OnInfeasible = "fallback",
    ) -> None:
        super().__init__(
            model,
            objective,
            horizon=horizon,
            num_candidates=num_candidates,
            iterations=iterations,
            num_elites=num_elites,
            smoothing=smoothing,
            min_std=min_std,
            block_rows=block_rows,
            on_infeasible=on_infeasible,
        )
        if not 1.0 <= population_decay < math.inf:
            raise ValueError(
                f"population_decay must be a finite number >= 1 (1 = no decay), got {population_decay}."
            )
        if not 0.0 <= keep_elites <= 1.0:
            raise ValueError(f"keep_elites must be in [0, 1], got {keep_elites}.")
        if not 0.0 <= noise_beta < math.inf:
            raise ValueError(f"noise_beta must be a finite number >= 0, got {noise_beta}.")
        self.population_decay, self.keep_elites, self.noise_beta = (
            population_decay,
            keep_elites,
            noise_beta,
        )
        self.num_kept = math.ceil(keep_elites * num_elites)
        self.memory = EliteMemory()

    def population_sizes(self) -> list[int]:
        """K_i of every iteration, before the kept elites and the mean are added."""
        floor = min(2 * self.num_elites, self.num_candidates)
        return [
            max(math.ceil(self.num_candidates / self.population_decay**i), floor)
            for i in range(self.iterations)
        ]

    def noise(
        self, batch: torch.Size, k: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Unit-variance colored noise ``[*B, k, H, M]``, correlated along H."""
        shape = (*batch, k, self.model.action_dim, 2, self.horizon // 2 + 1)
        white = self._draw_shape(torch.randn, shape, generator)
        return colored_noise(white, self.horizon, self.noise_beta).transpose(-1, -2)

    def _carried(
        self,
        init: torch.Tensor,
        batch: torch.Size,
        generator: torch.Generator | None,
        carry: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """The kept elites of the plan each row's ``init`` continues (``carry``, from
        :meth:`_recall`; recalled here when not given, outside a compiled graph), else draws
        around ``init``."""
        spread = WARM_START_STD * self._span * self.noise(batch, self.num_kept, generator)
        drawn = self._clamp(init.unsqueeze(-3) + spread)
        if carry is None and not in_graph():
            carry = self._recall(init)
        if carry is None:
            return drawn
        elites, found = carry
        return torch.where(found[..., None, None, None], elites, drawn)

    def _recall(self, init: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The elites :class:`EliteMemory` finds for each row's warm start ``init`` ``[*B, H, M]``
        (``[*B, E, H, M]``, zeros where none is found) and where it found them (``[*B]``), read
        before the plan's graph (the search needs the host); None without ``init`` or kept
        elites. Tensors of the same shapes whatever is found: one graph serves every call."""
        if init is None or not self.num_kept:
            return None
        batch, tail = init.shape[:-2], init.shape[-2:]
        recalled = self.memory.recall(init.reshape(-1, *tail))
        if recalled is None or recalled[0].shape[1] != self.num_kept:
            elites = init.new_zeros(*batch, self.num_kept, *tail)
            return elites, torch.zeros(batch, dtype=torch.bool, device=init.device)
        elites, found = recalled
        return elites.view(*batch, self.num_kept, *tail), found.view(batch)

    def _remember(self, result: PlanResult, kept: torch.Tensor | None) -> None:
        """Remember the last iteration's kept elites ``kept`` ``[*B, E, H, M]`` under the
        returned plan, for the next call whose ``init`` continues it."""
        if kept is None:
            return
        rows = result.actions.reshape(-1, *result.actions.shape[-2:])
        self.memory.remember(rows, kept.reshape(len(rows), -1, *rows.shape[-2:]))

    def start(self, batch: torch.Size, init: torch.Tensor | None) -> Gaussian:
        """mean = ``init`` clipped (or the middle of the bounds), std = 0.25·range."""
        low, high = self.model.action_low, self.model.action_high
        shape = (*batch, 1, self.horizon, self.model.action_dim)
        mean = ((low + high) / 2).expand(shape) if init is None else self._clamp(init.unsqueeze(-3))
        return Gaussian(mean, (WARM_START_STD * self._span).expand(shape))

    def sample(self, search: Gaussian, step: Iteration) -> torch.Tensor:
        """CEM's candidates (colored noise), then the kept elites: in the first iteration those
        of the plan ``init`` continues (``_carried``), later the previous iteration's; in
        the last, the mean too."""
        candidates = super().sample(search, step)
        if step.index == 0:
            extra = (
                []
                if step.init is None or not self.num_kept
                else [self._carried(step.init, step.batch, step.generator, step.carry)]
            )
        else:
            extra = [self.keep(search)] if self.num_kept else []
            if step.last:
                extra.append(self._clamp(search.mean))
        return torch.cat([candidates, *extra], -3)

    def keep(self, search: Gaussian) -> torch.Tensor | None:
        """The best ⌈keep_elites·num_elites⌉ elites of the last iteration, remembered for the
        next plan (``_remember``; copied out of a compiled graph's memory), or None."""
        return search.elites[..., : self.num_kept, :, :] if self.num_kept else None
