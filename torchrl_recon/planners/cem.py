"""Cross-entropy method over action sequences, on the shared planning model."""

from __future__ import annotations

import torch

from torchrl_recon.modules.checks import check_int
from torchrl_recon.planners.base import BLOCK_ROWS, OnInfeasible, PlannerBase
from torchrl_recon.planners.objective import Objective, rank_key
from torchrl_recon.planners.planning_model import PlanningModel, gather_candidates


class CEMPlanner(PlannerBase):
    """CEM: sample, keep the elites, refit a diagonal Gaussian, repeat; return the best sample seen.

    The first iteration samples uniformly within the bounds (with a warm start ``init``, half
    of it uniformly and half around ``init``; relative uncertainty bands are resolved from the
    uniform part); later ones sample N(mean, std) clipped to the bounds, with
    ``mean ← smoothing·mean + (1 − smoothing)·elite_mean`` (likewise std, floored at
    ``min_std``). Elites are ranked feasible-first (see :func:`rank_key`). The whole
    candidate batch is one call to the planning model per iteration.

    Keyword Args:
        horizon: H.
        num_candidates: K per iteration.
        iterations: number of CEM iterations.
        num_elites: top-k kept per iteration.
        smoothing: weight of the previous mean/std in the update (0 = plain CEM).
        min_std: floor on the standard deviation, as a fraction of the action range.
        block_rows: evaluate the ``B·K`` candidate rows in blocks of about this many (see
            :meth:`PlanningModel.forward`): many envs' candidates in one call then run at the
            speed of cache-sized batches instead of spilling the rollout state to memory. The
            result is the unblocked one up to float rounding. None: one pass.
        on_infeasible: ``"fallback"`` or ``"raise"``.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> planner = CEMPlanner(PlanningModel(LSTMWorldModel(12, 4), drone_cost), Objective(),
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
        block_rows: int | None = BLOCK_ROWS,
        on_infeasible: OnInfeasible = "fallback",
    ) -> None:
        super().__init__(model, objective, horizon=horizon, on_infeasible=on_infeasible)
        check_int("num_candidates", num_candidates)
        if block_rows is not None:
            check_int("block_rows", block_rows)
        self.block_rows = block_rows
        check_int("iterations", iterations)
        if not 1 <= num_elites <= num_candidates:
            raise ValueError(
                f"num_elites must be in [1, num_candidates={num_candidates}], got {num_elites}."
            )
        if not 0.0 <= smoothing < 1.0:
            raise ValueError(f"smoothing must be in [0, 1), got {smoothing}.")
        self.num_candidates, self.iterations, self.num_elites = (
            num_candidates,
            iterations,
            num_elites,
        )
        self.smoothing, self.min_std = smoothing, min_std

    @torch.inference_mode()
    def _optimise(self, context_obs, context_action, observation, init, state, generator):
        batch = observation.shape[:-1]
        low, high = self.model.action_low, self.model.action_high
        span = high - low
        mean = std = None
        best_candidates = best_prediction = bounds = None
        for it in range(self.iterations):
            if mean is None and init is None:
                candidates = self._uniform(batch, self.num_candidates, generator)
            elif mean is None:
                # Warm start: half uniform (the reference for relative bands), half around `init`.
                half = self.num_candidates // 2
                uniform = self._uniform(batch, self.num_candidates - half, generator)
                noise = self._normal(batch, half, generator)
                candidates = torch.cat(
                    [uniform, self._clamp(init.unsqueeze(-3) + 0.25 * span * noise)], -3
                )
            else:
                noise = self._normal(batch, self.num_candidates, generator)
                candidates = self._clamp(mean + std * noise)
            prediction = self.model(
                context_obs,
                context_action,
                observation,
                candidates,
                state=state,
                block_rows=self.block_rows,
            )
            if it == 0 and self.objective.band is not None:
                reference = torch.arange(
                    self.num_candidates - (self.num_candidates // 2 if init is not None else 0),
                    device=candidates.device,
                )
                bounds = self._bounds(prediction.take(reference.expand(*batch, -1)))
            key = rank_key(
                self.objective.score(prediction), self.objective.violation(prediction, bounds)
            )
            elite_idx = key.topk(self.num_elites, dim=-1).indices
            elites = gather_candidates(candidates, elite_idx)
            new_mean, new_std = (
                elites.mean(-3, keepdim=True),
                elites.std(-3, keepdim=True, correction=0),
            )
            if mean is None:
                mean, std = new_mean, new_std
            else:
                mean = self.smoothing * mean + (1 - self.smoothing) * new_mean
                std = self.smoothing * std + (1 - self.smoothing) * new_std
            std = torch.maximum(std, self.min_std * span)
            # Keep each iteration's best sample; the final choice is made among them.
            top = elite_idx[..., :1]
            kept_candidates, kept_prediction = (
                gather_candidates(candidates, top),
                prediction.take(top),
            )
            if best_candidates is not None:
                kept_candidates = torch.cat([best_candidates, kept_candidates], -3)
                kept_prediction = best_prediction.cat(kept_prediction)
            best_candidates, best_prediction = kept_candidates, kept_prediction
        return best_candidates, best_prediction, bounds
