"""Typed schemas of the recipes. A YAML recipe is merged onto these, so an unknown key or a
wrong type is an error before any work starts. The values' ranges (every number finite, counts
>= 1, ``guided.ratio`` > 1, ``training.val_fraction`` in (0, 1), env keywords of the chosen
env, ...) are checked next, by :mod:`torchrl_recon.experiments.recipe_checks`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING


@dataclass
class EnvConfig:
    """Which environment, its cost, its constructor keywords and the episode length.

    ``id``: a gymnasium id (``Pendulum-v1``, or ``my_module:MyEnv-v0``, which imports
    ``my_module`` first, where ``gymnasium.register`` registers ``MyEnv-v0``); null: ``name``
    is the env. ``name``: without ``id``, a registered env (``industrial_benchmark``, ``drone``,
    ``minitaur``, one given to ``torchrl_recon.envs.register_env``) or a gymnasium id; with
    ``id``, only the env's name in run directories, tables and loggers. ``cost``:
    ``module:function``, a batched torch ``cost(obs, action, next_obs) -> [...]`` (imported:
    the module's code runs); null: the registered env's own (a gymnasium env has none).
    ``state_names``: the observation's dims, for plots (empty: the registered env's, else
    ``s0, s1, ...``). ``kwargs``: keywords of the env's constructor."""

    name: str | None = None
    id: str | None = None
    cost: str | None = None
    state_names: list[str] = field(default_factory=list)
    kwargs: dict[str, Any] = field(default_factory=dict)
    episode_steps: int = 100


@dataclass
class WorldModelConfig:
    hidden_size: int = 32
    dense_size: int = 32
    activation: str = "relu"


@dataclass
class UncertaintyConfig:
    """Which estimator (``kind``: a key of ``torchrl_recon.modules.ESTIMATORS``), its hidden
    width and activation, and the keywords only that kind takes (e.g. ``num_members``)."""

    kind: str = "reconstruction"
    hidden_size: int = 100
    activation: str = "relu"
    kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass
class ModelsConfig:
    window: int = 10
    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)


@dataclass
class FitConfig:
    steps: int = 3000
    lr: float = 3e-3
    eval_every: int = 100
    patience: int = 10


@dataclass
class TrainingConfig:
    """How the networks are fitted: sequence windows of ``slice_len`` steps, ``num_slices`` a batch.

    ``window_sampling``: ``trajectory`` (TorchRL's ``SliceSampler``: a trajectory uniformly, then
    a window in it) or ``step`` (every window start alike; see ``StepUniformSliceSampler``).
    """

    slice_len: int = 40
    num_slices: int = 32
    window_sampling: str = "trajectory"
    val_fraction: float = 0.1
    world_model_mode: str = "multi_step"
    world_model: FitConfig = field(default_factory=FitConfig)
    uncertainty: FitConfig = field(default_factory=lambda: FitConfig(eval_every=250))


@dataclass
class PlannerConfig:
    """``kind``: ``shooting``, ``cem`` or ``gradient``; unused fields are ignored by the other kinds."""

    kind: str = "shooting"
    horizon: int = 50
    num_candidates: int = 1000
    iterations: int = 5
    num_elites: int = 100
    restarts: int = 16
    gradient_steps: int = 50
    lr: float = 0.05


@dataclass
class BandConfig:
    """Cumulative-u band; ``kind``: ``absolute``, ``quantile`` or ``mean_ratio`` (None = open side)."""

    low: float | None = None
    high: float | None = None
    kind: str = "quantile"


@dataclass
class LoggerConfig:
    """``backend``: ``wandb`` (offline unless ``mode: online``), ``csv`` or ``none``."""

    backend: str = "wandb"
    project: str = "torchrl_recon"
    mode: str = "offline"


@dataclass
class ValidationConfig:
    """The held-out set of Table 1: ``trajectories`` × (``window`` + ``steps``) real steps.

    ``policy``: ``random`` (uniform actions, like the random arm) or ``offset_noise``
    (per-trajectory random offset + noise, covering more of the action space).
    """

    trajectories: int = 100
    steps: int = 100
    policy: str = "random"


@dataclass
class GuidedConfig:
    """Uncertainty-guided exploration (paper §2.4): keep candidates with Σu ≥ ``ratio`` × mean and,
    when ``cap`` is set, Σu ≤ ``cap`` × mean; ``beta = -1`` maximises Σu among them (eq. 4),
    ``beta = 0`` takes any of them (the paper's "sample until"). ``ratio`` > 1, ``cap`` null or
    > ``ratio``, ``beta`` <= 0."""

    steps: int = 15000
    ratio: float = 1.2
    cap: float | None = None
    beta: float = 0.0
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    refit_every_episodes: int = 50


@dataclass
class RunConfig:
    """What every experiment run has: which env, seed, threads and device, where it writes, the
    models, how they are trained, and the logger.

    ``device``: ``auto`` (CUDA when available, else CPU), ``cpu``, ``cuda`` or ``cuda:N``; the
    networks, planning and fitting run there, the envs stay on the CPU.

    ``num_envs``: envs stepped side by side as one batch (a TorchRL ``SerialEnv``) when
    collecting data and playing control episodes; the policy then plans for all of them in
    one call. 1 keeps one env at a time."""

    experiment: str = MISSING
    env: EnvConfig = field(default_factory=EnvConfig)
    num_envs: int = 1
    seed: int = 0
    threads: int = 1
    device: str = "auto"
    output_dir: str = MISSING
    stop_after: str | None = None
    progress: bool = True
    models: ModelsConfig = field(default_factory=ModelsConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)


@dataclass
class ExploreConfig(RunConfig):
    """Active vs random exploration (paper §3.2, Table 1): one repeat per seed."""

    experiment: str = "explore"
    output_dir: str = "outputs/explore"
    initial_random_steps: int = 10000
    validation: ValidationConfig = field(default_factory=ValidationConfig)
    guided: GuidedConfig = field(default_factory=GuidedConfig)
    random_steps: int = 15000
    retrainings: int = 10
    retrainings_per_fit: int | None = None


@dataclass
class ControlSetting:
    """One arm of the control experiment: a planner, its objective and how it re-plans.

    With ``beta_relative``, ``beta`` is in units of the random data's cost-to-u ratio (mean
    |cost| per step over mean u per window), so β·u is that fraction of a typical step's cost
    whatever the scales of the env's cost and of the fitted estimator.
    """

    name: str = MISSING
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    alpha: float = 1.0
    beta: float = 0.0
    beta_relative: bool = False
    band: BandConfig | None = None
    cost_threshold: float | None = None


@dataclass
class ReplanConfig:
    """``mode``: ``every_step``, ``every_n`` or ``uncertainty``. The uncertainty threshold is the
    ``threshold_quantile`` of per-window u on the training data (per step), times ``threshold_scale``.
    ``error_threshold`` (not in the paper): also re-plan, in any mode, when the real state is
    further than this from the plan's prediction (RMS in the world model's normalised units)."""

    mode: str = "uncertainty"
    every: int = 10
    threshold_quantile: float = 0.95
    threshold_scale: float = 1.0
    threshold_on: str = "step"
    error_threshold: float | None = None


@dataclass
class ControlConfig(RunConfig):
    """Uncertainty-aware control (paper §3.1, Fig. 3)."""

    experiment: str = "control"
    output_dir: str = "outputs/control"
    random_episodes: int = 10
    random_episode_steps: int = 500
    episodes: int = 10
    warmup_random_steps: int = 10
    replan: ReplanConfig = field(default_factory=ReplanConfig)
    settings: list[ControlSetting] = field(default_factory=list)


@dataclass
class EstimatorSpec(UncertaintyConfig):
    """One estimator of the calibration benchmark: a ``models.uncertainty`` block plus a name."""

    name: str = MISSING


@dataclass
class CalibrationEvalConfig:
    """How u is judged. The world model imagines the last ``horizon`` steps of ``trajectories``
    held-out real trajectories (actions drawn by ``policy``) after a real context; u is ranked
    against the real error. Out of distribution: held-out windows with the states moved by
    ``ood_state_shift`` standard deviations, and with the actions held at the upper bound."""

    trajectories: int = 200
    horizon: int = 30
    policy: str = "offset_noise"
    ood_windows: int = 500
    ood_state_shift: float = 3.0


@dataclass
class TimingConfig:
    """Scoring ``candidates`` × H windows and one CEM call per estimator, for each H in ``horizons``."""

    candidates: int = 1000
    horizons: list[int] = field(default_factory=lambda: [30, 200])
    repeats: int = 5
    iterations: int = 5
    num_elites: int = 100


@dataclass
class OutcomesConfig:
    """Reduced-scale exploration and control runs with each estimator (a null recipe skips one).
    Recipe paths are relative to the working directory; the overrides are applied on top."""

    explore_recipe: str | None = None
    explore_overrides: list[str] = field(default_factory=list)
    control_recipe: str | None = None
    control_overrides: list[str] = field(default_factory=list)


@dataclass
class CalibrateConfig(RunConfig):
    """Uncertainty estimators side by side: fitted on the same random data, judged on
    the same imagined trajectories, timed in the same run. ``models.uncertainty`` is unused:
    the estimators are listed in ``estimators``."""

    experiment: str = "calibrate"
    output_dir: str = "outputs/calibrate"
    random_steps: int = 10000
    random_episode_steps: int = 500
    estimators: list[EstimatorSpec] = field(default_factory=list)
    evaluation: CalibrationEvalConfig = field(default_factory=CalibrationEvalConfig)
    timing: TimingConfig = field(default_factory=TimingConfig)
    outcomes: OutcomesConfig = field(default_factory=OutcomesConfig)
