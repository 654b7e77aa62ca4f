"""Batched MPC planners on one rollout engine, with uncertainty in the objective."""

from __future__ import annotations

from torchrl_recon.planners.base import (
    InfeasiblePlanError,
    InfeasiblePlanWarning,
    PlanFlags,
    PlannerBase,
    PlanOutput,
    PlanResult,
)
from torchrl_recon.planners.beta import cost_to_u_ratio, relative_beta, window_uncertainty
from torchrl_recon.planners.bounds import bounds_from_spec, check_bounds_match
from torchrl_recon.planners.cem import CEMPlanner, Gaussian
from torchrl_recon.planners.cpu_threads import run_aside, run_blocks
from torchrl_recon.planners.elite_memory import EliteMemory
from torchrl_recon.planners.gradient import GradientPlanner
from torchrl_recon.planners.icem import ICEMPlanner
from torchrl_recon.planners.model_env import WorldModelPlanningEnv
from torchrl_recon.planners.mppi import MPPIPlanner
from torchrl_recon.planners.noise import colored_noise
from torchrl_recon.planners.objective import Objective, UncertaintyBand
from torchrl_recon.planners.planning_model import (
    COMPILE_MODES,
    PlanningModel,
    Prediction,
    TerminationFn,
    check_step_fn,
    compile_mode,
    threaded_pass,
)
from torchrl_recon.planners.registry import (
    PLANNERS,
    check_planner_kwargs,
    get_planner_class,
    make_planner,
)
from torchrl_recon.planners.sampling import Iteration, SamplingPlanner
from torchrl_recon.planners.shooting import RandomShootingPlanner
from torchrl_recon.planners.torchrl_models import (
    CONTEXT_ACTION,
    CONTEXT_OBS,
    BatchedWorldModelEnv,
    LSTMWorldModelModule,
    TorchRLWorldModelAdapter,
)

__all__ = [
    "BatchedWorldModelEnv",
    "COMPILE_MODES",
    "CONTEXT_ACTION",
    "CONTEXT_OBS",
    "compile_mode",
    "CEMPlanner",
    "EliteMemory",
    "Gaussian",
    "GradientPlanner",
    "ICEMPlanner",
    "Iteration",
    "PLANNERS",
    "InfeasiblePlanError",
    "InfeasiblePlanWarning",
    "LSTMWorldModelModule",
    "MPPIPlanner",
    "Objective",
    "PlanFlags",
    "PlanOutput",
    "PlanResult",
    "PlannerBase",
    "PlanningModel",
    "Prediction",
    "RandomShootingPlanner",
    "SamplingPlanner",
    "TerminationFn",
    "TorchRLWorldModelAdapter",
    "UncertaintyBand",
    "WorldModelPlanningEnv",
    "bounds_from_spec",
    "check_bounds_match",
    "check_planner_kwargs",
    "check_step_fn",
    "colored_noise",
    "cost_to_u_ratio",
    "get_planner_class",
    "make_planner",
    "relative_beta",
    "run_aside",
    "run_blocks",
    "threaded_pass",
    "window_uncertainty",
]
