"""Model Predictive Path Integral control over action sequences, on the shared planning model."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchrl_recon.planners.base import OnInfeasible
from torchrl_recon.planners.objective import Objective
from torchrl_recon.planners.planning_model import PlanningModel, Prediction
from torchrl_recon.planners.sampling import Iteration, SamplingPlanner, check_positive


class MPPIPlanner(SamplingPlanner):
    """MPPI: perturb the mean plan with Gaussian noise, average the samples weighted by
    softmax(J / temperature), repeat; return the best of the final mean and the samples seen.

    Williams et al. 2017, "Information Theoretic MPC for Model-Based Reinforcement Learning"
    (ICRA): the path-integral update makes the new mean plan the expectation of the sampled
    sequences under weights ∝ exp(J / λ), with λ the ``temperature``. As TorchRL's
    ``MPPIPlanner`` and mbrl-lib's ``MPPIOptimizer``, several updates (``iterations``) may run
    per plan; unlike them, the noise is fixed (no refit of its std) and the candidates are
    scored by the same batched :class:`Objective` as :class:`CEMPlanner`'s, so the u term,
    uncertainty bands and cost thresholds apply.

    Per iteration, K candidates ``[*B, K, H, M]`` (K × H × A per batch element) are scored in
    one call to the planning model:

    * the first iteration draws CEM's first batch: uniform within the bounds, or with a warm
      start ``init`` ``[*B, H, M]`` (e.g. the previous plan shifted by one step, which
      :class:`~torchrl_recon.policies.MPCPolicy` passes) half uniformly (the reference of
      relative bands) and half ``init + noise_std·range·ε``, ε ~ N(0, I);
    * later ones draw ``mean + noise_std·range·ε``; all are clipped to the action bounds;
    * weights are softmax(J / temperature) over the feasible candidates of each batch
      element; where none is feasible, softmax(−violation / temperature), so the mean moves
      towards the constraints first. The new mean is Σ_k w_k·a_k (inside the bounds).

    After the last iteration the final mean is scored too (one more row per batch element);
    the plan returned is the best, feasible-first, of that mean and each iteration's best
    sample (TorchRL and mbrl-lib return the mean unconditionally).

    The temperature is in units of J (cost summed over the horizon, plus β·u): with
    λ far below the spread of the candidates' J, MPPI keeps the best sample; far above it,
    it averages them all. Scale it with the task's cost.

    Args:
        model: the :class:`PlanningModel`.
        objective: the :class:`Objective`.

    Keyword Args:
        horizon: H (steps planned ahead).
        num_candidates: K per iteration.
        iterations: number of updates of the mean.
        temperature: λ > 0 of the weights softmax(J / λ).
        noise_std: std of the perturbations, as a fraction of the action range (> 0).
        block_rows: evaluate the ``B·K`` candidate rows in blocks of about this many (see
            :class:`CEMPlanner`). "auto" (default): 1024 on the CPU, one pass on a GPU; None: one pass.
        on_infeasible: ``"fallback"`` or ``"raise"`` (see :class:`PlannerBase`).

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> world_model = LSTMWorldModel(12, 4)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> planner = MPPIPlanner(PlanningModel(world_model, drone_cost), Objective(),
        ...                       horizon=20, num_candidates=64, iterations=3, temperature=0.5)
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
        temperature: float = 1.0,
        noise_std: float = 0.25,
        block_rows: int | str | None = "auto",
        on_infeasible: OnInfeasible = "fallback",
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
        check_positive("temperature", temperature)
        check_positive("noise_std", noise_std)
        self.temperature, self.noise_std = temperature, noise_std

    def _weights(self, prediction: Prediction, bounds) -> torch.Tensor:
        """softmax(J / λ) over the feasible candidates, ``[*B, K]`` (−violation where none is).
        A candidate whose J is NaN weighs nothing (one NaN would make every weight NaN)."""
        violation = self.objective.violation(prediction, bounds)
        violation = violation.masked_fill(violation.isnan(), torch.inf)
        score = self.objective.score(prediction)
        feasible = (violation <= 0) & ~score.isnan()
        score = score.masked_fill(~feasible, -torch.inf)
        key = torch.where(feasible.any(-1, keepdim=True), score, -violation)
        return torch.softmax(key / self.temperature, dim=-1)

    @property
    def warm_start_std(self) -> float:
        """The first batch's spread around a warm start, as a fraction of the action range
        (``noise_std``)."""
        return self.noise_std

    def sample(self, mean: torch.Tensor | None, step: Iteration) -> torch.Tensor:
        """The first batch, then ``mean + noise_std·range·ε`` clipped to the bounds.

        Examples:
            >>> from torchrl_recon.modules import LSTMWorldModel
            >>> model = PlanningModel(LSTMWorldModel(1, 1), lambda s, a, s2: s2[..., 0])
            >>> planner = MPPIPlanner(model, Objective(), horizon=2, num_candidates=4)
            >>> noise = torch.tensor([[[1.0], [-8.0]]])  # one candidate [K, H, M] = [1, 2, 1]
            >>> step = Iteration(1, True, None, noise, torch.Size(), None, None, None)
            >>> planner.sample(torch.zeros(1, 2, 1), step)[0, :, 0]  # range 2, noise_std 0.25
            tensor([ 0.5000, -1.0000])
        """
        if step.first_batch is not None:
            return step.first_batch
        return self._clamp(mean + self.noise_std * self._span * step.noise)

    def update(
        self, mean: torch.Tensor | None, candidates: torch.Tensor, prediction: Prediction, bounds
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The new mean Σ_k w_k·a_k ``[*B, 1, H, M]`` (``_weights``) and the best-ranked
        candidate ``[*B, 1]``, kept for the final choice."""
        weights = self._weights(prediction, bounds)
        mean = (weights[..., None, None] * candidates).sum(-3, keepdim=True)
        return mean, self._rank(prediction, bounds).argmax(-1, True)

    def finish(
        self,
        mean: torch.Tensor,
        candidates: torch.Tensor,
        prediction: Prediction,
        evaluate: Callable[[torch.Tensor], Prediction],
    ) -> tuple[torch.Tensor, Prediction]:
        """The best samples and, last, the final mean, scored."""
        return torch.cat([candidates, mean], -3), Prediction.concat([prediction, evaluate(mean)])
