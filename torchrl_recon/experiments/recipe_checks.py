"""Value checks of a merged recipe: names, ranges, finite numbers and env keywords.

:func:`recipe_errors` is what :func:`torchrl_recon.experiments.recipe.validate` runs after the
schema merge (which has already checked keys and types). Each check adds one message naming
the key, the value and what was expected; nothing here builds an env or touches the disk
(beyond reading an outcome recipe of a calibration run).
"""

from __future__ import annotations

import inspect
import math
import re
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from torchrl_recon.data.step_sampler import WINDOW_SAMPLINGS
from torchrl_recon.devices import check_device
from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments.context import RecipeLoader

if TYPE_CHECKING:
    from torchrl_recon.experiments.experiment_type import ExperimentType

PLANNER_KINDS = ("shooting", "cem", "gradient")
BAND_KINDS = ("absolute", "quantile", "mean_ratio")
LOGGER_BACKENDS = ("wandb", "csv", "none")
LOGGER_MODES = ("offline", "online")
REPLAN_MODES = ("every_step", "every_n", "uncertainty")
THRESHOLD_ON = ("step", "cumulative")
VALIDATION_POLICIES = ("random", "offset_noise")
WORLD_MODEL_MODES = ("multi_step", "one_step")
NAME_PATTERN = re.compile(r"[A-Za-z0-9_.-]+")
"""Setting and estimator names: they name stage records and folders of the run directory."""


class _Errors(list):
    """The messages of one recipe, with helpers that skip values already refused as non-finite."""

    def need(self, key: str, value: Any, ok: bool, expected: str) -> None:
        if isinstance(value, float) and not math.isfinite(value):
            return  # reported once, by the finite-number check
        if not ok:
            self.append(f"'{key}' must be {expected}, got {value!r}")

    def at_least(self, cfg: DictConfig, keys: tuple[str, ...], low: int) -> None:
        for key in keys:
            value = OmegaConf.select(cfg, key)
            self.need(key, value, value >= low, f">= {low}")

    def one_of(self, cfg: DictConfig, key: str, choices: tuple[str, ...]) -> None:
        value = OmegaConf.select(cfg, key)
        self.need(key, value, value in choices, f"one of {list(choices)}")


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
        >>> recipe_errors(cfg, get_type("explore"))
        []
        >>> cfg.guided.ratio = float("nan")
        >>> cfg.training.val_fraction = 1.0
        >>> recipe_errors(cfg, get_type("explore"))
        ["'guided.ratio' must be a finite number, got nan", "'training.val_fraction' must be in (0, 1), got 1.0"]
    """
    errors = _Errors()
    env_defaults = _env_errors(cfg, errors)
    _finite_errors(OmegaConf.to_container(cfg, resolve=True), "", errors, env_defaults)
    _run_errors(cfg, errors)
    experiment.check(cfg, errors, recipes)
    if cfg.stop_after is not None and not experiment.is_stage(cfg, cfg.stop_after):
        errors.append(
            f"'stop_after': {cfg.stop_after!r} is not a stage of {cfg.experiment}; stages: "
            + ", ".join(experiment.stage_list(cfg))
        )
    return list(errors)


# ----------------------------------------------------------------------------------------------
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
    shipped = ENVS.get(entry.name)
    if shipped is not None and shipped.gym_id == entry.gym_id:
        if env.state_names and len(env.state_names) != len(shipped.state_names):
            errors.append(
                f"'env.state_names' must name the {len(shipped.state_names)} observation dims "
                f"of {entry.name!r}, got {len(env.state_names)} names"
            )
    elif len(errors) == before:
        _gym_env_errors(entry.gym_id, kwargs, cost, list(env.state_names), errors)
    return defaults


def _gym_env_errors(
    gym_id: str, kwargs: dict, cost: Any, state_names: list[str], errors: _Errors
) -> None:
    """Build a gymnasium env once (no step): its constructor takes ``kwargs``, its observation
    is a flat Box, its action a bounded float Box, ``state_names`` fit and ``cost`` runs."""
    import gymnasium as gym
    import numpy as np
    import torch

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
    if cost is None:
        return
    obs = torch.zeros(2, 3, n_obs)
    mid = torch.as_tensor((act_space.low + act_space.high) / 2, dtype=torch.float32)
    shapes = f"cost(obs [2, 3, {n_obs}], action [2, 3, {n_act}], next_obs [2, 3, {n_obs}])"
    try:
        out = cost(obs, mid.expand(2, 3, n_act), obs)
    except Exception as e:
        errors.append(f"'env.cost': {shapes} failed: {e!r}")
        return
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != (2, 3):
        got = list(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        errors.append(
            f"'env.cost': {shapes} must return one cost per step, a tensor [2, 3], got {got}"
        )


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
# Keys every experiment has


def _fit_errors(cfg: DictConfig, key: str, errors: _Errors) -> None:
    errors.at_least(cfg, (f"{key}.steps", f"{key}.eval_every", f"{key}.patience"), 1)
    lr = OmegaConf.select(cfg, f"{key}.lr")
    errors.need(f"{key}.lr", lr, lr > 0, "> 0")


def _run_errors(cfg: DictConfig, errors: _Errors) -> None:
    errors.need("output_dir", cfg.output_dir, bool(str(cfg.output_dir).strip()), "a directory")
    errors.at_least(cfg, ("env.episode_steps",), 1)
    errors.one_of(cfg, "logger.backend", LOGGER_BACKENDS)
    errors.one_of(cfg, "logger.mode", LOGGER_MODES)
    try:
        check_device(cfg.device)
    except ValueError as e:
        errors.append(f"'device': {e}")
    errors.at_least(
        cfg, ("threads", "num_envs", "models.window", "models.world_model.hidden_size"), 1
    )
    errors.at_least(cfg, ("models.world_model.dense_size", "models.uncertainty.hidden_size"), 1)
    errors.extend(_world_model_errors(cfg))
    errors.extend(
        _estimator_errors(cfg.models.uncertainty, "models.uncertainty", cfg.models.window)
    )
    t = cfg.training
    errors.one_of(cfg, "training.world_model_mode", WORLD_MODEL_MODES)
    errors.one_of(cfg, "training.window_sampling", WINDOW_SAMPLINGS)
    errors.at_least(cfg, ("training.slice_len", "training.num_slices"), 1)
    errors.need("training.val_fraction", t.val_fraction, 0 < t.val_fraction < 1, "in (0, 1)")
    multi = t.world_model_mode == "multi_step"
    errors.need(
        "training.slice_len",
        t.slice_len,
        t.slice_len > cfg.models.window if multi else t.slice_len >= cfg.models.window,
        f"{'above' if multi else 'at least'} models.window = {cfg.models.window} "
        f"(the {'multi-step loss predicts after' if multi else 'estimator sees'} a full window)",
    )
    _fit_errors(cfg, "training.world_model", errors)
    _fit_errors(cfg, "training.uncertainty", errors)


def _world_model_errors(cfg: DictConfig) -> list[str]:
    """Build the world model with tiny dims so that a bad activation fails before any work."""
    from torchrl_recon.experiments.common import build_world_model

    m = cfg.models
    if min(m.window, m.world_model.hidden_size, m.world_model.dense_size) < 1:
        return []  # reported by the range checks
    try:
        build_world_model(cfg, 1, 1)
    except (ValueError, TypeError) as e:
        return [f"'models.world_model': {e}"]
    return []


def _estimator_errors(spec: DictConfig, key: str, window: int) -> list[str]:
    """Build the estimator a block names (tiny dims) so a bad kind or keyword fails before any work."""
    from torchrl_recon.experiments.common import build_estimator

    if window < 1 or spec.hidden_size < 1:
        return []  # reported by the range checks
    try:
        build_estimator(spec, 1, 1, window)
    except (ValueError, TypeError) as e:
        return [f"'{key}': {e}"]
    return []


def _planner_errors(planner: DictConfig, key: str, errors: _Errors) -> None:
    errors.need(
        f"{key}.kind", planner.kind, planner.kind in PLANNER_KINDS, f"one of {list(PLANNER_KINDS)}"
    )
    for name in (
        "horizon",
        "num_candidates",
        "iterations",
        "num_elites",
        "restarts",
        "gradient_steps",
    ):
        errors.need(f"{key}.{name}", planner[name], planner[name] >= 1, ">= 1")
    errors.need(f"{key}.lr", planner.lr, planner.lr > 0, "> 0")
    if planner.kind == "cem":
        errors.need(
            f"{key}.num_elites",
            planner.num_elites,
            planner.num_elites <= planner.num_candidates,
            f"at most num_candidates = {planner.num_candidates}",
        )


def _name_errors(names: list[str], key: str, what: str, errors: _Errors) -> None:
    for i, name in enumerate(names):
        errors.need(
            f"{key}[{i}].name",
            name,
            bool(NAME_PATTERN.fullmatch(name)),
            "a name of letters, digits, '_', '.' or '-' (it names files of the run directory)",
        )
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
    errors.at_least(cfg, ("random_steps", "retrainings"), 1)
    if cfg.get("retrainings_per_fit") is not None:
        errors.at_least(cfg, ("retrainings_per_fit",), 1)
    errors.at_least(cfg, ("validation.trajectories", "validation.steps"), 1)
    errors.one_of(cfg, "validation.policy", VALIDATION_POLICIES)
    _data_errors(
        errors,
        frames_key="initial_random_steps",
        frames=cfg.initial_random_steps,
        episode_key="env.episode_steps",
        episode=cfg.env.episode_steps,
        slice_len=cfg.training.slice_len,
    )
    g = cfg.guided
    errors.at_least(cfg, ("guided.steps", "guided.refit_every_episodes"), 1)
    errors.need(
        "guided.ratio", g.ratio, g.ratio > 1, "above 1 (the threshold is ratio × the mean Σu)"
    )
    if g.cap is not None:
        errors.need("guided.cap", g.cap, g.cap > g.ratio, f"null or above guided.ratio = {g.ratio}")
    errors.need("guided.beta", g.beta, g.beta <= 0, "<= 0 (exploration seeks uncertainty)")
    if g.planner.kind == "gradient":
        errors.need(
            "guided.beta",
            g.beta,
            g.beta < 0,
            "< 0 with the gradient planner (with beta 0 the objective is constant: no gradient)",
        )
    _planner_errors(g.planner, "guided.planner", errors)


def control_errors(cfg: DictConfig, errors: _Errors) -> None:
    """The control recipe's own checks."""
    errors.at_least(cfg, ("random_episode_steps", "episodes", "replan.every"), 1)
    errors.at_least(cfg, ("random_episodes",), 2)
    errors.at_least(cfg, ("warmup_random_steps",), 0)
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
    r = cfg.replan
    errors.one_of(cfg, "replan.mode", REPLAN_MODES)
    errors.one_of(cfg, "replan.threshold_on", THRESHOLD_ON)
    q = r.threshold_quantile
    errors.need("replan.threshold_quantile", q, 0 < q <= 1, "in (0, 1]")
    errors.need("replan.threshold_scale", r.threshold_scale, r.threshold_scale > 0, "> 0")
    if r.error_threshold is not None:
        errors.need(
            "replan.error_threshold",
            r.error_threshold,
            r.error_threshold > 0,
            "a positive finite number or null",
        )
    if not cfg.settings:
        errors.append("'settings' is empty: a control recipe needs at least one setting")
    _name_errors([s.name for s in cfg.settings], "settings", "setting", errors)
    for i, setting in enumerate(cfg.settings):
        key = f"settings[{i}]"
        _planner_errors(setting.planner, f"{key}.planner", errors)
        errors.need(
            f"{key}.alpha", setting.alpha, setting.alpha >= 0, ">= 0 (the weight of reward)"
        )
        if setting.band is not None:
            _band_errors(setting.band, f"{key}.band", errors)


def _band_errors(band: DictConfig, key: str, errors: _Errors) -> None:
    from torchrl_recon.planners.objective import UncertaintyBand

    if band.kind not in BAND_KINDS:
        errors.append(f"'{key}.kind' must be one of {list(BAND_KINDS)}, got {band.kind!r}")
        return
    if any(v is not None and not math.isfinite(v) for v in (band.low, band.high)):
        return  # reported by the finite-number check
    try:
        UncertaintyBand(low=band.low, high=band.high, kind=band.kind)
    except ValueError as e:
        errors.append(f"'{key}': {e}")


def calibrate_errors(cfg: DictConfig, errors: _Errors, recipes: RecipeLoader | None) -> None:
    """The estimator comparison recipe's own checks; its outcome recipes are loaded (and so
    checked) with ``recipes`` when given."""
    if not cfg.estimators:
        errors.append("'estimators' is empty: a calibrate recipe needs at least one estimator")
    _name_errors([s.name for s in cfg.estimators], "estimators", "estimator", errors)
    for i, spec in enumerate(cfg.estimators):
        errors.need(f"estimators[{i}].hidden_size", spec.hidden_size, spec.hidden_size >= 1, ">= 1")
        errors.extend(_estimator_errors(spec, f"estimators[{i}]", cfg.models.window))
    errors.one_of(cfg, "evaluation.policy", VALIDATION_POLICIES)
    errors.at_least(
        cfg,
        (
            "evaluation.trajectories",
            "evaluation.horizon",
            "evaluation.ood_windows",
            "timing.candidates",
            "timing.repeats",
            "timing.iterations",
            "timing.num_elites",
            "random_steps",
            "random_episode_steps",
        ),
        1,
    )
    shift = cfg.evaluation.ood_state_shift
    errors.need("evaluation.ood_state_shift", shift, shift > 0, "> 0 (standard deviations)")
    if not cfg.timing.horizons or min(cfg.timing.horizons) < 1:
        errors.append(
            f"'timing.horizons' must be a non-empty list of ints >= 1, got {list(cfg.timing.horizons)}"
        )
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
