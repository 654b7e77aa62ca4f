"""The recipe's environment: the env itself (CPU, primed for a policy), its registry entry,
its cost, and whether its reward is learned."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING

from omegaconf import DictConfig, OmegaConf
from torchrl.envs import DeviceCastTransform, EnvBase

from torchrl_recon.envs import get_entry, make_env
from torchrl_recon.envs.registry import LEARNED, CostFn, EnvEntry

if TYPE_CHECKING:
    from torchrl_recon.policies import MPCPolicy


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
    ``learned``).

    Examples:
        >>> learns_reward(OmegaConf.create({"env": {"cost": None, "termination": "learned"}}))
        True
    """
    return LEARNED in (cfg.env.get("cost"), cfg.env.get("termination"))
