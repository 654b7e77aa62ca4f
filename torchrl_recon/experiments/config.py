"""Typed schemas of the recipes. A YAML recipe is merged onto these, so an unknown key, a wrong
type or a choice that is none of its ``Enum``'s is an error before any work starts. Each field
declares its range next to it (``count``, ``positive``, ``checked``; every float finite, see
:mod:`.field_checks`); what spans several sections or needs the env or a registry is checked
by :mod:`.recipe_checks`. :func:`upgrade_legacy_config` reads a run directory's
``config.yaml`` written before planner blocks took their class's own keywords."""

from __future__ import annotations

import inspect
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING, DictConfig, OmegaConf

from torchrl_recon.data import SHORT_EPISODES
from torchrl_recon.data.step_sampler import WINDOW_SAMPLINGS
from torchrl_recon.devices import DEVICE_CHOICES, check_device
from torchrl_recon.experiments.field_checks import (
    above,
    at_least,
    checked,
    choice,
    count,
    finite,
    positive,
)
from torchrl_recon.planners.executors import COMPILE_MODES, compile_mode

NAME_PATTERN = re.compile(r"[A-Za-z0-9_.-]+")
"""Setting and estimator names: they name stage records and folders of the run directory."""


def _file_name(value: str) -> str | None:
    if NAME_PATTERN.fullmatch(value):
        return None
    return "a name of letters, digits, '_', '.' or '-' (it names files of the run directory)"


def _directory(value: str) -> str | None:
    return None if value.strip() else "a directory"


def _device(value: str) -> str | None:
    try:
        check_device(value)
    except ValueError:
        return f"one of {', '.join(DEVICE_CHOICES)} (N = 0, 1, ...)"
    return None


LoggerBackend = choice("LoggerBackend", "wandb csv none", __name__)
LoggerMode = choice("LoggerMode", "offline online", __name__)
WindowSampling = choice("WindowSampling", list(WINDOW_SAMPLINGS), __name__)
ShortEpisodes = choice("ShortEpisodes", list(SHORT_EPISODES), __name__)
WorldModelMode = choice("WorldModelMode", "multi_step one_step", __name__)
BandKind = choice("BandKind", "absolute quantile mean_ratio", __name__)
DataPolicy = choice("DataPolicy", "random offset_noise", __name__)
ReplanMode = choice("ReplanMode", "every_step every_n uncertainty", __name__)
ThresholdOn = choice("ThresholdOn", "step cumulative", __name__)
Warmup = choice("Warmup", "auto random zeros plan", __name__)
RefitUncertainty = choice("RefitUncertainty", "auto always", __name__)


@dataclass
class EnvConfig:
    """Which environment, its cost, its constructor keywords and the episode length.

    ``id``: a gymnasium id (``Pendulum-v1``, or ``my_module:MyEnv-v0``, importing ``my_module``
    first); null: ``name`` is the env. ``name``: without ``id``, a registered env
    (``industrial_benchmark``, ``drone``, ``minitaur``, one given to
    ``torchrl_recon.envs.register_env``) or a gymnasium id; with ``id``, only the env's name in
    run directories, tables and loggers. ``cost`` and ``termination``: ``module:function``, a
    batched torch ``fn(obs, action, next_obs) -> [...]`` (bool for a termination, which stops a
    candidate's cost and u after its predicted end); null: the registered env's own cost (a
    gymnasium env has none), and episodes never end in the model. ``state_names``: the
    observation's dims, for plots. ``kwargs``: keywords of the env's constructor."""

    name: str | None = None
    id: str | None = None
    cost: str | None = None
    termination: str | None = None
    state_names: list[str] = field(default_factory=list)
    kwargs: dict[str, Any] = checked(factory=dict, finite=False)  # the env section checks them
    episode_steps: int = count(100)


@dataclass
class WorldModelConfig:
    hidden_size: int = count(32)
    dense_size: int = count(32)
    activation: str = "relu"


@dataclass
class UncertaintyConfig:
    """An estimator: ``kind``, a key of :data:`torchrl_recon.modules.ESTIMATORS` or
    ``module:Class`` (a user's :class:`~torchrl_recon.modules.UncertaintyEstimator`), built as
    ``Class(obs_dim, action_dim, window=models.window, hidden_size=..., activation=...,
    **kwargs)``."""

    kind: str = "reconstruction"
    hidden_size: int = count(100)
    activation: str = "relu"
    kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass
class RewardModelConfig:
    """A learned reward and termination (:class:`~torchrl_recon.modules.RewardModel`), built when
    ``env.cost`` or ``env.termination`` is ``learned``: ``layers`` hidden layers of
    ``hidden_size`` units; fitted with the world model's settings."""

    hidden_size: int = count(64)
    layers: int = count(2)
    activation: str = "relu"


@dataclass
class ModelsConfig:
    window: int = count(10)
    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)


@dataclass
class FitConfig:
    """One fit's keywords (:func:`~torchrl_recon.fitting.train_loss_module`). ``compile``: its
    training steps under ``torch.compile`` (the same fit up to float rounding; pays on long
    fits, see ``docs/benchmarks.md``)."""

    steps: int = count(3000)
    lr: float = positive(3e-3)
    eval_every: int = count(100)
    patience: int = count(10)
    compile: bool = False


@dataclass
class TrainingConfig:
    """Fitting on windows of ``slice_len`` steps, ``num_slices`` a batch. ``window_sampling``:
    ``trajectory`` (TorchRL's ``SliceSampler``) or ``step`` (every window start alike).
    ``short_episodes``: ``pad`` keeps every episode that ended before ``slice_len`` steps
    (padded, masked); ``pad_if_no_window`` pads them only where a split holds no full window,
    else leaves them out (a run directory made before the key resumes with it)."""

    slice_len: int = count(40)
    num_slices: int = count(32)
    window_sampling: WindowSampling = WindowSampling.trajectory
    short_episodes: ShortEpisodes = ShortEpisodes.pad
    val_fraction: float = checked(0.1, lambda v: None if 0 < v < 1 else "in (0, 1)")
    world_model_mode: WorldModelMode = WorldModelMode.multi_step
    world_model: FitConfig = field(default_factory=FitConfig)
    uncertainty: FitConfig = field(default_factory=lambda: FitConfig(eval_every=250))


@dataclass
class PlannerConfig:
    """A planner: ``kind``, a key of :data:`torchrl_recon.planners.registry.PLANNERS` or
    ``module:Class`` (a user's :class:`~torchrl_recon.planners.PlannerBase`), built as
    ``Class(model, objective, **kwargs)``, e.g. ``{kind: cem, kwargs: {horizon: 30,
    num_elites: 50}}``."""

    kind: str = "shooting"
    kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass
class BandConfig:
    """Cumulative-u band; ``kind``: ``absolute``, ``quantile`` or ``mean_ratio`` (None = open side)."""

    low: float | None = None
    high: float | None = None
    kind: BandKind = BandKind.quantile

    def more_errors(self, key: str) -> Iterator[tuple[str, str]]:
        """The band the objective would build (its limits against its kind)."""
        from torchrl_recon.planners.objective import UncertaintyBand

        if finite(self.low, self.high):
            try:
                UncertaintyBand(low=self.low, high=self.high, kind=self.kind)
            except ValueError as e:
                yield "", f": {e}"


@dataclass
class LoggerConfig:
    """``backend``: ``wandb`` (offline unless ``mode: online``), ``csv`` or ``none``."""

    backend: LoggerBackend = LoggerBackend.wandb
    project: str = "torchrl_recon"
    mode: LoggerMode = LoggerMode.offline


@dataclass
class ValidationConfig:
    """The held-out set of Table 1: ``trajectories`` × (``window`` + ``steps``) real steps, of
    uniform actions (``random``) or per-trajectory offset + noise (``offset_noise``)."""

    trajectories: int = count(100)
    steps: int = count(100)
    policy: DataPolicy = DataPolicy.random


@dataclass
class SeekBand:
    """Σu sought by an exploring plan: candidates with Σu ≥ ``ratio`` × the mean over
    candidates (and ≤ ``cap`` × the mean when set); ``beta = -1`` maximises Σu among them
    (paper eq. 4), ``beta = 0`` takes any of them (the paper's "sample until")."""

    ratio: float = checked(
        1.2, lambda v: None if v > 1 else "above 1 (the threshold is ratio × the mean Σu)"
    )
    cap: float | None = None
    beta: float = checked(0.0, lambda v: None if v <= 0 else "<= 0 (exploration seeks uncertainty)")

    def more_errors(self, key: str) -> Iterator[tuple[str, str]]:
        """``cap`` null or above ``ratio`` (``key``: this section's)."""
        if self.cap is not None and finite(self.cap, self.ratio) and not self.cap > self.ratio:
            yield "cap", f" must be null or above {key}.ratio = {self.ratio}, got {self.cap!r}"


@dataclass
class GuidedConfig(SeekBand):
    """Uncertainty-guided exploration (paper §2.4): ``steps`` steps planned with ``planner`` for
    Σu in the band, the models refitted every ``refit_every_episodes`` episodes."""

    steps: int = count(15000)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    refit_every_episodes: int = count(50)


@dataclass
class OnlineExplorationConfig(SeekBand):
    """The online loop's first ``iterations`` rounds played by an ``ExplorationPolicy`` with the
    recipe's ``planner`` for Σu in the band; 0 rounds: control from the first."""

    iterations: int = count(0, 0)


@dataclass
class RunConfig:
    """What every experiment run has. ``device``: ``auto`` (CUDA when available), ``cpu``,
    ``cuda`` or ``cuda:N``, for the networks (the envs stay on the CPU). ``num_envs``: envs
    stepped side by side as one batch (a TorchRL ``SerialEnv``), planned for in one call."""

    experiment: str = MISSING
    env: EnvConfig = field(default_factory=EnvConfig)
    num_envs: int = count(1)
    seed: int = 0
    threads: int = count(1)
    device: str = checked("auto", _device)
    output_dir: str = checked(MISSING, _directory)
    stop_after: str | None = None
    progress: bool = True
    models: ModelsConfig = field(default_factory=ModelsConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)


def _compile_choice(value: Any) -> str | None:
    try:
        compile_mode(value)
    except ValueError:
        return f"false, true or a torch.compile mode of {list(COMPILE_MODES)}"
    return None


@dataclass
class PlanningRunConfig(RunConfig):
    """What every run that plans has too. ``planning_compile``: the planning model's pass
    (rollout, cost, u) under ``torch.compile`` (``PlanningModel(compile=...)``: ``true`` or a
    mode such as ``reduce-overhead``, CUDA graphs); the same plans up to float rounding after a
    compile of seconds per new batch shape. Off by default: see ``docs/planning.md``.
    ``planning_threads``: on the CPU, the pass's row blocks on this many threads at once
    (``PlanningModel(threads=...)``; above 1 it needs ``planning_compile``)."""

    planning_compile: Any = checked(False, _compile_choice)
    planning_threads: int = count(1)


@dataclass
class ExploreConfig(PlanningRunConfig):
    """Active vs random exploration (paper §3.2, Table 1): one repeat per seed.
    ``fit_cuda_graph``: on a CUDA device, each step of the retrainings' population fits one
    replayed CUDA graph (``fit_population(cuda_graph=True)``)."""

    experiment: str = "explore"
    output_dir: str = checked("outputs/explore", _directory)
    initial_random_steps: int = 10000
    validation: ValidationConfig = field(default_factory=ValidationConfig)
    guided: GuidedConfig = field(default_factory=GuidedConfig)
    random_steps: int = count(15000)
    retrainings: int = count(10)
    retrainings_per_fit: int | None = count(None)
    fit_cuda_graph: bool = False


@dataclass
class ControlSetting:
    """One arm of the control experiment: a planner, its objective and how it re-plans. With
    ``beta_relative``, ``beta`` is in units of the random data's mean |cost| per step over mean
    u per window, whatever the scales of the cost and of the estimator."""

    name: str = checked(MISSING, _file_name)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    alpha: float = checked(1.0, at_least(0, " (the weight of reward)"))
    beta: float = 0.0
    beta_relative: bool = False
    band: BandConfig | None = None
    cost_threshold: float | None = None


@dataclass
class ReplanConfig:
    """``mode``: ``every_step``, ``every_n`` or ``uncertainty`` (above the ``threshold_quantile``
    of per-window u on the training data, times ``threshold_scale``). ``error_threshold``: also
    re-plan when the real state is further than this from the plan's (normalised RMS)."""

    mode: ReplanMode = ReplanMode.uncertainty
    every: int = count(10)
    threshold_quantile: float = checked(0.95, lambda v: None if 0 < v <= 1 else "in (0, 1]")
    threshold_scale: float = positive(1.0)
    threshold_on: ThresholdOn = ThresholdOn.step
    error_threshold: float | None = checked(
        None, lambda v: None if v > 0 else "a positive finite number or null"
    )


@dataclass
class OnlineConfig(PlanningRunConfig):
    """Learning a task online (PETS's loop): ``random_steps`` random steps, then ``iterations``
    rounds of ``steps_per_iteration`` MPC steps, each followed by a warm-started refit
    (``refit_steps``; on the round's new steps plus ``refit_old_steps`` older ones drawn by
    whole trajectories, or on all data when null; the estimator too when the plans read u,
    ``refit_uncertainty: auto``, or always) planning for Σ(α·r − β·u);
    ``world_model_members``: 1 world model, or R members (an ensemble, PETS's: each refitted
    as one batch, a plan's cost their mean); ``fit_cuda_graph``: with R ≥ 2 members on a CUDA
    device, each step of their fits one replayed CUDA graph (``FitSchedule(cuda_graph=True)``);
    ``warmup``: what the steps before each episode's first plan do, ``auto`` resolved once from
    the random data as in :class:`ControlConfig`; ``exploration``: how many of the first rounds
    explore instead. ``renormalize``: before each refit, the world model's (and a learned
    reward's) statistics refitted on all data so far, keeping their function
    (``FitSchedule(renormalize=True)``). ``reward_model``: the sizes of a learned reward and
    termination (``env.cost: learned``, ``env.termination: learned``)."""

    experiment: str = "online"
    output_dir: str = checked("outputs/online", _directory)
    random_steps: int = count(1000)
    iterations: int = count(10)
    steps_per_iteration: int = count(200)
    refit_steps: int = count(300)
    refit_old_steps: int | None = count(None)
    refit_uncertainty: RefitUncertainty = RefitUncertainty.auto
    renormalize: bool = False
    reward_model: RewardModelConfig = field(default_factory=RewardModelConfig)
    world_model_members: int = count(1)
    fit_cuda_graph: bool = False
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    alpha: float = checked(1.0, at_least(0, " (the weight of reward)"))
    beta: float = 0.0
    warmup: Warmup = Warmup.auto
    replan: ReplanConfig = field(default_factory=lambda: ReplanConfig(mode=ReplanMode.every_step))
    exploration: OnlineExplorationConfig = field(default_factory=OnlineExplorationConfig)


def _non_empty(what: str) -> Any:
    """A list field that needs at least one ``what``."""
    message = f"a non-empty list (a {what})"
    return checked(factory=list, check=lambda v: None if v else message)


@dataclass
class ControlConfig(PlanningRunConfig):
    """Uncertainty-aware control (paper §3.1, Fig. 3). The random data are a step budget,
    ``random_episodes × random_episode_steps`` steps (the paper's "10 episodes of 500 time
    steps, 5000 samples"): an env whose episodes end early fills it with more, shorter ones.
    (In Python, ``collect_random(..., episodes=N)`` stops at N whole episodes instead.)
    ``warmup``: what the steps before each episode's first plan do (``random``, ``zeros``,
    ``plan``, see :class:`~torchrl_recon.policies.MPCPolicy`); ``auto``: ``plan`` when most random
    episodes are shorter than ``training.slice_len`` steps (episodes that end early, whose fits
    started them at rest as ``plan`` plans them), else ``random`` (the paper's)."""

    experiment: str = "control"
    output_dir: str = checked("outputs/control", _directory)
    random_episodes: int = count(10, 2)  # two at least: one is held out to validate the fit
    random_episode_steps: int = count(500)
    episodes: int = count(10)
    warmup_random_steps: int = count(10, 0)
    warmup: Warmup = Warmup.auto
    replan: ReplanConfig = field(default_factory=ReplanConfig)
    settings: list[ControlSetting] = _non_empty("control recipe needs at least one setting")


@dataclass
class EstimatorSpec(UncertaintyConfig):
    """One estimator of the calibration benchmark: a ``models.uncertainty`` block plus a name."""

    name: str = checked(MISSING, _file_name)


@dataclass
class CalibrationEvalConfig:
    """How u is judged: imagined last ``horizon`` steps of ``trajectories`` held-out
    trajectories, ranked against the real error; out of distribution, windows with the states
    moved by ``ood_state_shift`` standard deviations and with the actions at the upper bound."""

    trajectories: int = count(200)
    horizon: int = count(30)
    policy: DataPolicy = DataPolicy.offset_noise
    ood_windows: int = count(500)
    ood_state_shift: float = checked(3.0, above(0, " (standard deviations)"))


@dataclass
class TimingConfig:
    """Scoring ``candidates`` × H windows and one CEM call per estimator, for each H in ``horizons``."""

    candidates: int = count(1000)
    horizons: list[int] = checked(
        factory=lambda: [30, 200],
        check=lambda v: None if v and min(v) >= 1 else "a non-empty list of ints >= 1",
    )
    repeats: int = count(5)
    iterations: int = count(5)
    num_elites: int = count(100)


@dataclass
class OutcomesConfig:
    """Reduced-scale exploration and control runs with each estimator (a null recipe skips one;
    paths relative to the working directory, the overrides applied on top)."""

    explore_recipe: str | None = None
    explore_overrides: list[str] = field(default_factory=list)
    control_recipe: str | None = None
    control_overrides: list[str] = field(default_factory=list)


@dataclass
class CalibrateConfig(RunConfig):
    """Uncertainty estimators side by side: fitted on the same random data, judged on the same
    imagined trajectories, timed in the same run (``models.uncertainty`` is unused)."""

    experiment: str = "calibrate"
    output_dir: str = checked("outputs/calibrate", _directory)
    random_steps: int = count(10000)
    random_episode_steps: int = count(500)
    estimators: list[EstimatorSpec] = _non_empty("calibrate recipe needs at least one estimator")
    evaluation: CalibrationEvalConfig = field(default_factory=CalibrationEvalConfig)
    timing: TimingConfig = field(default_factory=TimingConfig)
    outcomes: OutcomesConfig = field(default_factory=OutcomesConfig)


LEGACY_PLANNER_DEFAULTS: dict[str, Any] = dict(
    horizon=50, num_candidates=1000, iterations=5, num_elites=100, restarts=16, lr=0.05
) | {"gradient_steps": 50}
"""The flat planner block of configs written before planner blocks took ``kwargs``: every
planner kind's keywords side by side at these defaults (``gradient_steps``: the gradient
planner's ``steps``)."""


def upgrade_legacy_config(saved: DictConfig) -> DictConfig:
    """A run directory's stored config in the current form: each flat planner block becomes
    ``{kind, kwargs}`` with only that kind's own keywords; a current config comes back as is.

    Examples:
        >>> old = OmegaConf.create({"experiment": "explore", "guided": {"planner": {
        ...     "kind": "gradient", "horizon": 30, "num_candidates": 64, "iterations": 5,
        ...     "num_elites": 16, "restarts": 4, "gradient_steps": 20, "lr": 0.05}}})
        >>> OmegaConf.to_container(upgrade_legacy_config(old).guided.planner)
        {'kind': 'gradient', 'kwargs': {'horizon': 30, 'restarts': 4, 'steps': 20, 'lr': 0.05}}
    """
    from torchrl_recon.planners.registry import PLANNERS

    data = OmegaConf.to_container(saved, resolve=False)
    blocks = [data.get("guided"), *(data.get("settings") or [])] if isinstance(data, dict) else []
    legacy = [
        b["planner"]
        for b in blocks
        if isinstance(b, dict) and isinstance(b.get("planner"), dict)
        if "kwargs" not in b["planner"]
    ]
    for old in legacy:
        kind = old.get("kind", "shooting")
        if kind not in PLANNERS:
            continue  # the schema merge reports it
        flat = {**LEGACY_PLANNER_DEFAULTS, **old}
        flat["steps"] = flat.pop("gradient_steps")
        params = inspect.signature(PLANNERS[kind]).parameters
        old.clear()
        old.update(kind=kind, kwargs={k: flat[k] for k in params if k in flat})
    return OmegaConf.create(data) if legacy else saved
