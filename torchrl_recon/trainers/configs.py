"""The library's parts in TorchRL's config store (``torchrl.trainers.algorithms.configs``).

``import torchrl_recon.trainers.configs`` stores, beside TorchRL's own, one ``_target_``
dataclass per part in TorchRL's groups: ``env`` (``torchrl_recon``:
:func:`~torchrl_recon.envs.make_env`), ``model`` (the world model, every estimator),
``objective``, ``planner`` (every shipped planner), ``policy`` (MPC, exploration), ``loss``,
``fit_schedule``, ``hook`` (the Trainer hooks), ``collector`` (``online``), ``trainer``
(``online``: :func:`make_online_trainer`) and
``transform`` (``uncertainty_penalty``: :class:`~torchrl_recon.transforms.UncertaintyPenalty`);
``model`` also holds the adapters to TorchRL's world models
(``torchrl_world_model_adapter``, ``lstm_world_model_module``). A YAML
then composes them with Hydra's defaults list and ``hydra.utils.instantiate(cfg.trainer)``
builds the agent, as TorchRL's ``sota-implementations/*_trainer`` do
(``examples/config_trainer/``; docs/torchrl_trainer.md).

The configs of parts that another part completes (a world model needs the env's sizes, a
planner its model and objective, a policy its planner) are partial (``_partial_: true``):
:func:`make_online_trainer` calls them with what they lack, so every part is built once and
shared. Each config's fields are its target's keyword arguments with their defaults (made
from the signature, so they never drift from it); the TensorDict keys keep the targets'
defaults.

Examples:
    >>> from hydra.utils import instantiate
    >>> from torchrl_recon.trainers.configs import CEMPlannerConfig, LSTMWorldModelConfig
    >>> world = instantiate(LSTMWorldModelConfig(window=4))(3, 1)  # partial: sizes from the env
    >>> type(world).__name__, world.window
    ('LSTMWorldModel', 4)
    >>> CEMPlannerConfig(horizon=15).num_candidates
    1000
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable
from typing import Any

import torchrl.trainers.algorithms.configs  # noqa: F401  (TorchRL's groups, stored first)
from hydra.core.config_store import ConfigStore
from omegaconf import MISSING
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger
from torchrl.trainers import TrainerHookBase

from torchrl_recon.envs import make_env
from torchrl_recon.envs.registry import import_cost
from torchrl_recon.fitting.online import FitSchedule
from torchrl_recon.modules import ESTIMATORS, LSTMWorldModel
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss
from torchrl_recon.planners import Objective, PlanningModel
from torchrl_recon.planners.registry import PLANNERS
from torchrl_recon.planners.torchrl_models import LSTMWorldModelModule, TorchRLWorldModelAdapter
from torchrl_recon.policies import ExplorationPolicy, MPCPolicy, exploration_objective
from torchrl_recon.trainers import (
    FitNormalization,
    LogIteration,
    ModelFitStepper,
    OnlineCollector,
    OnlineTrainer,
)
from torchrl_recon.transforms import UncertaintyPenalty

PLAIN = (bool, int, float, str, type(None))


def target_config(
    target: Callable, name: str, *, partial: bool = False, given: tuple[str, ...] = ()
) -> type:
    """A Hydra structured-config dataclass ``name`` for ``target``: ``_target_`` its import path,
    one field per parameter not in ``given`` (MISSING where it has no default), ``_partial_``
    ``partial``. Parameters whose default is not a plain value (TensorDict keys, objects) and
    ``*args``/``**kwargs`` are left to the target's own defaults.

    Examples:
        >>> from torchrl_recon.planners import Objective
        >>> config = target_config(Objective, "ObjectiveConfig")
        >>> config().alpha, config._target_
        (1.0, 'torchrl_recon.planners.objective.Objective')
    """
    fields: list[tuple[str, Any, Any]] = []
    for param in inspect.signature(target).parameters.values():
        if param.name in given or param.kind in (param.VAR_POSITIONAL, param.VAR_KEYWORD):
            continue
        default = param.default
        if default is param.empty:
            fields.append((param.name, Any, dataclasses.field(default=MISSING)))
        elif isinstance(default, PLAIN) and not param.name.endswith(("_key", "_keys")):
            fields.append((param.name, Any, dataclasses.field(default=default)))
    path = f"{target.__module__}.{target.__qualname__}"
    fields.append(("_target_", str, dataclasses.field(default=path)))
    fields.append(("_partial_", bool, dataclasses.field(default=partial)))
    doc = f"Hydra config of :func:`~{path}` (``_target_``); its fields are the target's keywords."
    namespace = {"__doc__": doc, "__module__": __name__}
    return dataclasses.make_dataclass(name, fields, namespace=namespace)


def make_planning_model(
    world_model: LSTMWorldModel,
    env: EnvBase,
    cost: str,
    *,
    uncertainty: Any = None,
    termination: str | None = None,
    compile: bool | str = False,
    threads: int = 1,
) -> PlanningModel:
    """:meth:`PlanningModel.from_env` with the cost (and termination) named ``module:function``.

    Examples:
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> model = make_planning_model(LSTMWorldModel(3, 1), env, "torchrl_recon.envs.gym_costs:pendulum")
        >>> model.action_high.tolist()
        [2.0]
    """
    termination_fn = None if termination is None else import_cost(termination, what="termination")
    return PlanningModel.from_env(
        world_model,
        import_cost(cost),
        env,
        uncertainty=uncertainty,
        termination_fn=termination_fn,
        compile=compile,
        threads=threads,
    )


def make_online_trainer(
    *,
    env: EnvBase,
    world_model: Callable[[int, int], LSTMWorldModel],
    cost: str,
    planner: Callable[[PlanningModel, Objective], Any],
    objective: Objective,
    policy: Callable[[Any], MPCPolicy],
    schedule: FitSchedule,
    iterations: int,
    steps_per_iteration: int,
    random_steps: int,
    estimator: Callable[[int, int], Any] | None = None,
    termination: str | None = None,
    planning_compile: bool | str = False,
    planning_threads: int = 1,
    explore_iterations: int = 0,
    exploration: Objective | None = None,
    seed: int = 0,
    progress: bool = True,
    logger: Logger | None = None,
    hooks: list[TrainerHookBase] | None = None,
) -> OnlineTrainer:
    """The online agent's :class:`~torchrl_recon.trainers.OnlineTrainer` from partial configs
    (the config store's ``trainer: online``): the world model and the estimator get the env's
    observation and action sizes, one planning model holds them, and
    :meth:`OnlineTrainer.from_env <torchrl_recon.trainers.OnlineTrainer.from_env>` (the one
    builder) gets the planner on it with ``objective`` (and, for the first
    ``explore_iterations``, with ``exploration``, an
    :func:`~torchrl_recon.policies.exploration_objective`) and ``policy`` to wrap it.
    ``hooks``: more Trainer hooks (TorchRL's or the library's), each registered at its default
    stage.

    Examples:
        >>> import functools
        >>> from torchrl_recon.planners import CEMPlanner
        >>> trainer = make_online_trainer(
        ...     env=make_env("Pendulum-v1", seed=0, max_episode_steps=20),
        ...     world_model=functools.partial(LSTMWorldModel, window=4),
        ...     cost="torchrl_recon.envs.gym_costs:pendulum",
        ...     planner=functools.partial(CEMPlanner, horizon=4, num_candidates=16, num_elites=4),
        ...     objective=Objective(), policy=MPCPolicy,
        ...     schedule=FitSchedule(steps=4, refit_steps=2, eval_every=2, slice_len=8,
        ...                          num_slices=4, val_fraction=0.34),
        ...     iterations=1, steps_per_iteration=20, random_steps=60, progress=False)
        >>> trainer.train()
        >>> [r.policy for r in trainer.records]
        ['random', 'mpc']
    """
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.full_action_spec[env.action_key].shape[-1]
    world = world_model(obs_dim, action_dim)
    uncertainty = None if estimator is None else estimator(obs_dim, action_dim)
    model = make_planning_model(
        world,
        env,
        cost,
        uncertainty=uncertainty,
        termination=termination,
        compile=planning_compile,
        threads=planning_threads,
    )
    return OnlineTrainer.from_env(
        env,
        world,
        uncertainty,
        lambda: planner(model, objective),
        iterations=iterations,
        steps_per_iteration=steps_per_iteration,
        random_steps=random_steps,
        schedule=schedule,
        make_policy=policy,
        explore_iterations=explore_iterations,
        make_explorer=lambda: planner(model, exploration or exploration_objective()),
        seed=seed,
        progress=progress,
        logger=logger,
        hooks=hooks,
    )


def _planner_name(kind: str) -> str:
    return (
        "RandomShootingPlannerConfig" if kind == "shooting" else f"{PLANNERS[kind].__name__}Config"
    )


MakeEnvConfig = target_config(make_env, "MakeEnvConfig")
LSTMWorldModelConfig = target_config(
    LSTMWorldModel, "LSTMWorldModelConfig", partial=True, given=("obs_dim", "action_dim")
)
ESTIMATOR_CONFIGS = {
    kind: target_config(cls, f"{cls.__name__}Config", partial=True, given=("obs_dim", "action_dim"))
    for kind, cls in ESTIMATORS.items()
}
"""The config of each estimator of :data:`~torchrl_recon.estimators.ESTIMATORS`, by its name."""
ObjectiveConfig = target_config(Objective, "ObjectiveConfig")
ExplorationObjectiveConfig = target_config(exploration_objective, "ExplorationObjectiveConfig")
PLANNER_CONFIGS = {
    kind: target_config(cls, _planner_name(kind), partial=True, given=("model", "objective"))
    for kind, cls in PLANNERS.items()
}
"""The config of each planner of :data:`~torchrl_recon.planners.registry.PLANNERS`, by its name."""
ReconstructionUncertaintyConfig = ESTIMATOR_CONFIGS["reconstruction"]
EnsembleUncertaintyConfig = ESTIMATOR_CONFIGS["ensemble"]
MCDropoutUncertaintyConfig = ESTIMATOR_CONFIGS["mc_dropout"]
RNDUncertaintyConfig = ESTIMATOR_CONFIGS["rnd"]
WorldModelEnsembleUncertaintyConfig = ESTIMATOR_CONFIGS["world_model_ensemble"]
CEMPlannerConfig = PLANNER_CONFIGS["cem"]
ICEMPlannerConfig = PLANNER_CONFIGS["icem"]
MPPIPlannerConfig = PLANNER_CONFIGS["mppi"]
GradientPlannerConfig = PLANNER_CONFIGS["gradient"]
RandomShootingPlannerConfig = PLANNER_CONFIGS["shooting"]
MPCPolicyConfig = target_config(MPCPolicy, "MPCPolicyConfig", partial=True, given=("planner",))
ExplorationPolicyConfig = target_config(
    ExplorationPolicy, "ExplorationPolicyConfig", partial=True, given=("planner",)
)
WorldModelPredictionLossConfig = target_config(
    WorldModelPredictionLoss, "WorldModelPredictionLossConfig"
)
UncertaintyLossConfig = target_config(UncertaintyLoss, "UncertaintyLossConfig")
FitScheduleConfig = target_config(FitSchedule, "FitScheduleConfig")
ModelFitStepperConfig = target_config(ModelFitStepper, "ModelFitStepperConfig")
FitNormalizationConfig = target_config(FitNormalization, "FitNormalizationConfig")
LogIterationConfig = target_config(LogIteration, "LogIterationConfig")
OnlineCollectorConfig = target_config(OnlineCollector, "OnlineCollectorConfig")
OnlineTrainerConfig = target_config(make_online_trainer, "OnlineTrainerConfig")
UncertaintyPenaltyConfig = target_config(
    UncertaintyPenalty, "UncertaintyPenaltyConfig", partial=True, given=("estimator",)
)
TorchRLWorldModelAdapterConfig = target_config(
    TorchRLWorldModelAdapter, "TorchRLWorldModelAdapterConfig", partial=True, given=("world_model",)
)
LSTMWorldModelModuleConfig = target_config(
    LSTMWorldModelModule,
    "LSTMWorldModelModuleConfig",
    partial=True,
    given=("world_model", "cost_fn"),
)

CONFIGS: dict[tuple[str, str], type] = {
    ("env", "torchrl_recon"): MakeEnvConfig,
    ("model", "lstm_world_model"): LSTMWorldModelConfig,
    **{("model", f"{kind}_uncertainty"): c for kind, c in ESTIMATOR_CONFIGS.items()},
    ("objective", "objective"): ObjectiveConfig,
    ("objective", "exploration"): ExplorationObjectiveConfig,
    **{("planner", kind): c for kind, c in PLANNER_CONFIGS.items()},
    ("policy", "mpc"): MPCPolicyConfig,
    ("policy", "exploration"): ExplorationPolicyConfig,
    ("loss", "world_model_prediction"): WorldModelPredictionLossConfig,
    ("loss", "uncertainty"): UncertaintyLossConfig,
    ("fit_schedule", "default"): FitScheduleConfig,
    ("hook", "model_fit_stepper"): ModelFitStepperConfig,
    ("hook", "fit_normalization"): FitNormalizationConfig,
    ("hook", "log_iteration"): LogIterationConfig,
    ("collector", "online"): OnlineCollectorConfig,
    ("trainer", "online"): OnlineTrainerConfig,
    ("transform", "uncertainty_penalty"): UncertaintyPenaltyConfig,
    ("model", "torchrl_world_model_adapter"): TorchRLWorldModelAdapterConfig,
    ("model", "lstm_world_model_module"): LSTMWorldModelModuleConfig,
}
"""Every config this module stores, by (group, name) in TorchRL's config store."""


def register_configs() -> None:
    """Store :data:`CONFIGS` in Hydra's ``ConfigStore`` (done on import; again is harmless)."""
    store = ConfigStore.instance()
    for (group, name), node in CONFIGS.items():
        store.store(group=group, name=name, node=node)


register_configs()

__all__ = [
    "CEMPlannerConfig",
    "CONFIGS",
    "EnsembleUncertaintyConfig",
    "GradientPlannerConfig",
    "ICEMPlannerConfig",
    "MCDropoutUncertaintyConfig",
    "MPPIPlannerConfig",
    "RNDUncertaintyConfig",
    "RandomShootingPlannerConfig",
    "ReconstructionUncertaintyConfig",
    "WorldModelEnsembleUncertaintyConfig",
    "ESTIMATOR_CONFIGS",
    "PLANNER_CONFIGS",
    "ExplorationObjectiveConfig",
    "ExplorationPolicyConfig",
    "FitNormalizationConfig",
    "FitScheduleConfig",
    "LSTMWorldModelConfig",
    "LSTMWorldModelModuleConfig",
    "LogIterationConfig",
    "MPCPolicyConfig",
    "MakeEnvConfig",
    "ModelFitStepperConfig",
    "ObjectiveConfig",
    "TorchRLWorldModelAdapterConfig",
    "UncertaintyPenaltyConfig",
    "OnlineCollectorConfig",
    "OnlineTrainerConfig",
    "UncertaintyLossConfig",
    "WorldModelPredictionLossConfig",
    "make_online_trainer",
    "make_planning_model",
    "register_configs",
    "target_config",
]
