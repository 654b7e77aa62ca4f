"""DeepMind Control tasks (``"dmc:cartpole/swingup"``) through TorchRL's ``DMControlEnv``.

An optional extra: ``pip install "torchrl-recon[dmc]"``. dm_control is imported only when a
``dmc:`` id is asked for, so ``import torchrl_recon`` works without it.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torchrl.envs import CatTensors, DMControlEnv, FlattenObservation, TransformedEnv

from torchrl_recon.envs.registry import CostFn, EnvEntry

PREFIX = "dmc:"
"""What a DeepMind Control id starts with: ``dmc:<domain>/<task>``."""

INSTALL = 'pip install "torchrl-recon[dmc]"'


class MissingExtraError(ImportError, ValueError):
    """A ``dmc:`` id without dm_control installed (a ``ValueError`` too, as any unknown env)."""


@dataclass(frozen=True)
class DMCEntry(EnvEntry):
    """A DeepMind Control task: ``gym_id`` is its ``dmc:<domain>/<task>`` id; no torch cost (its
    rewards come from the simulator's state: a recipe learns them, ``env.cost: learned``);
    ``max_episode_steps`` counts simulator steps (``frame_skip`` agent steps are fewer)."""

    @property
    def domain(self) -> str:
        """The suite's domain (``"cartpole"``)."""
        return self.gym_id.removeprefix(PREFIX).split("/")[0]

    @property
    def task(self) -> str:
        """The domain's task (``"swingup"``)."""
        return self.gym_id.removeprefix(PREFIX).split("/")[1]

    def cost_fn(self) -> CostFn:
        """Refused: a DeepMind Control task has no torch cost."""
        raise ValueError(
            f"environment {self.gym_id!r} has no torch cost (DeepMind Control's rewards are not "
            "functions of the observation); learn it (env.cost=learned, docs/online.md) or give "
            "one with env.cost=module:function."
        )

    def env_class(self) -> type:
        """TorchRL's ``DMControlEnv``."""
        return DMControlEnv

    def keywords(self) -> dict[str, Any]:
        """The keywords a ``dmc:`` env takes: ``frame_skip`` (the action repeat, default 1)."""
        return {"frame_skip": 1}


def is_dmc_id(name: object) -> bool:
    """Whether ``name`` is a DeepMind Control id (``"dmc:<domain>/<task>"``).

    Examples:
        >>> is_dmc_id("dmc:cartpole/swingup"), is_dmc_id("Pendulum-v1")
        (True, False)
    """
    return isinstance(name, str) and name.startswith(PREFIX)


def dmc_entry(dmc_id: str) -> DMCEntry:
    """The entry of ``"dmc:<domain>/<task>"``, its state names read from the suite's specs.

    Raises:
        MissingExtraError: dm_control is not installed (the message names the extra).
        ValueError: ``dmc_id`` is not ``dmc:<domain>/<task>`` of a suite task.

    Examples:
        >>> entry = dmc_entry("dmc:pendulum/swingup")  # doctest: +SKIP
        >>> entry.domain, entry.task, entry.state_names  # doctest: +SKIP
        ('pendulum', 'swingup', ('orientation_0', 'orientation_1', 'velocity'))
    """
    domain, _, task = dmc_id.removeprefix(PREFIX).partition("/")
    suite = _suite(dmc_id)
    tasks = sorted(t for d, t in suite.ALL_TASKS if d == domain)
    if not tasks or task not in tasks:
        known = (
            f"{domain}'s tasks: {tasks}"
            if tasks
            else f"domains: {sorted({d for d, _ in suite.ALL_TASKS})}"
        )
        raise ValueError(
            f"Unknown DeepMind Control task {dmc_id!r}: give dmc:<domain>/<task>; {known}."
        )
    names, _ = task_dims(domain, task)
    return DMCEntry(dmc_id, dmc_id, "torchrl.envs:DMControlEnv", "", 1000, names)


@functools.cache
def task_dims(domain: str, task: str) -> tuple[tuple[str, ...], int]:
    """The names of the dims of the concatenated observation (entries sorted by key, as
    ``CatTensors``) and the action's size, read from the suite's specs without stepping."""
    try:
        env = _suite(f"{PREFIX}{domain}/{task}").load(domain, task)
    except MissingExtraError:
        raise
    except Exception as e:  # dm_control beside a MuJoCo it does not match (mujoco 4)
        raise _mismatch(f"{PREFIX}{domain}/{task}", e) from None
    names: list[str] = []
    for key, spec in sorted(env.observation_spec().items()):
        size = int(torch.Size(spec.shape).numel())
        names += [key] if size == 1 else [f"{key}_{i}" for i in range(size)]
    n_act = int(env.action_spec().shape[0])
    env.close()
    return tuple(names), n_act


def _suite(dmc_id: str) -> Any:
    """``dm_control.suite``, or one line naming the extra when it cannot be imported."""
    if importlib.util.find_spec("dm_control") is None:
        raise MissingExtraError(
            f"environment {dmc_id!r} is a DeepMind Control task and dm_control is not "
            f"installed: {INSTALL}"
        )
    try:
        from dm_control import suite
    except Exception as e:
        raise _mismatch(dmc_id, e) from None
    return suite


def _mismatch(dmc_id: str, error: Exception) -> MissingExtraError:
    return MissingExtraError(
        f"dm_control cannot load {dmc_id!r} ({type(error).__name__}: {error}); install the "
        f"versions that work together (mujoco<4): {INSTALL}"
    )


def make_dmc_env(
    domain: str,
    task: str,
    *,
    seed: int | None = None,
    frame_skip: int = 1,
    device: str | torch.device = "cpu",
) -> TransformedEnv:
    """``DMControlEnv(domain, task, frame_skip=...)`` with its observation entries flattened
    and concatenated (sorted by key) under ``"observation"``; seeded when ``seed`` is given.
    :func:`~torchrl_recon.envs.make_env` adds the float32 cast, step counter and batching.

    Examples:
        >>> env = make_dmc_env("cartpole", "swingup", seed=0, frame_skip=2)  # doctest: +SKIP
        >>> env.rollout(3)["next", "observation"].shape  # doctest: +SKIP
        torch.Size([3, 5])
    """
    if not isinstance(frame_skip, int) or isinstance(frame_skip, bool) or frame_skip < 1:
        raise ValueError(f"frame_skip must be a positive int, got {frame_skip!r}.")
    base = DMControlEnv(domain, task, frame_skip=frame_skip, device=device)
    keys = sorted(base.observation_spec.keys())
    env = TransformedEnv(base)
    for key in keys:
        dims = len(base.observation_spec[key].shape)
        if dims > 1:  # manipulator's arm_pos [8, 2]
            env.append_transform(FlattenObservation(-dims, -1, in_keys=[key]))
    env.append_transform(CatTensors(keys, "observation", del_keys=True))
    if seed is not None:
        env.set_seed(seed)
    return env


def dmc_errors(
    entry: DMCEntry, kwargs: Mapping[str, Any], state_names: Sequence[str], key: str
) -> list[str]:
    """A recipe's problems with a ``dmc:`` env, one line each: ``frame_skip`` positive,
    ``state_names`` one per observation dim (its cost and termination are checked as any
    env's, :func:`~torchrl_recon.envs.entry_checks.entry_errors`).

    Examples:
        >>> dmc_errors(dmc_entry("dmc:pendulum/swingup"), {"frame_skip": 0}, [], "env")  # doctest: +SKIP
        ["'env.kwargs.frame_skip' must be a positive integer, got 0"]
    """
    errors = []
    skip = kwargs.get("frame_skip", 1)
    if isinstance(skip, int) and skip < 1:
        errors.append(f"'{key}.kwargs.frame_skip' must be a positive integer, got {skip!r}")
    names, _ = task_dims(entry.domain, entry.task)
    if state_names and len(state_names) != len(names):
        errors.append(
            f"'{key}.state_names' must name the {len(names)} observation dims of "
            f"{entry.gym_id!r} ({', '.join(names)}), got {len(state_names)} names"
        )
    return errors
