"""The one table of environments: names, gymnasium ids, classes and torch cost functions."""

from __future__ import annotations

import functools
import importlib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import torch

CostFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class EnvEntry:
    """One environment: short name, gymnasium id, class path, cost function path, episode limit, state names."""

    name: str
    gym_id: str
    entry_point: str
    cost_fn_path: str
    max_episode_steps: int
    state_names: tuple[str, ...] = ()

    def cost_fn(self) -> CostFn:
        """Import and return the batched torch cost ``cost(obs, action, next_obs) -> [...]``."""
        module, attr = self.cost_fn_path.split(":")
        return getattr(importlib.import_module(module), attr)

    def cost_fn_with(self, env_kwargs: Mapping[str, Any]) -> CostFn:
        """The cost with the env keywords (a recipe's ``env.kwargs``) that the cost also takes.

        Examples:
            >>> get_entry("minitaur").cost_fn_with({"cost": "forward", "motor_kp": 1.0}).keywords
            {'cost': 'forward'}
        """
        fn = self.cost_fn()
        params = inspect.signature(fn).parameters
        shared = {
            k: v
            for k, v in env_kwargs.items()
            if k in params and params[k].kind is inspect.Parameter.KEYWORD_ONLY
        }
        return functools.partial(fn, **shared) if shared else fn

    def env_class(self) -> type:
        """Import and return the gymnasium environment class."""
        module, attr = self.entry_point.split(":")
        return getattr(importlib.import_module(module), attr)

    def keywords(self) -> dict[str, Any] | None:
        """The constructor keywords of the environment class and their defaults.

        Read from the class's ``__init__`` signature; a keyword without a default maps to
        ``inspect.Parameter.empty``. None when the constructor takes ``**kwargs`` (any keyword).

        Examples:
            >>> sorted(get_entry("industrial_benchmark").keywords())
            ['reference_rng', 'setpoint', 'stationary_setpoint']
        """
        params = inspect.signature(self.env_class().__init__).parameters
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            return None
        return {
            name: p.default
            for name, p in params.items()
            if name != "self" and p.kind is not inspect.Parameter.VAR_POSITIONAL
        }

    def check_kwargs(self, kwargs: Mapping[str, Any]) -> None:
        """Refuse constructor keywords the environment class does not take.

        Raises:
            TypeError: naming the environment, the unknown keywords and the accepted ones.

        Examples:
            >>> get_entry("drone").check_kwargs({"delta": 0.1})
            >>> try:
            ...     get_entry("drone").check_kwargs({"action_mode": "leg"})
            ... except TypeError as e:
            ...     print(str(e).split(";")[0])
            environment 'drone' (DroneEnv) has no keyword(s) ['action_mode']
        """
        allowed = self.keywords()
        if allowed is None:
            return
        unknown = sorted(set(kwargs) - set(allowed))
        if unknown:
            raise TypeError(
                f"environment {self.name!r} ({self.env_class().__name__}) has no keyword(s) "
                f"{unknown}; it accepts {sorted(allowed)}."
            )


ENVS: dict[str, EnvEntry] = {
    e.name: e
    for e in (
        EnvEntry(
            "industrial_benchmark",
            "torchrl_recon/IndustrialBenchmark-v0",
            "torchrl_recon.envs.industrial_benchmark:IndustrialBenchmarkEnv",
            "torchrl_recon.envs.industrial_benchmark:industrial_benchmark_cost",
            1000,
            ("p", "v", "g", "h", "f", "c"),
        ),
        EnvEntry(
            "drone",
            "torchrl_recon/Drone-v0",
            "torchrl_recon.envs.drone:DroneEnv",
            "torchrl_recon.envs.drone:drone_cost",
            500,
            ("x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw", "p", "q", "r"),
        ),
        EnvEntry(
            "minitaur",
            "torchrl_recon/Minitaur-v0",
            "torchrl_recon.envs.minitaur:MinitaurEnv",
            "torchrl_recon.envs.minitaur:minitaur_cost",
            500,
            tuple(
                [f"motor_angle_{i}" for i in range(8)]
                + [f"motor_velocity_{i}" for i in range(8)]
                + [f"motor_torque_{i}" for i in range(8)]
                + ["qx", "qy", "qz", "qw", "x - x0", "y - y0", "z", "vx", "vy", "vz"]
            ),
        ),
    )
}


def get_entry(name: str) -> EnvEntry:
    """Look an environment up by short name (``"drone"``) or gymnasium id.

    Examples:
        >>> get_entry("torchrl_recon/Drone-v0").name
        'drone'
    """
    for entry in ENVS.values():
        if name in (entry.name, entry.gym_id):
            return entry
    known = sorted(list(ENVS) + [e.gym_id for e in ENVS.values()])
    raise ValueError(f"Unknown environment {name!r}; expected one of {known}.")


def register_envs() -> None:
    """Register every environment with gymnasium (idempotent)."""
    for entry in ENVS.values():
        if entry.gym_id not in gym.registry:
            gym.register(
                id=entry.gym_id,
                entry_point=entry.entry_point,
                max_episode_steps=entry.max_episode_steps,
            )
