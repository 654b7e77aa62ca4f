"""The recipe's networks, built at its sizes: the world model, the uncertainty estimator, a
learned reward and termination; and the observation and action sizes of a dataset."""

from __future__ import annotations

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase

from torchrl_recon.devices import resolve_device
from torchrl_recon.envs.registry import LEARNED
from torchrl_recon.experiments.recipe_env import learns_reward
from torchrl_recon.modules import LSTMWorldModel, RewardModel, UncertaintyEstimator, make_estimator


def dims(data: TensorDictBase) -> tuple[int, int]:
    """The observation and action sizes of ``data``."""
    return data["observation"].shape[-1], data["action"].shape[-1]


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
