"""What the library needs of an env's spaces, checked where a user's env first enters it."""

from __future__ import annotations

import torch
from torchrl.envs import EnvBase


def space_errors(env: EnvBase, name: str) -> list[str]:
    """Why ``env`` (a TorchRL env, batched or not) cannot be modelled and planned for: its
    observation must be one flat float vector under ``"observation"`` (a gymnasium ``Box``),
    its action a bounded continuous float vector. Empty when it can.

    Examples:
        >>> from torchrl.envs import GymEnv
        >>> space_errors(GymEnv("Pendulum-v1"), "Pendulum-v1")
        []
        >>> print(space_errors(GymEnv("CartPole-v1"), "CartPole-v1")[0])  # doctest: +ELLIPSIS
        environment 'CartPole-v1' has a discrete action space (OneHot ...); the planners need ...
    """
    errors = []
    batch = len(env.batch_size)
    obs_spec = env.observation_spec
    obs = obs_spec.get("observation", None) if "observation" in obs_spec.keys() else None
    if obs is None or len(obs.shape) - batch != 1 or not obs.dtype.is_floating_point:
        found = {str(k): list(obs_spec[k].shape[batch:]) for k in obs_spec.keys(True, True)}
        errors.append(
            f"environment {name!r} has observations {found}; the world model needs one flat "
            "float vector (a gymnasium Box) under 'observation': wrap the env in "
            "gymnasium.wrappers.FlattenObservation and register that (docs/custom_env.md)"
        )
    action = env.action_spec
    domain = getattr(action, "domain", "continuous")
    if domain != "continuous" or len(action.shape) - batch != 1:
        errors.append(
            f"environment {name!r} has a {domain} action space ({type(action).__name__} of "
            f"shape {list(action.shape[batch:])}); the planners need a bounded continuous "
            "vector of floats (a gymnasium Box with finite low and high)"
        )
    elif not (
        hasattr(action.space, "low")
        and torch.isfinite(action.space.low).all()
        and torch.isfinite(action.space.high).all()
    ):
        errors.append(
            f"environment {name!r} has unbounded actions; the planners sample within finite "
            "bounds: give the Box finite low and high (e.g. gymnasium.wrappers.ClipAction)"
        )
    return errors
