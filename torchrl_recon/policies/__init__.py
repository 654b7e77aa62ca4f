"""TensorDict policies on the planners: MPC control and uncertainty-seeking exploration."""

from __future__ import annotations

from torchrl_recon.policies.env_checks import PlannerStatePrimer
from torchrl_recon.policies.exploration import ExplorationPolicy, exploration_objective
from torchrl_recon.policies.mpc import MPCPolicy

__all__ = ["ExplorationPolicy", "MPCPolicy", "PlannerStatePrimer", "exploration_objective"]
