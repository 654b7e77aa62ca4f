"""The checks of a merged recipe that span several keys or need the env or a registry, after the
schema's own (:func:`~.field_checks.schema_errors`), and the parts each kind's ``check`` (in its
module) is made of; one message per problem, naming the key and the value."""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_recon.experiments.context import RecipeLoader
from torchrl_recon.experiments.field_checks import finite, finite_error, nonfinite, schema_errors

if TYPE_CHECKING:
    from torchrl_recon.experiments.experiment_type import ExperimentType
    from torchrl_recon.planners import Objective


class RecipeErrors(list):
    """The messages of one recipe ``cfg`` (what a kind's ``check`` adds to)."""

    def __init__(self, cfg: DictConfig) -> None:
        super().__init__()
        self.cfg = cfg

    def need(self, key: str, ok: bool, expected: str) -> None:
        """Add ``'key' must be <expected>, got <value>`` unless ``ok`` (or the value is a
        non-finite number: the schema walk reports it)."""
        value = OmegaConf.select(self.cfg, key)
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
    errors = RecipeErrors(cfg)
    kwargs = OmegaConf.to_container(cfg.env.kwargs, resolve=True)
    defaults = _env_errors(cfg, kwargs, errors)
    for key, value in nonfinite(kwargs, "env.kwargs"):
        # an env keyword whose own default is infinite (Minitaur's distance_limit) may be so
        if math.isnan(value) or defaults.get(key.removeprefix("env.kwargs.")) != value:
            errors.append(finite_error(key, value))
    errors.extend(schema_errors(cfg))
    _run_errors(errors)
    experiment.check(cfg, errors, recipes)
    if cfg.stop_after is not None and not experiment.is_stage(cfg, cfg.stop_after):
        errors.append(
            f"'stop_after': {cfg.stop_after!r} is not a stage of {cfg.experiment}; stages: "
            + ", ".join(experiment.stage_list(cfg))
        )
    return list(errors)


def _env_errors(cfg: DictConfig, kwargs: dict[str, Any], errors: RecipeErrors) -> dict[str, Any]:
    """``env.id`` / ``env.name`` known and agreeing, then the entry's own checks. Returns the
    env's keyword defaults ({} when the env or a keyword is unknown)."""
    from torchrl_recon.envs import ENVS, LEARNED, entry_errors
    from torchrl_recon.experiments.recipe_env import env_entry

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
    names = list(env.state_names)
    for key in ("cost", "termination"):
        if env.get(key) == LEARNED and cfg.experiment != "online":
            errors.append(
                f"'env.{key}': learned is for the online kind (its fits learn the reward from "
                f"the data as it grows); the {cfg.experiment} kind needs module:function"
            )
    errors.extend(entry_errors(entry, kwargs, termination=env.termination, state_names=names))
    try:
        entry.check_kwargs(kwargs)
    except TypeError:
        return {}  # reported by entry_errors
    return entry.keywords() or {}


def _run_errors(errors: RecipeErrors) -> None:
    """Keys every experiment has: a training slice holds a window; the world model and the
    estimator build with tiny dims, so that a bad value fails before any work."""
    from torchrl_recon.experiments.recipe_models import build_world_model

    cfg = errors.cfg
    t, m = cfg.training, cfg.models
    if m.window >= 1:
        multi = t.world_model_mode == "multi_step"
        errors.need(
            "training.slice_len",
            t.slice_len > m.window if multi else t.slice_len >= m.window,
            f"{'above' if multi else 'at least'} models.window = {m.window} (the "
            f"{'multi-step loss predicts after' if multi else 'estimator sees'} a full window)",
        )
    if min(m.window, m.world_model.hidden_size, m.world_model.dense_size) >= 1:
        try:
            build_world_model(cfg, 1, 1)
        except (ValueError, TypeError) as e:
            errors.append(f"'models.world_model': {e}")
    estimator_errors(errors, "models.uncertainty", m.uncertainty)
    if cfg.get("planning_threads", 1) > 1:
        errors.need(
            "planning_compile",
            cfg.planning_compile is not False,
            "true or a torch.compile mode with planning_threads above 1 (the blocks run in "
            "parallel only as compiled calls)",
        )


def _part_errors(
    errors: RecipeErrors,
    key: str,
    get_class: Callable[[str], type],
    check_kwargs: Callable[[type, dict], None],
    build: Callable[[type, dict], Any] | None,
    note: str = "",
) -> None:
    """The block ``key``'s class (``kind``), its ``kwargs`` against the class's signature, then
    ``build(cls, kwargs)`` (None: a value the schema's checks report), so that a bad value
    fails before any work; ``note`` describes the build in a message."""
    spec = OmegaConf.select(errors.cfg, key)
    try:
        cls = get_class(spec.kind)
    except ValueError as e:
        return errors.append(f"'{key}.kind': {e}")
    kwargs = OmegaConf.to_container(spec.kwargs, resolve=True)
    try:
        check_kwargs(cls, kwargs)
    except TypeError as e:
        return errors.append(f"'{key}.kwargs': {e}")
    if build is None or nonfinite(kwargs, ""):
        return None
    try:
        build(cls, kwargs)
    except Exception as e:  # a user's class: any error is theirs to fix
        first = str(e).split(" ", 1)[0]  # a message that starts with a keyword is about it
        where = f"{key}.kwargs.{first}" if first in kwargs else key
        errors.append(f"'{where}'{note if where == key else ''}: {e}")


def estimator_errors(errors: RecipeErrors, key: str, spec: DictConfig) -> None:
    """The estimator block ``key``, built with tiny dims."""
    from torchrl_recon.experiments.recipe_models import build_estimator
    from torchrl_recon.modules import get_estimator_class
    from torchrl_recon.plugins import check_keywords

    window, taken = errors.cfg.models.window, ("window", "hidden_size", "activation")
    given = f"models.window, {key}.hidden_size and {key}.activation"
    check = partial(check_keywords, positional=2, keywords=taken, given_by=given)
    ok = window >= 1 and spec.hidden_size >= 1
    build = (lambda cls, kwargs: build_estimator(spec, 1, 1, window)) if ok else None
    _part_errors(errors, key, get_estimator_class, check, build)


def planner_errors(
    errors: RecipeErrors, key: str, objective: Callable[[], Objective], note: str
) -> None:
    """The planner block ``key``, built on a tiny model (one state and one action dim, with an
    estimator, on the CPU) with the recipe's objective (``objective()``, described by
    ``note``)."""
    from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
    from torchrl_recon.planners import PlanningModel
    from torchrl_recon.planners.registry import check_planner_kwargs, get_planner_class

    window = errors.cfg.models.window

    def build(cls: type, kwargs: dict) -> None:
        try:
            goal = objective()
        except ValueError:
            return  # the objective's values are reported by the schema's checks
        with torch.random.fork_rng(devices=[]):  # the run's random numbers stay as they are
            world = LSTMWorldModel(1, 1, window=window, hidden_size=1, dense_size=1)
            u = ReconstructionUncertainty(1, 1, window=window, hidden_size=1)
            cls(PlanningModel(world, lambda o, a, n: o[..., 0], uncertainty=u), goal, **kwargs)

    build_if = build if window >= 1 else None
    _part_errors(errors, key, get_planner_class, check_planner_kwargs, build_if, f" ({note})")


def duplicate_errors(errors: RecipeErrors, key: str, what: str) -> None:
    """Each name the list ``key`` of ``what`` holds twice."""
    names = [s.name for s in errors.cfg[key]]
    for name in sorted({n for n in names if names.count(n) > 1}):
        errors.append(f"'{key}': duplicate {what} name {name!r}")


def data_errors(errors: RecipeErrors, episode_key: str, frames_key: str | None = None) -> None:
    """Random data in episodes of ``episode_key`` steps must hold a training slice per episode
    and, with ``frames_key`` steps in all, two trajectories (one is held out to validate a fit)."""
    cfg = errors.cfg
    slice_len, episode = cfg.training.slice_len, OmegaConf.select(cfg, episode_key)
    why = f"at least training.slice_len = {slice_len} (a training slice never crosses an episode)"
    errors.need(episode_key, episode >= slice_len, why)
    if frames_key is not None:
        errors.need(
            frames_key,
            cfg[frames_key] >= episode + slice_len,
            f"at least {episode_key} + training.slice_len = {episode + slice_len} (two "
            "trajectories: one is held out to validate the fit)",
        )
