"""What plans in a recipe: its planning model, a planner block's planner, a control setting's
objective, the re-planning threshold and the MPC policy of its ``replan`` block."""

from __future__ import annotations

import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_recon.envs import closing_env
from torchrl_recon.envs.registry import LEARNED, import_cost
from torchrl_recon.experiments.recipe_env import build_env, cost_fn
from torchrl_recon.modules import (
    LearnedCost,
    LearnedTermination,
    LSTMWorldModel,
    RewardModel,
    UncertaintyEstimator,
)
from torchrl_recon.planners import (
    Objective,
    PlannerBase,
    PlanningModel,
    UncertaintyBand,
    make_planner,
)
from torchrl_recon.policies import MPCPolicy


def planning_model(
    cfg: DictConfig,
    world: LSTMWorldModel,
    uncertainty: UncertaintyEstimator | None = None,
    reward_model: RewardModel | None = None,
) -> PlanningModel:
    """The recipe's :class:`PlanningModel`: its cost, ``env.termination`` (either ``learned``:
    ``reward_model``'s) and the action bounds of its env (built and closed without stepping),
    its pass compiled as ``planning_compile`` says, its row blocks on ``planning_threads``
    threads."""
    path = cfg.env.get("termination")
    if path == LEARNED:
        termination = LearnedTermination(reward_model)
    else:
        termination = None if path is None else import_cost(path, what="termination")
    cost = LearnedCost(reward_model) if cfg.env.get("cost") == LEARNED else cost_fn(cfg)
    with closing_env(build_env(cfg, seed=0, episode_steps=1)) as env:
        return PlanningModel.from_env(
            world,
            cost,
            env,
            uncertainty=uncertainty,
            termination_fn=termination,
            compile=cfg.get("planning_compile", False),
            threads=cfg.get("planning_threads", 1),
        )


def build_planner(
    planner_cfg: DictConfig, model: PlanningModel, objective: Objective
) -> PlannerBase:
    """The planner of a recipe's planner block (:func:`~torchrl_recon.planners.make_planner`)."""
    kwargs = OmegaConf.to_container(planner_cfg.kwargs, resolve=True)
    return make_planner(planner_cfg.kind, model, objective, **kwargs)


def setting_objective(setting: DictConfig, beta_unit: float) -> tuple[Objective, float]:
    """The setting's objective and its β (× ``beta_unit`` when relative).

    Examples:
        >>> setting = OmegaConf.create({"alpha": 1.0, "beta": 0.5, "beta_relative": True,
        ...     "band": None, "cost_threshold": None})
        >>> setting_objective(setting, 4.0)[1]
        2.0
    """
    b = setting.band
    band = None if b is None else UncertaintyBand(b.low, b.high, b.kind)
    beta = setting.beta * beta_unit if setting.beta_relative else setting.beta
    objective = Objective(
        alpha=setting.alpha, beta=beta, band=band, cost_threshold=setting.cost_threshold
    )
    return objective, beta


def replan_threshold(cfg: DictConfig, per_window_u: torch.Tensor) -> float:
    """The re-planning threshold on u: a quantile of the windows' u, scaled (× ``every`` when
    it bounds Σu over the steps between plans).

    Examples:
        >>> cfg = OmegaConf.create({"replan": {"threshold_quantile": 1.0, "threshold_scale": 2.0,
        ...     "threshold_on": "cumulative", "every": 3}})
        >>> replan_threshold(cfg, torch.tensor([0.5, 1.0]))
        6.0
    """
    r = cfg.replan
    threshold = float(per_window_u.quantile(r.threshold_quantile)) * r.threshold_scale
    return threshold * r.every if r.threshold_on == "cumulative" else threshold


def mpc_policy(
    cfg: DictConfig, planner: PlannerBase, threshold: float | None, **kwargs
) -> MPCPolicy:
    """The MPC policy of the recipe's ``replan`` block (``threshold`` in mode ``uncertainty``)."""
    r = cfg.replan
    return MPCPolicy(
        planner,
        replan=str(r.mode),
        replan_every=r.every,
        threshold=threshold if r.mode == "uncertainty" else None,
        threshold_on=str(r.threshold_on),
        error_threshold=r.error_threshold,
        **kwargs,
    )
