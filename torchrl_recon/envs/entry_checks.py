"""The checks of an env a recipe names, before any work: its keywords, its cost and termination
functions, its state names, and (for a gymnasium env that is not shipped) its spaces."""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from torchrl_recon.envs.dmc import DMCEntry, dmc_errors, task_dims
from torchrl_recon.envs.registry import ENVS, LEARNED, EnvEntry, import_cost


def entry_errors(
    entry: EnvEntry,
    kwargs: dict[str, Any],
    *,
    termination: str | None = None,
    state_names: Sequence[str] = (),
    key: str = "env",
) -> list[str]:
    """Every problem of ``entry`` built with ``kwargs``, one line each naming the key of the
    recipe's env section ``key`` (empty when there is none): keywords the env takes, of its
    defaults' types; a cost that imports (``entry.cost_fn_path``); a ``termination`` that
    imports; ``state_names`` one per observation dim. A gymnasium env that is not shipped is
    built once (not stepped) to check its spaces and a call of the cost and termination.

    Examples:
        >>> from torchrl_recon.envs import get_entry
        >>> entry_errors(get_entry("drone"), {"delta": 0.1})
        []
        >>> entry_errors(get_entry("drone"), {"delta": "big"}, state_names=["x"])  # doctest: +NORMALIZE_WHITESPACE
        ["'env.kwargs.delta' must be a number (DroneEnv's default is 0.05), got 'big'",
        "'env.state_names' must name the 12 observation dims of 'drone', got 1 names"]
    """
    try:
        entry.check_kwargs(kwargs)
    except TypeError as e:
        return [f"'{key}.kwargs': {e} Fix the keyword, or drop it when changing the env."]
    errors = []
    defaults = entry.keywords() or {}
    cls = entry.env_class().__name__
    for name, value in kwargs.items():
        expected = _expected_like(defaults.get(name), value)
        if expected:
            errors.append(
                f"'{key}.kwargs.{name}' must be {expected} ({cls}'s default is "
                f"{defaults[name]!r}), got {value!r}"
            )
    cost = term = None
    before = len(errors)  # a keyword of the wrong type still lets the env be built
    if entry.cost_fn_path == LEARNED:
        pass  # learned from the data's rewards: nothing to import
    elif not entry.cost_fn_path:
        errors.append(
            f"'{key}.cost': environment {entry.gym_id!r} has no torch cost; give "
            f"{key}.cost=module:function, a batched torch cost(obs, action, next_obs) -> [...] "
            f"in a module on PYTHONPATH (e.g. {key}.cost=my_costs:pendulum; see docs/custom_env.md), "
            f"or {key}.cost=learned (the env's reward, learned from the data)"
        )
    else:
        try:
            import_cost(entry.cost_fn_path)
            cost = entry.cost_fn_with(kwargs)
        except ValueError as e:
            errors.append(f"'{key}.cost': {e}")
    if termination is not None and termination != LEARNED:
        try:
            term = import_cost(termination, what="termination")
        except ValueError as e:
            errors.append(f"'{key}.termination': {e}")
    shipped = ENVS.get(entry.name)
    if shipped is not None and shipped.gym_id == entry.gym_id:
        if state_names and len(state_names) != len(shipped.state_names):
            errors.append(
                f"'{key}.state_names' must name the {len(shipped.state_names)} observation dims "
                f"of {entry.name!r}, got {len(state_names)} names"
            )
    elif len(errors) == before and isinstance(entry, DMCEntry):
        names, n_act = task_dims(entry.domain, entry.task)
        errors += dmc_errors(entry, kwargs, state_names, key)
        errors += _step_fn_errors(cost, term, len(names), n_act, key)
    elif len(errors) == before:
        errors += _gym_errors(entry.gym_id, kwargs, cost, term, state_names, key)
    return errors


def _gym_errors(
    gym_id: str, kwargs: dict, cost: Any, termination: Any, state_names: Sequence[str], key: str
) -> list[str]:
    """Build a gymnasium env once (no step): its constructor takes ``kwargs``, its observation
    is a flat Box, its action a bounded float Box, ``state_names`` fit, and ``cost`` and
    ``termination`` return one value per step."""
    try:
        made = gym.make(gym_id, disable_env_checker=True, **kwargs)
    except Exception as e:  # the user's constructor: any error is theirs to fix
        return [f"'{key}.kwargs': building {gym_id!r} with {kwargs} failed: {e!r}"]
    try:
        obs_space, act_space = made.observation_space, made.action_space
    finally:
        made.close()
    box = gym.spaces.Box
    if not (isinstance(obs_space, box) and len(obs_space.shape) == 1):
        return [
            f"'{key}.id': {gym_id!r} has observation space {obs_space}; the world model needs a "
            "flat Box (wrap the env, e.g. gymnasium.wrappers.FlattenObservation, and register that)"
        ]
    if not (
        isinstance(act_space, box)
        and len(act_space.shape) == 1
        and np.issubdtype(act_space.dtype, np.floating)
        and np.isfinite(act_space.low).all()
        and np.isfinite(act_space.high).all()
    ):
        return [
            f"'{key}.id': {gym_id!r} has action space {act_space}; the planners need a flat Box "
            "of floats with finite bounds"
        ]
    errors = []
    n_obs, n_act = obs_space.shape[0], act_space.shape[0]
    if state_names and len(state_names) != n_obs:
        errors.append(
            f"'{key}.state_names' must name the {n_obs} observation dims of {gym_id!r}, got "
            f"{len(state_names)} names"
        )
    return errors + _step_fn_errors(cost, termination, n_obs, n_act, key)


def _step_fn_errors(cost: Any, termination: Any, n_obs: int, n_act: int, key: str) -> list[str]:
    """``cost`` and ``termination`` (where given) called on zeros of the env's sizes: one line
    each that does not return one value per step (``check_step_fn``)."""
    from torchrl_recon.planners.planning_model import check_step_fn

    errors = []
    for name, fn, boolean in (("cost", cost, False), ("termination", termination, True)):
        try:
            if fn is not None:
                check_step_fn(name, fn, n_obs, n_act, boolean=boolean)
        except ValueError as e:
            errors.append(f"'{key}.{name}': {e}")
    return errors


def _expected_like(default: Any, value: Any) -> str | None:
    """What ``value`` should be to take the place of ``default`` (None when it fits)."""

    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    if default is None or default is inspect.Parameter.empty:
        return None
    if isinstance(default, bool):
        return None if isinstance(value, bool) else "true or false"
    if isinstance(default, int):
        return None if isinstance(value, int) and not isinstance(value, bool) else "an integer"
    if isinstance(default, float):
        return None if number(value) else "a number"
    if isinstance(default, str):
        return None if isinstance(value, str) else "a string"
    if isinstance(default, (tuple, list)):
        ok = isinstance(value, (tuple, list)) and len(value) == len(default)
        if ok and all(number(d) for d in default):
            ok = all(number(v) for v in value)
        return None if ok else f"a list of {len(default)} like the default"
    return None
