"""Gradient ascent on the action sequence through the world model and the estimator (BPTT)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from torchrl_recon.modules.checks import check_int
from torchrl_recon.planners.base import OnInfeasible, PlannerBase
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import PlanningModel, Prediction


@contextmanager
def frozen(module: nn.Module) -> Iterator[None]:
    """Turn ``requires_grad`` off on ``module``'s parameters for the block, then restore it.

    Planning differentiates with respect to the actions only; with frozen weights autograd
    records nothing for them and the world model's rollout skips their gradients.

    Examples:
        >>> layer = nn.Linear(2, 2)
        >>> with frozen(layer):
        ...     layer.weight.requires_grad
        False
        >>> layer.weight.requires_grad
        True
    """
    params = [p for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


def _copied(prediction: Prediction) -> Prediction:
    """A copy of ``prediction`` without autograd history, in memory of its own."""
    kept = prediction.detach()
    u = None if kept.uncertainty is None else kept.uncertainty.clone()
    return Prediction(kept.states.clone(), kept.cost.clone(), u)


class GradientPlanner(PlannerBase):
    """Maximise J by Adam on ``restarts`` action sequences at once, projected onto the bounds.

    Paper §2.3: the objective is the sum of two differentiable networks' outputs, so it can be
    optimised by backpropagation through time with respect to the actions. Every step scores
    all restarts in one batched pass; every sample seen (all restarts, all steps) is kept and
    the best feasible one returned, which is the paper's "stop the ascent" at an uncertainty cap.

    Keyword Args:
        horizon: H (steps planned ahead).
        restarts: sequences optimised in parallel (uniform initialisation; the first one starts
            from ``init`` when a warm start is given).
        steps: Adam steps.
        lr: Adam learning rate, in action units.
        on_infeasible: ``"fallback"`` or ``"raise"``.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> world_model = LSTMWorldModel(12, 4)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> planner = GradientPlanner(PlanningModel(world_model, drone_cost), Objective(),
        ...                           horizon=20, restarts=4, steps=5)
        >>> planner.plan(torch.zeros(10, 12), torch.zeros(10, 4), torch.zeros(12)).actions.shape
        torch.Size([20, 4])
    """

    def __init__(
        self,
        model: PlanningModel,
        objective: Objective,
        *,
        horizon: int,
        restarts: int = 16,
        steps: int = 50,
        lr: float = 0.05,
        on_infeasible: OnInfeasible = "fallback",
    ) -> None:
        super().__init__(model, objective, horizon=horizon, on_infeasible=on_infeasible)
        check_int("restarts", restarts)
        check_int("steps", steps)
        if not lr > 0:
            raise ValueError(f"lr must be positive, got {lr!r}.")
        if objective.alpha == 0 and objective.beta == 0:
            raise ValueError(
                "GradientPlanner needs an objective that depends on the actions: alpha or beta "
                "must be non-zero (a constant objective has no gradient); to pick any plan inside "
                "the constraints, use RandomShootingPlanner."
            )
        self.restarts, self.steps, self.lr = restarts, steps, lr

    def _optimise(self, context_obs, context_action, observation, init, state, generator):
        batch = observation.shape[:-1]
        with torch.no_grad():
            start = self._uniform(batch, self.restarts, generator)
            if init is not None:
                start[..., 0, :, :] = init
        actions = start.requires_grad_(True)
        optimizer = torch.optim.Adam([actions], lr=self.lr)
        # Every step's samples, concatenated once at the end (not step by step: that copy grows
        # with the steps and the rows).
        seen_actions, seen_predictions = [], []
        with torch.enable_grad(), frozen(self.model):
            for step in range(self.steps + 1):
                prediction = self.model(
                    context_obs, context_action, observation, actions, state=state
                )
                # copies: a compiled pass's outputs live in its graph's memory, which its next
                # call (a CUDA graph's replay) overwrites before the samples are concatenated
                seen_actions.append(actions.detach().clone())
                seen_predictions.append(_copied(prediction))
                if step == self.steps:
                    break
                (grad,) = torch.autograd.grad(-self.objective.score(prediction).sum(), actions)
                actions.grad = grad
                optimizer.step()
                with torch.no_grad():
                    actions.copy_(self._clamp(actions))
        # Relative bands are resolved on the uniform initial restarts (restart 0 is `init` when given).
        first = 1 if init is not None and self.restarts > 1 else 0
        seen = Prediction.concat(seen_predictions)
        uniform = torch.arange(first, self.restarts, device=start.device)
        bounds = self._bounds(seen.take(uniform.expand(*batch, -1)))
        return torch.cat(seen_actions, -3), seen, bounds
