"""The planning objective J = Σ_t (α·r_t − β·u_t) with optional bounds on cumulative u and cost."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from torchrl_recon.modules.checks import check_real
from torchrl_recon.planners.planning_model import Prediction

BandKind = Literal["absolute", "quantile", "mean_ratio"]


@dataclass(frozen=True)
class UncertaintyBand:
    """Keep candidates whose cumulative u lies in ``[low, high]`` (either side may be None).

    ``kind`` says what the numbers are:

    * ``"absolute"``: values of Σu (the paper's ranges, e.g. 15–30 on IB);
    * ``"quantile"``: quantiles in [0, 1] of Σu over a batch of uniformly sampled candidates;
    * ``"mean_ratio"``: multiples of the mean Σu over that batch (the paper's exploration
      keeps candidates at 1.2–1.5 × the mean).

    Relative bands are resolved once per planning call, from uniformly sampled candidates (the
    planner's first batch, or its uniform part when the planner was given a warm start), and
    then held fixed.

    Examples:
        >>> band = UncertaintyBand(low=0.25, high=0.75, kind="quantile")
        >>> low, high = band.resolve(torch.arange(5.0)[None])
        >>> low.item(), high.item()
        (1.0, 3.0)
    """

    low: float | None = None
    high: float | None = None
    kind: BandKind = "absolute"

    def __post_init__(self) -> None:
        for name in ("low", "high"):
            if getattr(self, name) is not None:
                check_real(f"band {name}", getattr(self, name), finite=False)
        if self.kind not in ("absolute", "quantile", "mean_ratio"):
            raise ValueError(
                f"band kind must be 'absolute', 'quantile' or 'mean_ratio', got {self.kind!r}."
            )
        if self.low is not None and self.high is not None and self.low > self.high:
            raise ValueError(f"band low={self.low} is above high={self.high}.")
        if self.kind == "quantile" and any(
            v is not None and not 0 <= v <= 1 for v in (self.low, self.high)
        ):
            raise ValueError(
                f"quantile band bounds must lie in [0, 1], got low={self.low}, high={self.high}."
            )

    def resolve(self, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Absolute bounds ``([*B, 1], [*B, 1])`` from reference cumulative u ``[*B, K]``.

        Reference candidates whose u is NaN are left out of a relative band (one would make
        the bounds NaN, and every candidate infeasible).
        """
        batch = reference.shape[:-1]
        # Each row's statistic skips NaN only where that row has one (else the exact ops as
        # before), chosen per row by `where`: no host read, so a compiled plan stays one graph.
        has_nan = reference.isnan().any(-1, keepdim=True)

        def one(value: float | None, default: float) -> torch.Tensor:
            if value is None:
                return reference.new_full((*batch, 1), default)
            if self.kind == "absolute":
                return reference.new_full((*batch, 1), value)
            if self.kind == "quantile":
                plain = torch.quantile(reference, value, dim=-1, keepdim=True)
                skipping = torch.nanquantile(reference, value, dim=-1, keepdim=True)
            else:
                plain = value * torch.mean(reference, -1, keepdim=True)
                skipping = value * torch.nanmean(reference, -1, keepdim=True)
            return torch.where(has_nan, skipping, plain)

        return one(self.low, -torch.inf), one(self.high, torch.inf)


@dataclass(frozen=True)
class Objective:
    """Score candidates: J = Σ_t (α·r_t − β·u_t), r = −cost (paper eq. 3; eq. 4 is α = 0, β = −1).

    Args:
        alpha: weight of reward.
        beta: weight of uncertainty (negative to seek uncertainty, as in exploration).
        band: optional :class:`UncertaintyBand` on cumulative u.
        cost_threshold: optional upper bound on predicted cumulative cost.

    Each is checked when the objective is made: NaN, inf or a non-number is refused.

    Examples:
        >>> from torchrl_recon.planners.planning_model import Prediction
        >>> pred = Prediction(states=torch.zeros(1, 2, 3, 1), cost=torch.ones(1, 2, 3), uncertainty=torch.ones(1, 2, 3))
        >>> Objective(alpha=1.0, beta=0.5).score(pred)
        tensor([[-4.5000, -4.5000]])
    """

    alpha: float = 1.0
    beta: float = 0.0
    band: UncertaintyBand | None = None
    cost_threshold: float | None = None

    def __post_init__(self) -> None:
        check_real("alpha", self.alpha)
        check_real("beta", self.beta)
        if self.cost_threshold is not None:
            check_real("cost_threshold", self.cost_threshold)
        if self.band is not None and not isinstance(self.band, UncertaintyBand):
            raise TypeError(f"band must be an UncertaintyBand or None, got {self.band!r}.")

    @property
    def needs_uncertainty(self) -> bool:
        """Whether u must be computed."""
        return self.beta != 0.0 or self.band is not None

    def score(self, prediction: Prediction) -> torch.Tensor:
        """J for every candidate, ``[*B, K]``."""
        value = -self.alpha * prediction.cumulative_cost if self.alpha else 0.0
        if self.beta:
            value = value - self.beta * prediction.cumulative_uncertainty
        if isinstance(value, float):
            return prediction.cost.new_zeros(prediction.cost.shape[:-1])
        return value

    def violation(
        self, prediction: Prediction, bounds: tuple[torch.Tensor, torch.Tensor] | None
    ) -> torch.Tensor:
        """How far each candidate is outside the constraints (0 when feasible), ``[*B, K]``."""
        out = prediction.cost.new_zeros(prediction.cost.shape[:-1])
        if bounds is not None:
            cum_u = prediction.cumulative_uncertainty
            low, high = bounds
            out = out + (low - cum_u).clamp_min(0) + (cum_u - high).clamp_min(0)
        if self.cost_threshold is not None:
            out = out + (prediction.cumulative_cost - self.cost_threshold).clamp_min(0)
        return out


def rank_key(objective: torch.Tensor, violation: torch.Tensor) -> torch.Tensor:
    """A key whose top-k picks feasible candidates by J first, then the least-violating ones.

    A candidate whose J or violation is NaN (its predicted cost or u was NaN: a diverged
    model, or a cost undefined there) ranks below every other: ``topk`` and ``argmax`` take
    NaN for the largest value, so it would otherwise be picked first.

    Examples:
        >>> rank_key(torch.tensor([1.0, float("nan"), 3.0]), torch.zeros(3)).argsort().tolist()
        [1, 0, 2]
    """
    objective = objective.masked_fill(objective.isnan(), -torch.inf)
    violation = violation.masked_fill(violation.isnan(), torch.inf)
    feasible = violation <= 0
    inner = torch.where(feasible, objective, -violation)
    # the span of the finite keys (an infinite one would make every feasible key infinite)
    finite = inner.isfinite()
    high = inner.masked_fill(~finite, -torch.inf).amax(-1, keepdim=True)
    low = inner.masked_fill(~finite, torch.inf).amin(-1, keepdim=True)
    span = (high - low).nan_to_num(0.0, posinf=0.0, neginf=0.0) + 1.0
    return torch.where(feasible, inner + span, inner)
