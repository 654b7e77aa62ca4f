"""The checks of a merged recipe that span several keys or need the env or a registry.

:func:`recipe_errors` is what :func:`torchrl_recon.experiments.recipe.validate` runs after the
schema merge (which has already checked keys, types and choices). The per-field ranges and
finiteness are declared on the schema's fields (:mod:`.config`, run by
:func:`~.field_checks.schema_errors`); here: the env section (the env known, its keywords, its
cost), the planner and estimator classes a recipe names (``kind``: shipped or
``module:Class``; ``kwargs`` against the class's signature; built on a tiny model), data sizes
against ``training.slice_len``, unique names, ``stop_after`` and a calibration's outcome
recipes. Each problem is one message naming the key, the value and what was expected; nothing
here touches the disk (beyond reading an outcome recipe of a calibration run).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments.context import RecipeLoader
from torchrl_recon.experiments.field_checks import finite, schema_errors

if TYPE_CHECKING:
    from torchrl_recon.experiments.experiment_type import ExperimentType
    from torchrl_recon.planners import Objective, PlanningModel


class _Errors(list):
    """The messages of one recipe."""

    def need(self, key: str, value: Any, ok: bool, expected: str) -> None:
        """Add ``'key' must be <expected>, got <value>`` unless ``ok`` (or the value is a
        non-finite number: the schema walk reports it)."""
        if finite(value) and not ok:
            self.append(f"'{key}' must be {expected}, got {value!r}")


def recipe_errors(
    cfg: DictConfig, experiment: ExperimentType, recipes: RecipeLoader | None = None
) -> list[str]:
    """Every problem of a merged, resolved recipe of ``experiment``, one message each (empty
    when it is valid). ``recipes`` loads the recipes a kind runs (checked only when given).

    Examples:
        >>> from torchrl_recon.experiments.config import ExploreConfig
        >>> from torchrl_recon.experiments.registry import get_type
        >>> cfg = OmegaConf.structured(ExploreConfig(output_dir="out"))
        >>> cfg.env.name = "drone"
        >>> cfg.guided.planner.kwargs = {"horizon": 10}
        >>> recipe_errors(cfg, get_type("explore"))
        []
        >>> cfg.guided.ratio = float("nan")
        >>> cfg.training.val_fraction = 1.0
        >>> cfg.guided.planner.kwargs.num_elites = 4
        >>> recipe_errors(cfg, get_type("explore"))  # doctest: +NORMALIZE_WHITESPACE
        ["'training.val_fraction' must be in (0, 1), got 1.0", "'guided.ratio' must be a finite
        number, got nan", "'guided.planner.kwargs': RandomShootingPlanner does not accept
        ['num_elites']; it accepts ['block_rows', 'horizon', 'num_candidates', 'on_infeasible']."]
    """
    errors = _Errors()
    env_defaults = _env_errors(cfg, errors)
    _finite_errors(
        OmegaConf.to_container(cfg.env.kwargs, resolve=True), "env.kwargs", errors, env_defaults
    )
    errors.extend(schema_errors(cfg))
    _run_errors(cfg, errors)
    experiment.check(cfg, errors, recipes)
    if cfg.stop_after is not None and not experiment.is_stage(cfg, cfg.stop_after):
        errors.append(
            f"'stop_after': {cfg.stop_after!r} is not a stage of {cfg.experiment}; stages: "
            + ", ".join(experiment.stage_list(cfg))
        )
    return list(errors)


# Every number finite; env keywords the env takes


def _finite_errors(node: Any, key: str, errors: _Errors, env_defaults: dict[str, Any]) -> None:
    """Refuse NaN and ±inf at any depth (list items too); an env keyword whose own default is
    infinite (e.g. Minitaur's ``distance_limit``) may be infinite."""
    if isinstance(node, dict):
        for k, v in node.items():
            _finite_errors(v, f"{key}.{k}" if key else str(k), errors, env_defaults)
    elif isinstance(node, list):
        for i, v in enumerate(node):
            _finite_errors(v, f"{key}[{i}]", errors, env_defaults)
    elif isinstance(node, float) and not math.isfinite(node):
        default = (
            env_defaults.get(key.removeprefix("env.kwargs."))
            if key.startswith("env.kwargs.")
            else None
        )
        if math.isnan(node) or not (isinstance(default, float) and default == node):
            errors.append(f"'{key}' must be a finite number, got {node}")


def _env_errors(cfg: DictConfig, errors: _Errors) -> dict[str, Any]:
    """The env section: ``env.id`` / ``env.name`` known, ``env.kwargs`` keywords of that env of
    its defaults' types, a cost (``env.cost`` or the registered env's) that imports, and
    ``env.state_names`` one per observation dim. A gymnasium env that is not shipped is built
    once (not stepped) to check its spaces, its keywords and a call of the cost.

    Returns the env's keyword defaults ({} when unknown).
    """
    from torchrl_recon.envs import ENVS, import_cost
    from torchrl_recon.experiments.common import env_entry

    env = cfg.env
    if env.id is None and env.name is None:
        errors.append(
            "'env': no environment given; give env.id (a gymnasium id such as Pendulum-v1, or "
            "my_module:MyEnv-v0) with env.cost=module:function, or env.name (one of "
            f"{sorted(ENVS)})"
        )
        return {}
    try:
        entry = env_entry(cfg)
    except ValueError as e:
        errors.append(f"'{'env.id' if env.id else 'env.name'}': {e}")
        return {}
    if env.id and env.name in ENVS and ENVS[env.name].gym_id != entry.gym_id:
        errors.append(
            f"'env.name': {env.name!r} names a shipped env, but env.id is {env.id!r}; give "
            f"env.name=<your env's name> too, or start from recipes/gym"
        )
        return {}
    kwargs = OmegaConf.to_container(env.kwargs, resolve=True)
    try:
        entry.check_kwargs(kwargs)
    except TypeError as e:
        errors.append(f"'env.kwargs': {e} Fix the keyword, or drop it when changing the env.")
        return {}
    defaults = entry.keywords() or {}
    cls = entry.env_class().__name__
    for name, value in kwargs.items():
        expected = _expected_like(defaults.get(name), value)
        if expected:
            errors.append(
                f"'env.kwargs.{name}' must be {expected} ({cls}'s default is "
                f"{defaults[name]!r}), got {value!r}"
            )
    cost, before = None, len(errors)
    if not entry.cost_fn_path:
        errors.append(
            f"'env.cost': environment {entry.gym_id!r} has no torch cost; give "
            "env.cost=module:function, a batched torch cost(obs, action, next_obs) -> [...] "
            "in a module on PYTHONPATH (e.g. env.cost=my_costs:pendulum; see docs/custom_env.md)"
        )
    else:
        try:
            import_cost(entry.cost_fn_path)
            cost = entry.cost_fn_with(kwargs)
        except ValueError as e:
            errors.append(f"'env.cost': {e}")
    termination = None
    if env.get("termination") is not None:
        try:
            termination = import_cost(env.termination, what="termination")
        except ValueError as e:
            errors.append(f"'env.termination': {e}")
    shipped = ENVS.get(entry.name)
    if shipped is not None and shipped.gym_id == entry.gym_id:
        if env.state_names and len(env.state_names) != len(shipped.state_names):
            errors.append(
                f"'env.state_names' must name the {len(shipped.state_names)} observation dims "
                f"of {entry.name!r}, got {len(env.state_names)} names"
            )
    elif len(errors) == before:
        _gym_env_errors(entry.gym_id, kwargs, cost, termination, list(env.state_names), errors)
    return defaults


def _gym_env_errors(
    gym_id: str,
    kwargs: dict,
    cost: Any,
    termination: Any,
    state_names: list[str],
    errors: _Errors,
) -> None:
    """Build a gymnasium env once (no step): its constructor takes ``kwargs``, its observation
    is a flat Box, its action a bounded float Box, ``state_names`` fit, and ``cost`` and
    ``termination`` return one value per step."""
    import gymnasium as gym
    import numpy as np

    try:
        made = gym.make(gym_id, disable_env_checker=True, **kwargs)
    except Exception as e:  # the user's constructor: any error is theirs to fix
        errors.append(f"'env.kwargs': building {gym_id!r} with {kwargs} failed: {e!r}")
        return
    try:
        obs_space, act_space = made.observation_space, made.action_space
    finally:
        made.close()
    box = gym.spaces.Box
    if not (isinstance(obs_space, box) and len(obs_space.shape) == 1):
        errors.append(
            f"'env.id': {gym_id!r} has observation space {obs_space}; the world model needs a "
            "flat Box (wrap the env, e.g. gymnasium.wrappers.FlattenObservation, and register that)"
        )
        return
    if not (
        isinstance(act_space, box)
        and len(act_space.shape) == 1
        and np.issubdtype(act_space.dtype, np.floating)
        and np.isfinite(act_space.low).all()
        and np.isfinite(act_space.high).all()
    ):
        errors.append(
            f"'env.id': {gym_id!r} has action space {act_space}; the planners need a flat Box "
            "of floats with finite bounds"
        )
        return
    n_obs, n_act = obs_space.shape[0], act_space.shape[0]
    if state_names and len(state_names) != n_obs:
        errors.append(
            f"'env.state_names' must name the {n_obs} observation dims of {gym_id!r}, got "
            f"{len(state_names)} names"
        )
    from torchrl_recon.planners import check_step_fn

    for key, fn, boolean in (("cost", cost, False), ("termination", termination, True)):
        if fn is None:
            continue
        try:
            check_step_fn(key, fn, n_obs, n_act, boolean=boolean)
        except ValueError as e:
            errors.append(f"'env.{key}': {e}")


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


# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# Keys every experiment has


def _run_errors(cfg: DictConfig, errors: _Errors) -> None:
    t = cfg.training
    multi = t.world_model_mode == "multi_step"
    if cfg.models.window >= 1:
        errors.need(
            "training.slice_len",
            t.slice_len,
            t.slice_len > cfg.models.window if multi else t.slice_len >= cfg.models.window,
            f"{'above' if multi else 'at least'} models.window = {cfg.models.window} "
            f"(the {'multi-step loss predicts after' if multi else 'estimator sees'} a full "
            "window)",
        )
    errors.extend(_world_model_errors(cfg))
    errors.extend(
        _estimator_errors(cfg.models.uncertainty, "models.uncertainty", cfg.models.window)
    )


def _world_model_errors(cfg: DictConfig) -> list[str]:
    """Build the world model with tiny dims so that a bad activation fails before any work."""
    from torchrl_recon.experiments.common import build_world_model

    m = cfg.models
    if min(m.window, m.world_model.hidden_size, m.world_model.dense_size) < 1:
        return []  # reported by the schema's checks
    try:
        build_world_model(cfg, 1, 1)
    except (ValueError, TypeError) as e:
        return [f"'models.world_model': {e}"]
    return []


# ----------------------------------------------------------------------------------------------
# The parts a recipe names: shipped or a user's own class, with that class's keywords


def _kwargs_key(key: str, message: str, kwargs: dict[str, Any]) -> str:
    """``<key>.kwargs.<name>`` when the message starts with one of the keywords, else ``key``."""
    first = message.split(" ", 1)[0]
    return f"{key}.kwargs.{first}" if first in kwargs else key


def _estimator_errors(spec: DictConfig, key: str, window: int) -> list[str]:
    """The estimator block's class (``kind``), its keywords against the class's signature,
    then the estimator built with tiny dims, so that a bad value fails before any work."""
    from torchrl_recon.experiments.common import build_estimator
    from torchrl_recon.modules import get_estimator_class
    from torchrl_recon.plugins import check_keywords

    try:
        cls = get_estimator_class(spec.kind)
    except ValueError as e:
        return [f"'{key}.kind': {e}"]
    kwargs = OmegaConf.to_container(spec.kwargs, resolve=True)
    try:
        check_keywords(
            cls,
            kwargs,
            positional=2,
            keywords=("window", "hidden_size", "activation"),
            given_by=f"models.window, {key}.hidden_size and {key}.activation",
        )
    except TypeError as e:
        return [f"'{key}.kwargs': {e}"]
    if window < 1 or spec.hidden_size < 1 or not _all_finite(kwargs):
        return []  # reported by the schema's checks
    try:
        build_estimator(spec, 1, 1, window)
    except Exception as e:  # a user's class: any error is theirs to fix
        return [f"'{_kwargs_key(key, str(e), kwargs)}': {e}"]
    return []


def _planner_errors(
    planner: DictConfig,
    key: str,
    window: int,
    objective: Callable[[], Objective],
    with_objective: str,
) -> list[str]:
    """The planner block's class (``kind``), its keywords against the class's signature, then
    the planner built on a tiny model with the recipe's objective (``objective()``; described
    by ``with_objective`` in a message), so that a bad value fails before any work."""
    from torchrl_recon.planners import check_planner_kwargs, get_planner_class

    try:
        cls = get_planner_class(planner.kind)
    except ValueError as e:
        return [f"'{key}.kind': {e}"]
    kwargs = OmegaConf.to_container(planner.kwargs, resolve=True)
    try:
        check_planner_kwargs(cls, kwargs)
    except TypeError as e:
        return [f"'{key}.kwargs': {e}"]
    if window < 1 or not _all_finite(kwargs):
        return []  # reported by the schema's checks
    try:
        goal = objective()
    except ValueError:
        return []  # the objective's values are reported by the schema's checks
    try:
        with torch.random.fork_rng(devices=[]):  # the run's random numbers stay as they are
            cls(_tiny_planning_model(window), goal, **kwargs)
    except Exception as e:  # a user's class: any error is theirs to fix
        where = _kwargs_key(key, str(e), kwargs)
        return [f"'{where}'{'' if where != key else f' ({with_objective})'}: {e}"]
    return []


def _tiny_planning_model(window: int) -> PlanningModel:
    """A planning model of one state and one action dim, with an estimator, on the CPU."""
    from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
    from torchrl_recon.planners import PlanningModel

    world = LSTMWorldModel(1, 1, window=window, hidden_size=1, dense_size=1)
    u = ReconstructionUncertainty(1, 1, window=window, hidden_size=1)
    return PlanningModel(world, lambda obs, action, next_obs: obs[..., 0], uncertainty=u)


def _all_finite(node: Any) -> bool:
    if isinstance(node, dict):
        return all(_all_finite(v) for v in node.values())
    if isinstance(node, list):
        return all(_all_finite(v) for v in node)
    return finite(node)


# ----------------------------------------------------------------------------------------------
# Names and data sizes


def _duplicate_errors(names: list[str], key: str, what: str, errors: _Errors) -> None:
    for name in sorted({n for n in names if names.count(n) > 1}):
        errors.append(f"'{key}': duplicate {what} name {name!r}")


def _data_errors(
    errors: _Errors,
    *,
    episode_key: str,
    episode: int,
    slice_len: int,
    frames_key: str | None = None,
    frames: int = 0,
) -> None:
    """Random data in episodes of ``episode`` steps must hold a training slice per episode and,
    with ``frames`` steps in all, at least two trajectories (one is held out to validate a fit)."""
    errors.need(
        episode_key,
        episode,
        episode >= slice_len,
        f"at least training.slice_len = {slice_len} (a training slice never crosses an episode)",
    )
    if frames_key is not None:
        errors.need(
            frames_key,
            frames,
            frames >= episode + slice_len,
            f"at least {episode_key} + training.slice_len = {episode + slice_len} (two "
            "trajectories: one is held out to validate the fit)",
        )


# ----------------------------------------------------------------------------------------------
# Per experiment


def explore_errors(cfg: DictConfig, errors: _Errors) -> None:
    """The explore recipe's own checks."""
    from torchrl_recon.policies import exploration_objective

    _data_errors(
        errors,
        frames_key="initial_random_steps",
        frames=cfg.initial_random_steps,
        episode_key="env.episode_steps",
        episode=cfg.env.episode_steps,
        slice_len=cfg.training.slice_len,
    )
    g = cfg.guided
    errors.extend(
        _planner_errors(
            g.planner,
            "guided.planner",
            cfg.models.window,
            lambda: exploration_objective(ratio=g.ratio, cap=g.cap, beta=g.beta),
            f"with the exploration objective: alpha 0, guided.beta = {g.beta}",
        )
    )


def control_errors(cfg: DictConfig, errors: _Errors) -> None:
    """The control recipe's own checks."""
    from torchrl_recon.experiments.control_stages import setting_objective

    # two episodes at least (random_episodes >= 2): one is held out to validate the fit
    _data_errors(
        errors,
        episode_key="random_episode_steps",
        episode=cfg.random_episode_steps,
        slice_len=cfg.training.slice_len,
    )
    warmup = max(cfg.warmup_random_steps, cfg.models.window)
    errors.need(
        "env.episode_steps",
        cfg.env.episode_steps,
        cfg.env.episode_steps > warmup,
        f"above max(warmup_random_steps, models.window) = {warmup} (or no step is planned)",
    )
    _duplicate_errors([s.name for s in cfg.settings], "settings", "setting", errors)
    for i, setting in enumerate(cfg.settings):
        errors.extend(
            _planner_errors(
                setting.planner,
                f"settings[{i}].planner",
                cfg.models.window,
                lambda setting=setting: setting_objective(setting, 1.0)[0],
                f"with settings[{i}].alpha = {setting.alpha}, beta = {setting.beta}",
            )
        )


def calibrate_errors(cfg: DictConfig, errors: _Errors, recipes: RecipeLoader | None) -> None:
    """The estimator comparison recipe's own checks; its outcome recipes are loaded (and so
    checked) with ``recipes`` when given."""
    _duplicate_errors([s.name for s in cfg.estimators], "estimators", "estimator", errors)
    for i, spec in enumerate(cfg.estimators):
        errors.extend(_estimator_errors(spec, f"estimators[{i}]", cfg.models.window))
    _data_errors(
        errors,
        frames_key="random_steps",
        frames=cfg.random_steps,
        episode_key="random_episode_steps",
        episode=cfg.random_episode_steps,
        slice_len=cfg.training.slice_len,
    )
    for kind in ("explore", "control"):
        recipe = cfg.outcomes[f"{kind}_recipe"]
        if recipe is None or recipes is None:
            continue
        key = f"outcomes.{kind}_recipe"
        try:
            path = recipes.resolve(recipe)
        except FileNotFoundError as e:
            errors.append(f"'{key}': {e}")
            continue
        # The outcome run uses this recipe's window (and estimator, checked above).
        overrides = list(cfg.outcomes[f"{kind}_overrides"])
        try:
            recipes.load(path, [*overrides, f"models.window={cfg.models.window}"])
        except (RecipeError, FileNotFoundError) as e:
            errors.append(
                f"'{key}' (with outcomes.{kind}_overrides {overrides} and this recipe's "
                f"models.window = {cfg.models.window}): {e}"
            )


def online_errors(cfg: DictConfig, errors: _Errors) -> None:
    """The online recipe's own checks: random data that holds two training slices, episodes
    long enough to plan in, and the planner built with the recipe's objective."""
    from torchrl_recon.planners import Objective

    _data_errors(
        errors,
        frames_key="random_steps",
        frames=cfg.random_steps,
        episode_key="env.episode_steps",
        episode=cfg.env.episode_steps,
        slice_len=cfg.training.slice_len,
    )
    errors.extend(
        _planner_errors(
            cfg.planner,
            "planner",
            cfg.models.window,
            lambda: Objective(alpha=cfg.alpha, beta=cfg.beta),
            f"with alpha = {cfg.alpha}, beta = {cfg.beta}",
        )
    )
