"""One factory that turns a torchrl_recon gymnasium environment into a TorchRL env."""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import torch
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    GymEnv,
    InitTracker,
    ParallelEnv,
    SerialEnv,
    StepCounter,
    TransformedEnv,
)

from torchrl_recon.envs.dmc import DMCEntry, make_dmc_env
from torchrl_recon.envs.registry import get_entry, register_envs
from torchrl_recon.envs.spaces import space_errors


def _make_gym_env(gym_id: str, seed: int | None = None, **kwargs) -> GymEnv:
    # ParallelEnv workers are spawned processes that never import torchrl_recon unless the main
    # module does; unpickling this function imports it, and register_envs() makes sure the
    # torchrl_recon/* ids exist in the worker before gymnasium.make looks them up.
    register_envs()
    env = GymEnv(gym_id, **kwargs)
    if seed is not None:  # a sub-env of a batch seeded on its own (make_env(seed=[...]))
        env.set_seed(seed)
    return env


def make_env(
    name: str,
    *,
    seed: int | Sequence[int],
    num_envs: int | None = None,
    device: str | torch.device = "cpu",
    parallel: bool = True,
    max_episode_steps: int | None = None,
    **env_kwargs,
) -> EnvBase:
    """Build the TorchRL env for ``name`` with the transforms every recipe expects.

    The result is ``TransformedEnv(GymEnv(...), Compose(DoubleToFloat(), StepCounter(),
    InitTracker()))``; with ``num_envs > 1`` the base is a ``ParallelEnv`` (or ``SerialEnv``
    when ``parallel=False``) of ``num_envs`` workers; the first is seeded with ``seed``, the
    next ones with seeds derived from it by TorchRL's ``seed_generator`` chain.
    Episode truncation comes from the gymnasium registration (``TimeLimit``).

    A DeepMind Control task is ``"dmc:<domain>/<task>"`` (``pip install "torchrl-recon[dmc]"``):
    TorchRL's ``DMControlEnv`` with ``frame_skip`` from ``env_kwargs`` and its observation
    entries concatenated under ``"observation"``; episodes end at the suite's limit (1,000
    simulator steps) or at ``max_episode_steps`` (``StepCounter``).

    Any gymnasium environment works: a gymnasium id (``"Pendulum-v1"``) or
    ``"my_module:MyEnv-v0"``, for which gymnasium imports ``my_module`` (where the env is
    registered with ``gymnasium.register``) first; see
    :func:`~torchrl_recon.envs.registry.get_entry`. Such an env has no torch cost unless it is
    registered with :func:`~torchrl_recon.envs.registry.register_env`; its action bounds come
    from its action spec (:meth:`~torchrl_recon.planners.PlanningModel.from_env`).

    Args:
        name: short name (``"industrial_benchmark"``, ``"drone"``, ``"minitaur"``, or one given
            to ``register_env``), gymnasium id (``"Pendulum-v1"``, ``"my_module:MyEnv-v0"``) or
            DeepMind Control task (``"dmc:cartpole/swingup"``).

    Keyword Args:
        seed: seed of the (first) environment, or one seed per environment.
        num_envs: number of environments in the batch (default: ``len(seed)`` for a list of
            seeds, else 1).
        device: device of the TorchRL env.
        parallel: use worker processes when ``num_envs > 1``.
        max_episode_steps: truncate episodes here instead of at the registered limit.
        **env_kwargs: keyword arguments of the gymnasium environment's constructor.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> env = make_env("drone", seed=0)
        >>> td = env.rollout(3)
        >>> td["next", "observation"].shape, td["next", "observation"].dtype
        (torch.Size([3, 12]), torch.float32)
        >>> env.close()
        >>> make_env("Pendulum-v1", seed=0).action_spec.space.high.tolist()
        [2.0]
        >>> batch = make_env("drone", seed=[3, 7], parallel=False)  # a SerialEnv, one seed each
        >>> batch.reset()["observation"].shape
        torch.Size([2, 12])
        >>> batch.close()
        >>> make_env("CartPole-v1", seed=0)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ValueError: environment 'CartPole-v1' has a discrete action space ...

    Raises:
        ValueError: the env's observation is not one flat float vector, or its action not a
            bounded continuous vector (the message says how to wrap it).
    """
    register_envs()
    entry = get_entry(name)
    seeds = None
    if isinstance(seed, Sequence) and not isinstance(seed, str):
        seeds = list(seed)
        if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
            raise TypeError(f"seed must be an int or a non-empty list of ints, got {seed!r}.")
        num_envs = len(seeds) if num_envs is None else num_envs
        if num_envs != len(seeds):
            raise ValueError(
                f"seed lists {len(seeds)} seeds but num_envs is {num_envs}: give one per env."
            )
    elif not isinstance(seed, int) or isinstance(seed, bool):
        raise TypeError(f"seed must be an int or a list of ints, got {seed!r}.")
    num_envs = 1 if num_envs is None else num_envs
    if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive int, got {num_envs!r}.")
    entry.check_kwargs(env_kwargs)
    if max_episode_steps is not None:
        if not isinstance(max_episode_steps, int) or max_episode_steps < 1:
            raise ValueError(
                f"max_episode_steps must be a positive int, got {max_episode_steps!r}."
            )
    max_steps = None  # a gymnasium env truncates itself (TimeLimit), a DeepMind Control one here
    if isinstance(entry, DMCEntry):
        max_steps = max_episode_steps
        create = partial(make_dmc_env, entry.domain, entry.task, device=device, **env_kwargs)
    else:
        if max_episode_steps is not None:
            env_kwargs["max_episode_steps"] = max_episode_steps
        create = partial(_make_gym_env, entry.gym_id, device=device, **env_kwargs)
    batched = ParallelEnv if parallel else SerialEnv
    if seeds is not None and num_envs > 1:
        base = batched(num_envs, [partial(create, seed=s) for s in seeds], device=device)
    elif num_envs > 1:
        base = batched(num_envs, create, device=device)
    else:
        base = create()
    errors = space_errors(base, name)
    if errors:
        base.close()
        raise ValueError("; ".join(errors) + ".")
    transforms = Compose(DoubleToFloat(), StepCounter(max_steps), InitTracker())
    env = TransformedEnv(base, transforms, auto_unwrap=True)  # a dmc env's own joins these
    if seeds is None or num_envs == 1:
        env.set_seed(seed if seeds is None else seeds[0])
    return env
