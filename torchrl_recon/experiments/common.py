"""Builders the experiments share: envs, models, fitting, planners, metrics scale."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs import DeviceCastTransform, EnvBase
from torchrl.record.loggers import Logger

from torchrl_recon.collectors import collect_random
from torchrl_recon.data import make_sequence_buffer, split_by_trajectory
from torchrl_recon.data.buffers import TRAJ_KEY
from torchrl_recon.devices import resolve_device
from torchrl_recon.envs import close_env, get_entry, make_env
from torchrl_recon.envs.registry import CostFn, EnvEntry, import_cost
from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.modules import LSTMWorldModel, Normalizer, UncertaintyEstimator
from torchrl_recon.planners import (
    Objective,
    PlannerBase,
    PlanningModel,
    TerminationFn,
    make_planner,
)
from torchrl_recon.training import (
    fit_uncertainty,
    fit_world_model,
    load_checkpoint,
    save_checkpoint,
)


def build_env(
    cfg: DictConfig,
    *,
    seed: int | Sequence[int],
    episode_steps: int,
    policy_device: torch.device | None = None,
    num_envs: int | None = None,
) -> EnvBase:
    """The recipe's TorchRL env with episodes of ``episode_steps``, simulated on the CPU.

    With ``num_envs > 1`` (or a list of seeds, one per env) it is a ``SerialEnv`` batch (see
    :func:`~torchrl_recon.envs.make_env`). With a ``policy_device`` other than the CPU,
    TorchRL's ``DeviceCastTransform`` hands the policy its data on that device and the env
    its actions back on the CPU.
    """
    kwargs = OmegaConf.to_container(cfg.env.kwargs, resolve=True)
    env = make_env(
        cfg.env.id or cfg.env.name,
        seed=seed,
        num_envs=num_envs,
        parallel=False,  # worker processes cost more than they save here (docs/benchmarks.md)
        max_episode_steps=episode_steps,
        **kwargs,
    )
    if policy_device is not None and torch.device(policy_device).type != "cpu":
        env.append_transform(DeviceCastTransform(policy_device, env.device))
    return env


def env_entry(cfg: DictConfig) -> EnvEntry:
    """The recipe's env as a registry entry: ``env.id`` (else ``env.name``) looked up in the
    registry, named ``env.name``, with ``env.cost`` and ``env.state_names`` when given.

    A shipped env and a gymnasium id go through the same lookup
    (:func:`~torchrl_recon.envs.get_entry`); nothing is imported but the env's module (for
    ``module:EnvId``).

    Raises:
        ValueError: the env is unknown (the message says how to register one).

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
    """The env's batched torch cost (``env.cost``, else the registered env's), with the
    recipe's env keywords where the cost takes them (keyword-only parameters)."""
    kwargs = OmegaConf.to_container(cfg.env.kwargs, resolve=True)
    return env_entry(cfg).cost_fn_with(kwargs)


def termination_fn(cfg: DictConfig) -> TerminationFn | None:
    """The recipe's ``env.termination`` function, imported (None when not given)."""
    path = cfg.env.get("termination")
    return None if path is None else import_cost(path, what="termination")


def planning_model(
    cfg: DictConfig, world: LSTMWorldModel, uncertainty: UncertaintyEstimator | None = None
) -> PlanningModel:
    """The recipe's :class:`PlanningModel`: its cost and termination, and the action bounds of
    its env's spec (:meth:`PlanningModel.from_env`; the env is built, read and closed, without
    stepping)."""
    env = build_env(cfg, seed=0, episode_steps=1)
    try:
        return PlanningModel.from_env(
            world, cost_fn(cfg), env, uncertainty=uncertainty, termination_fn=termination_fn(cfg)
        )
    finally:
        close_env(env)


def random_data_stage(
    ctx: RunContext,
    name: str,
    *,
    frames: int,
    episode_steps: int,
    keys: tuple | None = None,
) -> TensorDictBase:
    """A resumable stage: ``frames`` uniform random steps in episodes of ``episode_steps``,
    seeded by (seed, ``name``), stored as ``buffers/<name>`` (only ``keys``, if given); returns
    the stored data. With the recipe's ``num_envs > 1`` the steps come from that many envs
    stepped as one batch (each env's trajectories contiguous in the stored data)."""

    def run() -> dict:
        seed = ctx.stage_seed(name)
        env = build_env(ctx.cfg, seed=seed, episode_steps=episode_steps, num_envs=ctx.cfg.num_envs)
        data = collect_random(env, frames=frames, seed=seed, progress=ctx.cfg.progress)
        close_env(env)  # the collector has closed a batched env already
        ctx.stages.save_data(name, data if keys is None else data.select(*keys))
        return {"steps": data.numel()}

    ctx.stages.run(name, run)
    return ctx.stages.load_data(name)


def build_world_model(cfg: DictConfig, obs_dim: int, action_dim: int) -> LSTMWorldModel:
    """The world model of the recipe's sizes."""
    m = cfg.models
    return LSTMWorldModel(
        obs_dim,
        action_dim,
        window=m.window,
        hidden_size=m.world_model.hidden_size,
        dense_size=m.world_model.dense_size,
        activation=m.world_model.activation,
    )


def build_estimator(
    spec: DictConfig, obs_dim: int, action_dim: int, window: int
) -> UncertaintyEstimator:
    """The estimator a recipe's ``models.uncertainty`` block (or a calibration entry) names:
    ``kind`` (a key of :data:`~torchrl_recon.modules.ESTIMATORS` or ``module:Class``) built as
    ``Class(obs_dim, action_dim, window=window, hidden_size=..., activation=..., **kwargs)``."""
    from torchrl_recon.modules.estimators import make_estimator

    kwargs = OmegaConf.to_container(spec.kwargs, resolve=True) if spec.get("kwargs") else {}
    return make_estimator(
        spec.kind,
        obs_dim,
        action_dim,
        window=window,
        hidden_size=spec.hidden_size,
        activation=spec.activation,
        **kwargs,
    )


def build_models(
    cfg: DictConfig, obs_dim: int, action_dim: int, device: torch.device | None = None
) -> tuple[LSTMWorldModel, UncertaintyEstimator]:
    """World model and estimator of the recipe's sizes, on ``device`` (the run context's; by
    default the recipe's ``device``)."""
    m = cfg.models
    device = resolve_device(cfg.device) if device is None else device
    world = build_world_model(cfg, obs_dim, action_dim).to(device)
    return world, build_estimator(m.uncertainty, obs_dim, action_dim, m.window).to(device)


def check_episode_lengths(cfg: DictConfig, data: TensorDictBase) -> None:
    """Refuse data whose train or validation split could hold no training window: fewer than
    two trajectories of ``training.slice_len`` steps (an env whose episodes end early, e.g.
    InvertedPendulum's random episodes of 3-8 steps).

    Raises:
        RecipeError: naming the longest episode and the keys to change.

    Examples:
        >>> from tensordict import TensorDict
        >>> cfg = OmegaConf.create({"training": {"slice_len": 8}, "models": {"window": 4}})
        >>> short = TensorDict({("collector", "traj_ids"): torch.arange(30) // 5}, [30])
        >>> check_episode_lengths(cfg, short)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        torchrl_recon.errors.RecipeError: 0 of the 6 episodes in the data have training.slice_len = 8 steps (the longest has 5)...
    """
    ids = data.get(TRAJ_KEY)
    _, lengths = torch.unique_consecutive(ids, return_counts=True)
    slice_len = cfg.training.slice_len
    long = int((lengths >= slice_len).sum())
    if long < 2:
        raise RecipeError(
            f"{long} of the {len(lengths)} episodes in the data have training.slice_len = "
            f"{slice_len} steps (the longest has {int(lengths.max())}); the fits sample windows of "
            "slice_len steps inside one episode, and two such episodes at least (one to "
            f"validate): lower training.slice_len (above models.window = {cfg.models.window}) "
            "and models.window, or collect longer episodes."
        )


def split_buffers(cfg: DictConfig, data: TensorDictBase, seed: int):
    """Training and validation sequence buffers of ``data``, split by trajectory (``seed``)
    with the recipe's ``training`` sizes and window sampling."""
    check_episode_lengths(cfg, data)
    train, val = split_by_trajectory(data, cfg.training.val_fraction, seed=seed)
    t = cfg.training
    sizes = dict(slice_len=t.slice_len, num_slices=t.num_slices, sampling=t.window_sampling)
    rb = make_sequence_buffer(len(train), **sizes)
    val_rb = make_sequence_buffer(len(val), **sizes)
    rb.extend(train)
    val_rb.extend(val)
    return rb, val_rb


def fit_kwargs(fit: DictConfig, progress: bool, logger: Logger | None, prefix: str) -> dict:
    """The keywords of a fit (``fit_world_model``, ``fit_population``, ...) from a recipe's
    ``training.world_model`` or ``training.uncertainty`` block."""
    return dict(
        steps=fit.steps,
        lr=fit.lr,
        eval_every=fit.eval_every,
        patience=fit.patience,
        progress=progress,
        logger=logger,
        log_prefix=prefix,
    )


def fit_module(
    ctx: RunContext,
    module: LSTMWorldModel | UncertaintyEstimator,
    data: TensorDictBase,
    *,
    seed: int,
    prefix: str,
    fit_normalization: bool = True,
) -> float:
    """Fit the world model or the estimator on ``data`` (validation split by trajectory).

    Returns the best validation loss.
    """
    cfg = ctx.cfg
    rb, val_rb = split_buffers(cfg, data, seed)
    common = dict(val_buffer=val_rb, fit_normalization=fit_normalization, checkpoint_modules={})
    if isinstance(module, LSTMWorldModel):
        fit_cfg, extra = cfg.training.world_model, {"mode": cfg.training.world_model_mode}
        fit = fit_world_model
    else:
        fit_cfg, extra, fit = cfg.training.uncertainty, {}, fit_uncertainty
    kwargs = fit_kwargs(fit_cfg, cfg.progress, ctx.logger, prefix)
    return fit(module, rb, seed=seed, **common, **extra, **kwargs).best_val_loss


def fit_stage(
    ctx: RunContext,
    name: str,
    data: TensorDictBase,
    modules: Mapping[str, LSTMWorldModel | UncertaintyEstimator],
    *,
    fit_normalization: bool = True,
) -> dict:
    """A resumable stage that fits ``modules`` on ``data`` (one seed for all, in order) and
    checkpoints them together as ``checkpoints/<name>.pt`` under their keys.

    The record holds ``val_loss`` for one module, else ``<key>_val_loss`` for each (logged
    under ``<name>/`` or ``<name>/<key>/``). On resume the checkpoint is loaded back.
    """
    path = ctx.stages.path("checkpoints", f"{name}.pt")
    single = len(modules) == 1

    def run() -> dict:
        seed = torch.initial_seed() % (2**31)
        record = {}
        for key, module in modules.items():
            loss = fit_module(
                ctx,
                module,
                data,
                seed=seed,
                prefix=f"{name}/" if single else f"{name}/{key}/",
                fit_normalization=fit_normalization,
            )
            record["val_loss" if single else f"{key}_val_loss"] = loss
        save_checkpoint(path, dict(modules))
        return record

    record = ctx.stages.run(name, run)
    load_checkpoint(path, dict(modules))
    return record


def build_planner(
    planner_cfg: DictConfig, model: PlanningModel, objective: Objective
) -> PlannerBase:
    """The planner a recipe's planner block names: ``kind`` (a key of
    :data:`~torchrl_recon.planners.PLANNERS` or ``module:Class``) built as
    ``Class(model, objective, **kwargs)``."""
    kwargs = OmegaConf.to_container(planner_cfg.kwargs, resolve=True)
    return make_planner(planner_cfg.kind, model, objective, **kwargs)


def state_scale(data: TensorDictBase) -> torch.Tensor:
    """Per-dimension standard deviation of the observations (1 where constant): the unit of reported MSEs."""
    norm = Normalizer(data["observation"].shape[-1])
    norm.fit(data["observation"].cpu())
    return norm.scale.clone()
