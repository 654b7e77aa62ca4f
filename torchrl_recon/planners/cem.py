"""Cross-entropy method over action sequences, on the shared planning model."""

from __future__ import annotations

import math

import torch

from torchrl_recon.planners.base import OnInfeasible
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import (
    PlanningModel,
    Prediction,
    gather_candidates,
    without_grad,
)
from torchrl_recon.planners.sampling import (
    WARM_START_STD,
    BestSeen,
    SamplingPlanner,
    check_num_elites,
    check_smoothing,
    refit_gaussian,
)


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

    def _elite_update(
        self,
        candidates: torch.Tensor,
        prediction: Prediction,
        bounds,
        mean: torch.Tensor | None,
        std: torch.Tensor | None,
        seen: BestSeen,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rank the candidates, keep the best in ``seen`` and refit the Gaussian to the top
        ``num_elites`` (std floored at ``min_std``·range): the new mean and std ``[*B, 1, H, M]``
        and the elites ``[*B, num_elites, H, M]``, best first."""
        elite_idx = self._rank(prediction, bounds).topk(self.num_elites, dim=-1).indices
        elites = gather_candidates(candidates, elite_idx)
        mean, std = refit_gaussian(elites, mean, std, self.smoothing)
        std = torch.maximum(std, self.min_std * self._span)
        # Keep each iteration's best sample; the final choice is made among them.
        seen.add(candidates, prediction, elite_idx[..., :1])
        return mean, std, elites

    @without_grad
    def _optimise(self, context_obs, context_action, observation, init, state, generator):
        batch = observation.shape[:-1]
        mean = std = bounds = None
        seen = BestSeen()
        next_noise = None  # drawn after each pass (see _noise_later)
        for it in range(self.iterations):
            if mean is None:
                candidates, uniform = self._first_candidates(
                    batch, init, WARM_START_STD, self._normal, generator, self.warm_start_uniform
                )
            else:
                candidates = self._clamp(mean + std * next_noise())
            prediction = self._evaluate(context_obs, context_action, observation, candidates, state)
            if it + 1 < self.iterations:
                next_noise = self._noise_later(self._normal, batch, self.num_candidates, generator)
            if it == 0:
                bounds = self._reference_bounds(prediction, uniform, batch)
            mean, std, _ = self._elite_update(candidates, prediction, bounds, mean, std, seen)
        candidates, prediction = seen.result()
        # With return_mean_elites the mean leads; _pick returns it unless it breaks a constraint.
        if self.return_mean_elites:
            at_mean = self._evaluate(context_obs, context_action, observation, mean, state)
            candidates = torch.cat([mean, candidates], -3)
            prediction = Prediction.concat([at_mean, prediction])
        return candidates, prediction, bounds

    def _pick(self, objective: torch.Tensor, violation: torch.Tensor) -> torch.Tensor:
        best = super()._pick(objective, violation)
        if not self.return_mean_elites:
            return best
        return torch.where(violation[..., :1] <= 0, torch.zeros_like(best), best)
