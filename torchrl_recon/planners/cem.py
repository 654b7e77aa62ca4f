"""Cross-entropy method over action sequences, on the shared planning model."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchrl_recon.planners.base import OnInfeasible
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import (
    PlanningModel,
    Prediction,
    gather_candidates,
)
from torchrl_recon.planners.sampling import (
    Iteration,
    SamplingPlanner,
    check_num_elites,
    check_smoothing,
    refit_gaussian,
)

__all__ = ["CEMPlanner", "Gaussian"]


@dataclass
class Gaussian:
    """CEM's (and iCEM's) search state: the sampling Gaussian and the last elites.

    Attributes:
        mean: ``[*B, 1, H, M]``, or None before the first refit (CEM's first batch).
        std: ``[*B, 1, H, M]``, or None with ``mean``.
        elites: the last iteration's elites ``[*B, num_elites, H, M]``, best first, or None.
    """

    mean: torch.Tensor | None = None
    std: torch.Tensor | None = None
    elites: torch.Tensor | None = None


class CEMPlanner(SamplingPlanner):
    """CEM: sample, keep the elites, refit a diagonal Gaussian, repeat; return the best sample seen
    (or, with ``return_mean_elites``, the final Gaussian's mean).

    The first iteration samples uniformly within the bounds (with a warm start ``init``, half
    of it uniformly and half around ``init``; relative uncertainty bands are resolved from the
    uniform part); later ones sample N(mean, std) clipped to the bounds, with
    ``mean ← smoothing·mean + (1 − smoothing)·elite_mean`` (likewise std, floored at
    ``min_std``). Elites are ranked feasible-first (see ``rank_key``). The whole
    candidate batch is one call to the planning model per iteration.

    Keyword Args:
        horizon: H (steps planned ahead).
        num_candidates: K per iteration.
        iterations: number of CEM iterations.
        num_elites: top-k kept per iteration.
        smoothing: weight of the previous mean/std in the update (0 = plain CEM).
        min_std: floor on the standard deviation, as a fraction of the action range.
        warm_start_uniform: the fraction of the first iteration's candidates drawn uniformly
            within the bounds when the plan has a warm start ``init`` (the rest around it);
            0 samples them all around the warm start, as mbrl-lib's CEM (PETS) samples around
            the shifted previous plan. Not 0 with an uncertainty band (resolved from the
            uniform ones).
        return_mean_elites: return the mean of the Gaussian after the last iteration (the last
            elites' mean, smoothed as above) instead of the best single sample seen, as
            mbrl-lib's CEM with ``return_mean_elites=True`` (PETS's setting): an average of
            many good plans, less exposed to one candidate that exploits a model error. It
            costs one more model call of one candidate. With constraints (an uncertainty band
            or a cost threshold) the mean is returned when it meets them, else the best of the
            samples seen (the mean included), as without this option.
        block_rows: evaluate the ``B·K`` candidate rows in blocks of about this many (see
            :meth:`PlanningModel.forward`): many envs' candidates in one call then run at the
            speed of cache-sized batches instead of spilling the rollout state to memory. The
            result is the unblocked one up to float rounding. "auto" (default): 1024 on the CPU, one pass on a GPU; None: one pass.
        on_infeasible: ``"fallback"`` or ``"raise"``.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> world_model = LSTMWorldModel(12, 4)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> planner = CEMPlanner(PlanningModel(world_model, drone_cost), Objective(),
        ...                      horizon=20, num_candidates=64, num_elites=8, iterations=3)
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
        smoothing: float = 0.1,
        min_std: float = 0.02,
        block_rows: int | str | None = "auto",
        on_infeasible: OnInfeasible = "fallback",
        return_mean_elites: bool = False,
        warm_start_uniform: float = 0.5,
    ) -> None:
        super().__init__(
            model,
            objective,
            horizon=horizon,
            num_candidates=num_candidates,
            iterations=iterations,
            block_rows=block_rows,
            on_infeasible=on_infeasible,
        )
        check_num_elites(num_elites, num_candidates)
        check_smoothing(smoothing)
        if not 0.0 <= min_std < math.inf:
            raise ValueError(f"min_std must be a finite number >= 0, got {min_std}.")
        self.num_elites, self.smoothing, self.min_std = num_elites, smoothing, min_std
        if not isinstance(return_mean_elites, bool):
            raise TypeError(f"return_mean_elites must be a bool, got {return_mean_elites!r}.")
        self.return_mean_elites = return_mean_elites
        if not 0.0 <= warm_start_uniform <= 1.0:
            raise ValueError(f"warm_start_uniform must be in [0, 1], got {warm_start_uniform}.")
        if warm_start_uniform == 0.0 and objective.band is not None:
            raise ValueError(
                "warm_start_uniform=0 leaves no uniform candidates to resolve the uncertainty "
                "band from; give it a fraction above 0."
            )
        self.warm_start_uniform = warm_start_uniform

    def start(self, batch: torch.Size, init: torch.Tensor | None) -> Gaussian:
        """No Gaussian yet: the first iteration samples the first batch."""
        return Gaussian()

    def sample(self, search: Gaussian, step: Iteration) -> torch.Tensor:
        """The first batch, then N(mean, std) clipped to the bounds.

        Examples:
            >>> from torchrl_recon.modules import LSTMWorldModel
            >>> model = PlanningModel(LSTMWorldModel(1, 1), lambda s, a, s2: s2[..., 0])
            >>> planner = CEMPlanner(model, Objective(), horizon=2, num_candidates=4, num_elites=2)
            >>> noise = torch.tensor([[[0.1], [-1.0]]])  # one candidate [K, H, M] = [1, 2, 1]
            >>> step = Iteration(1, True, None, noise, torch.Size(), None, None, None)
            >>> gaussian = Gaussian(torch.zeros(1, 2, 1), torch.full((1, 2, 1), 2.0))
            >>> planner.sample(gaussian, step)[0, :, 0]  # mean + std·noise, clipped to [-1, 1]
            tensor([ 0.2000, -1.0000])
        """
        if step.first_batch is not None:
            return step.first_batch
        return self._clamp(search.mean + search.std * step.noise)

    def update(
        self, search: Gaussian, candidates: torch.Tensor, prediction: Prediction, bounds
    ) -> tuple[Gaussian, torch.Tensor]:
        """Rank the candidates and refit the Gaussian to the top ``num_elites`` (std floored
        at ``min_std``·range): the new :class:`Gaussian` ``[*B, 1, H, M]`` with the elites,
        best first, and the best candidate ``[*B, 1]``, kept for the final choice."""
        elite_idx = self._rank(prediction, bounds).topk(self.num_elites, dim=-1).indices
        elites = gather_candidates(candidates, elite_idx)
        mean, std = refit_gaussian(elites, search.mean, search.std, self.smoothing)
        std = torch.maximum(std, self.min_std * self._span)
        return Gaussian(mean, std, elites), elite_idx[..., :1]

    def finish(
        self,
        search: Gaussian,
        candidates: torch.Tensor,
        prediction: Prediction,
        evaluate: Callable[[torch.Tensor], Prediction],
    ) -> tuple[torch.Tensor, Prediction]:
        """With ``return_mean_elites``, the final mean scored and put first (``_pick``
        returns it unless it breaks a constraint); else the best samples as they are."""
        if not self.return_mean_elites:
            return candidates, prediction
        at_mean = evaluate(search.mean)
        return torch.cat([search.mean, candidates], -3), Prediction.concat([at_mean, prediction])

    def _pick(self, objective: torch.Tensor, violation: torch.Tensor) -> torch.Tensor:
        best = super()._pick(objective, violation)
        if not self.return_mean_elites:
            return best
        return torch.where(violation[..., :1] <= 0, torch.zeros_like(best), best)
