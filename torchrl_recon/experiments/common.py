"""What the experiments share: envs, models, fits, planners and policies made from a recipe."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs import DeviceCastTransform, EnvBase

from torchrl_recon.collectors import collect_random
from torchrl_recon.data import (
    FIT_KEYS,
    REWARD_FIT_KEYS,
    long_trajectories,
    needs_padding,
    sequence_buffers,
    split_by_trajectory,
)
from torchrl_recon.devices import resolve_device
from torchrl_recon.envs import closing_env, get_entry, make_env
from torchrl_recon.envs.registry import LEARNED, CostFn, EnvEntry, import_cost
from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.modules import (
    LearnedCost,
    LearnedTermination,
    LSTMWorldModel,
    Normalizer,
    RewardModel,
    UncertaintyEstimator,
    get_estimator_class,
    make_estimator,
)
from torchrl_recon.modules.padding import loss_takes_mask
from torchrl_recon.planners import (
    Objective,
    PlannerBase,
    PlanningModel,
    UncertaintyBand,
    make_planner,
)
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.training import (
    fit_reward,
    fit_uncertainty,
    load_checkpoint,
    save_checkpoint,
    world_model_fit,
)


def build_env(
    cfg: DictConfig,
    *,
    seed: int | Sequence[int],
    episode_steps: int | None = None,
    policy: MPCPolicy | None = None,
    num_envs: int | None = None,
) -> EnvBase:
    """The recipe's env (CPU) with episodes of ``episode_steps`` (default ``env.episode_steps``):
    a ``SerialEnv`` batch for ``num_envs > 1`` or a list of seeds (:func:`~.envs.make_env`); with a
    ``policy``, its primer appended and its data cast to its device (``DeviceCastTransform``)."""
    env = make_env(
        cfg.env.id or cfg.env.name,
        seed=seed,
        num_envs=num_envs,
        parallel=False,  # worker processes cost more than they save here (docs/benchmarks.md)
        max_episode_steps=episode_steps or cfg.env.episode_steps,
        **OmegaConf.to_container(cfg.env.kwargs, resolve=True),
    )
    if policy is not None:
        if policy.device.type != "cpu":
            env.append_transform(DeviceCastTransform(policy.device, env.device))
        env.append_transform(policy.make_tensordict_primer())
    return env


def env_entry(cfg: DictConfig) -> EnvEntry:
    """The recipe's env as a registry entry: ``env.id`` (else ``env.name``) looked up, named
    ``env.name``, with ``env.cost`` and ``env.state_names`` when given.

    Examples:
        >>> cfg = OmegaConf.create({"env": {"id": "Pendulum-v1", "name": "pendulum",
        ...     "cost": "my_costs:pendulum", "state_names": ["cos", "sin", "omega"]}})
        >>> entry = env_entry(cfg)
        >>> entry.name, entry.gym_id, entry.cost_fn_path, entry.state_names
        ('pendulum', 'Pendulum-v1', 'my_costs:pendulum', ('cos', 'sin', 'omega'))
        >>> env_entry(OmegaConf.create({"env": {"name": "drone"}})).cost_fn_path
        'torchrl_recon.envs.drone:drone_cost'
    """
    env = cfg.env
    entry = get_entry(env.get("id") or env.name)
    return dataclasses.replace(
        entry,
        name=env.name or entry.name,
        cost_fn_path=env.get("cost") or entry.cost_fn_path,
        state_names=tuple(env.get("state_names") or ()) or entry.state_names,
    )


def cost_fn(cfg: DictConfig) -> CostFn:
    """The env's batched torch cost, with the recipe's env keywords it takes."""
    return env_entry(cfg).cost_fn_with(OmegaConf.to_container(cfg.env.kwargs, resolve=True))


def learns_reward(cfg: DictConfig) -> bool:
    """Whether the recipe's cost or termination is learned (``env.cost`` or ``env.termination``
    ``learned``)."""
    return LEARNED in (cfg.env.get("cost"), cfg.env.get("termination"))


def build_reward_model(
    cfg: DictConfig, obs_dim: int, action_dim: int, device: torch.device | None = None
) -> RewardModel | None:
    """The recipe's learned reward and termination (``reward_model`` sizes), on ``device``, or
    None when neither ``env.cost`` nor ``env.termination`` is ``learned``."""
    if not learns_reward(cfg):
        return None
    device = resolve_device(cfg.device) if device is None else device
    sizes = OmegaConf.to_container(cfg.reward_model, resolve=True)
    return RewardModel(
        obs_dim,
        action_dim,
        reward=cfg.env.get("cost") == LEARNED,
        termination=cfg.env.get("termination") == LEARNED,
        **sizes,
    ).to(device)


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


def random_data_stage(
    ctx: RunContext, name: str, *, frames: int, episode_steps: int | None = None, keys: tuple = ()
) -> TensorDictBase:
    """Stage ``name``: ``frames`` uniform random steps (``num_envs`` envs as one batch), stored
    as ``buffers/<name>`` (only ``keys``, if given); returns the stored data."""

    def run() -> dict:
        seed = ctx.stage_seed(name)
        env = build_env(ctx.cfg, seed=seed, episode_steps=episode_steps, num_envs=ctx.cfg.num_envs)
        with closing_env(env):  # the collector has closed a batched env already
            data = collect_random(env, frames=frames, seed=seed, progress=ctx.cfg.progress)
        ctx.stages.save_data(name, data.select(*keys) if keys else data)
        return {"steps": data.numel()}

    ctx.stages.run(name, run)
    return ctx.stages.load_data(name)


def warmup_mode(cfg: DictConfig, data: TensorDictBase) -> str:
    """The recipe's ``warmup`` (control and online kinds), ``auto`` resolved on the random
    ``data`` as :class:`~torchrl_recon.experiments.config.ControlConfig` says (a random warm-up
    would end most MPC episodes before their first plan). Most, not all: one random episode that
    lasted longer (InvertedPendulum's reach 20-26 steps now and then) keeps ``plan``.

    Examples:
        >>> from tensordict import TensorDict
        >>> cfg = OmegaConf.create({"warmup": "auto", "training": {"slice_len": 4}})
        >>> ids = torch.tensor([0, 0, 0, 1, 1, 1, 1, 1, 2, 2, 3, 3])  # episodes of 3, 5, 2, 2 steps
        >>> data = TensorDict({("collector", "traj_ids"): ids}, [12])
        >>> warmup_mode(cfg, data), warmup_mode(OmegaConf.merge(cfg, {"warmup": "zeros"}), data)
        ('plan', 'zeros')
    """
    mode = str(cfg.warmup)
    if mode != "auto":
        return mode
    long, episodes = (long_trajectories(data, n) for n in (cfg.training.slice_len, 1))
    return "plan" if 2 * long < episodes else "random"


def build_world_model(
    cfg: DictConfig, obs_dim: int, action_dim: int, members: int | None = None
) -> LSTMWorldModel:
    """The world model of the recipe's sizes (``members``: R members, an ensemble)."""
    return LSTMWorldModel(
        obs_dim, action_dim, window=cfg.models.window, num_members=members, **cfg.models.world_model
    )


def build_estimator(
    spec: DictConfig, obs_dim: int, action_dim: int, window: int
) -> UncertaintyEstimator:
    """The estimator of a ``models.uncertainty`` block or a calibration entry
    (:func:`~torchrl_recon.modules.make_estimator`)."""
    kwargs = OmegaConf.to_container(spec.kwargs, resolve=True) if spec.get("kwargs") else {}
    sizes = dict(window=window, hidden_size=spec.hidden_size, activation=spec.activation)
    return make_estimator(spec.kind, obs_dim, action_dim, **sizes, **kwargs)


def build_models(
    cfg: DictConfig, obs_dim: int, action_dim: int, device: torch.device | None = None
) -> tuple[LSTMWorldModel, UncertaintyEstimator]:
    """World model (an ensemble of the recipe's ``world_model_members`` where above 1) and
    estimator of the recipe's sizes, on ``device`` (default: ``cfg.device``)."""
    m, device = cfg.models, resolve_device(cfg.device) if device is None else device
    r = cfg.get("world_model_members", 1)
    world = build_world_model(cfg, obs_dim, action_dim, r if r > 1 else None).to(device)
    return world, build_estimator(m.uncertainty, obs_dim, action_dim, m.window).to(device)


def models_stage(
    ctx: RunContext, data: TensorDictBase, name: str
) -> tuple[LSTMWorldModel, UncertaintyEstimator, dict]:
    """Stage ``name``: the world model and the estimator fitted on ``data``, and its record."""
    world, estimator = build_models(ctx.cfg, *dims(data), ctx.device)
    record = fit_stage(ctx, name, data, {"world_model": world, "uncertainty": estimator})
    return world, estimator, record


def dims(data: TensorDictBase) -> tuple[int, int]:
    """The observation and action sizes of ``data``."""
    return data["observation"].shape[-1], data["action"].shape[-1]


def check_random_data(cfg: DictConfig, data: TensorDictBase, key: str = "random_steps") -> None:
    """Refuse random ``data`` (``key`` steps) without two episodes a fit can use, each ended or
    of ``training.slice_len`` steps: a fit holds whole episodes out to validate. Where episodes
    may end early (``env.termination``), it replaces the recipe check ``key >=
    env.episode_steps + training.slice_len``.

    Raises:
        RecipeError: naming ``key``, before any fit.

    Examples:
        >>> from tensordict import TensorDict
        >>> cfg = OmegaConf.create({"training": {"slice_len": 4}, "random_steps": 5,
        ...     "env": {"episode_steps": 10}})
        >>> data = TensorDict({("collector", "traj_ids"): torch.tensor([0, 0, 0, 1, 1]),
        ...     ("next", "done"): torch.tensor([[0], [0], [1], [0], [0]]).bool()}, [5])
        >>> check_random_data(cfg, data)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        torchrl_recon.errors.RecipeError: 'random_steps' = 5 gave 1 episode that ended or held...
    """
    t = cfg.training
    count = long_trajectories(data, t.slice_len, ended=True)
    if count < 2:
        raise RecipeError(
            f"'{key}' = {cfg[key]} gave {count} episode{'' if count == 1 else 's'} that ended or "
            f"held training.slice_len = {t.slice_len} steps; a fit holds whole episodes out to "
            f"validate, so it needs two: raise {key} (env.episode_steps + training.slice_len = "
            f"{cfg.env.episode_steps + t.slice_len} always gives two) in a new output_dir."
        )


def check_padding(cfg: DictConfig) -> None:
    """Refuse what padded slices (:func:`split_buffers`) cannot train, before the first fit:
    ``training.window_sampling = step``, or an estimator whose loss takes no mask
    (``models.uncertainty.kind``, or each of a calibrate recipe's ``estimators``).

    Raises:
        RecipeError: naming the key to change.

    Examples:
        >>> cfg = OmegaConf.create({"training": {"slice_len": 8, "window_sampling": "step"},
        ...     "models": {"window": 4, "uncertainty": {"kind": "reconstruction"}}})
        >>> check_padding(cfg)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        torchrl_recon.errors.RecipeError: episodes shorter than training.slice_len = 8 steps are padded...
    """
    t = cfg.training
    where = f"episodes shorter than training.slice_len = {t.slice_len} steps are padded"
    lower = f"or lower training.slice_len (above models.window = {cfg.models.window})"
    if t.window_sampling != "trajectory":
        raise RecipeError(
            f"{where}, which needs training.window_sampling = trajectory (got "
            f"{t.window_sampling}): set it, {lower}."
        )
    if "estimators" in cfg:  # a calibrate recipe fits each of its estimators
        named = [(f"estimators[{i}].kind", spec) for i, spec in enumerate(cfg.estimators)]
    else:
        named = [("models.uncertainty.kind", cfg.models.uncertainty)]
    for key, spec in named:
        if not loss_takes_mask(get_estimator_class(spec.kind)):
            raise RecipeError(
                f"{where}, and {key} = {spec.kind} cannot train on padded slices: "
                f"use reconstruction or rnd, {lower}."
            )


def split_buffers(cfg: DictConfig, data: TensorDictBase, seed: int, keys: tuple = FIT_KEYS):
    """Training and validation sequence buffers of ``data`` (its ``keys``), split by trajectory
    (``seed``); when a split has no trajectory of ``slice_len`` steps, both pad shorter ones
    (:func:`~torchrl_recon.data.sequence_buffers`), once :func:`check_padding` passes."""
    t = cfg.training
    parts = split_by_trajectory(data, t.val_fraction, seed=seed)
    if needs_padding(t.slice_len, *parts):
        check_padding(cfg)
    sizes = dict(slice_len=t.slice_len, num_slices=t.num_slices, sampling=t.window_sampling)
    return sequence_buffers(parts, **sizes, keys=keys)


def fit_kwargs(ctx: RunContext, fit: DictConfig, prefix: str) -> dict:
    """The keywords of a fit from a recipe's ``training.world_model`` or ``.uncertainty`` block."""
    return dict(**fit, progress=ctx.cfg.progress, logger=ctx.logger, log_prefix=prefix)


def fit_module(
    ctx: RunContext,
    module: LSTMWorldModel | UncertaintyEstimator,
    data: TensorDictBase,
    *,
    seed: int,
    prefix: str,
    fit_normalization: bool = True,
) -> float:
    """Fit the world model, an estimator or a learned reward on ``data``; returns the best
    validation loss. A learned reward takes the world model's fit settings (uncompiled)."""
    t, world = ctx.cfg.training, isinstance(module, LSTMWorldModel)
    reward = isinstance(module, RewardModel)
    rb, val_rb = split_buffers(ctx.cfg, data, seed, keys=REWARD_FIT_KEYS if reward else FIT_KEYS)
    if reward:
        block = OmegaConf.merge(t.world_model, {"compile": False})
    else:
        block = t.world_model if world else t.uncertainty
    kwargs = fit_kwargs(ctx, block, prefix)
    kwargs |= {"mode": t.world_model_mode} if world else {}
    if world and module.num_members is not None and ctx.cfg.get("fit_cuda_graph", False):
        kwargs["cuda_graph"] = True  # online's first fit of members, as its refits
    common = dict(val_buffer=val_rb, fit_normalization=fit_normalization, checkpoint_modules={})
    fit = world_model_fit(module) if world else fit_reward if reward else fit_uncertainty
    return fit(module, rb, seed=seed, **common, **kwargs).best_val_loss


def checkpoint_stage(
    ctx: RunContext, name: str, modules: Mapping[str, torch.nn.Module], fit: Callable[[], dict]
) -> dict:
    """Stage ``name``: ``fit()`` (returns the record), then ``modules`` checkpointed together as
    ``checkpoints/<name>.pt`` under their keys (loaded back when the stage is done)."""
    path = ctx.stages.path("checkpoints", f"{name}.pt")

    def run() -> dict:
        record = fit()
        save_checkpoint(path, dict(modules))
        return record

    record = ctx.stages.run(name, run)
    load_checkpoint(path, dict(modules))
    return record


def fit_stage(
    ctx: RunContext,
    name: str,
    data: TensorDictBase,
    modules: Mapping[str, LSTMWorldModel | UncertaintyEstimator],
    *,
    fit_normalization: bool = True,
) -> dict:
    """A :func:`checkpoint_stage` fitting ``modules`` on ``data`` (one seed, in order); the record
    holds ``val_loss`` for one module, else ``<key>_val_loss``."""
    one = len(modules) == 1

    def fit() -> dict:
        seed, record = torch.initial_seed() % (2**31), {}
        for key, module in modules.items():
            prefix = f"{name}/" if one else f"{name}/{key}/"
            loss = fit_module(
                ctx, module, data, seed=seed, prefix=prefix, fit_normalization=fit_normalization
            )
            record["val_loss" if one else f"{key}_val_loss"] = loss
        return record

    return checkpoint_stage(ctx, name, modules, fit)


def build_planner(
    planner_cfg: DictConfig, model: PlanningModel, objective: Objective
) -> PlannerBase:
    """The planner of a recipe's planner block (:func:`~torchrl_recon.planners.make_planner`)."""
    kwargs = OmegaConf.to_container(planner_cfg.kwargs, resolve=True)
    return make_planner(planner_cfg.kind, model, objective, **kwargs)


def setting_objective(setting: DictConfig, beta_unit: float) -> tuple[Objective, float]:
    """The setting's objective and its β (× ``beta_unit`` when relative)."""
    b = setting.band
    band = None if b is None else UncertaintyBand(b.low, b.high, b.kind)
    beta = setting.beta * beta_unit if setting.beta_relative else setting.beta
    objective = Objective(
        alpha=setting.alpha, beta=beta, band=band, cost_threshold=setting.cost_threshold
    )
    return objective, beta


def replan_threshold(cfg: DictConfig, per_window_u: torch.Tensor) -> float:
    """The re-planning threshold on u: a quantile of the windows' u, scaled (× ``every`` when
    it bounds Σu over the steps between plans)."""
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


def batches(count: int, size: int | None) -> list[range]:
    """``range(count)`` in batches of ``size`` (one batch if None; the last may be smaller).

    Examples:
        >>> [list(b) for b in batches(5, 2)], batches(3, None)
        ([[0, 1], [2, 3], [4]], [range(0, 3)])
    """
    size = size or count
    return [range(i, min(i + size, count)) for i in range(0, count, size)]


def state_scale(data: TensorDictBase) -> torch.Tensor:
    """Per-dimension standard deviation of the observations (1 where constant): the unit of reported MSEs."""
    norm = Normalizer(data["observation"].shape[-1])
    norm.fit(data["observation"].cpu())
    return norm.scale.clone()
