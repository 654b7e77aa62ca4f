"""Recipes: load a YAML recipe, apply overrides and check every key before any work starts.

A recipe is a YAML file holding every number of one experiment; it is merged onto the typed
schema of :mod:`torchrl_recon.experiments.config` so that an unknown key or a wrong type is an
error naming the key before any work starts. Run directories are :mod:`.run_dir`'s job.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

from torchrl_recon.experiments.config import SCHEMAS, ControlSetting, EstimatorSpec

PLANNER_KINDS = ("shooting", "cem", "gradient")
BAND_KINDS = ("absolute", "quantile", "mean_ratio")
LOGGER_BACKENDS = ("wandb", "csv", "none")
LOGGER_MODES = ("offline", "online")
REPLAN_MODES = ("every_step", "every_n", "uncertainty")
THRESHOLD_ON = ("step", "cumulative")
VALIDATION_POLICIES = ("random", "offset_noise")
WORLD_MODEL_MODES = ("multi_step", "one_step")

LIST_FIELDS = {"control": ("settings", ControlSetting), "calibrate": ("estimators", EstimatorSpec)}
"""List fields whose items are checked against their own schema (OmegaConf merges lists whole)."""

STAGE_PATTERNS = {
    "explore": (
        r"initial_random",
        r"initial_models",
        r"validation",
        r"guided_data_\d+",
        r"guided_refit_\d+",
        r"random_arm",
        r"retrain_(random|active)_\d+",
    ),
    "control": (r"random_data", r"models", r"setting_.+"),
    "calibrate": (
        r"random_data",
        r"world_model",
        r"fit_.+",
        r"evaluation",
        r"timing",
        r"outcome_.+",
    ),
}
"""Stage names of ``run_explore`` / ``run_control`` / ``run_calibration`` (a ``stop_after`` must match one)."""


class RecipeError(ValueError):
    """A recipe (or an override) is not valid: unknown key, wrong type, unknown name."""


# ----------------------------------------------------------------------------------------------
# Loading and validation


def _load_yaml(path: Path) -> DictConfig:
    try:
        cfg = OmegaConf.load(path)
    except OmegaConfBaseException as e:
        raise RecipeError(f"{path}: cannot parse the recipe: {e}") from e
    except Exception as e:  # yaml.YAMLError and friends
        raise RecipeError(f"{path}: cannot parse the recipe: {e}") from e
    if not isinstance(cfg, DictConfig):
        raise RecipeError(f"{path}: a recipe must be a YAML mapping, got {type(cfg).__name__}.")
    return cfg


def compose_recipe(path: Path, stack: tuple[Path, ...] = ()) -> DictConfig:
    """Load ``path`` and resolve a Hydra-style ``defaults`` list of sibling recipes.

    Supports the subset the recipes use: entries naming another recipe of the same directory
    (``explore`` or ``/explore``, without ``.yaml``) and ``_self_`` (implicitly last, as in
    Hydra >= 1.1). Entries that only configure Hydra itself (``override hydra/...``) are ignored.
    """
    path = path.resolve()
    if path in stack:
        chain = " -> ".join(str(p) for p in (*stack, path))
        raise RecipeError(f"recipe defaults form a cycle: {chain}")
    cfg = _load_yaml(path)
    defaults = cfg.pop("defaults", None) if "defaults" in cfg else None
    if defaults is None:
        return cfg
    if not isinstance(defaults, ListConfig):
        raise RecipeError(f"{path}: 'defaults' must be a list, got {defaults!r}.")
    entries = list(defaults)
    if "_self_" not in entries:
        entries.append("_self_")
    out = OmegaConf.create({})
    for entry in entries:
        if entry == "_self_":
            out = OmegaConf.merge(out, cfg)
        elif isinstance(entry, str):
            name = entry.lstrip("/")
            if name.endswith(".yaml"):
                name = name[: -len(".yaml")]
            child = path.parent / f"{name}.yaml"
            if not child.is_file():
                raise FileNotFoundError(f"{path}: defaults entry {entry!r}: no recipe file {child}")
            out = OmegaConf.merge(out, compose_recipe(child, (*stack, path)))
        elif isinstance(entry, DictConfig) and all(
            str(k).removeprefix("override ").startswith("hydra") for k in entry
        ):
            continue  # Hydra's own settings (launcher, sweeper, ...): not part of the recipe
        else:
            raise RecipeError(
                f"{path}: unsupported defaults entry {OmegaConf.to_container(entry) if isinstance(entry, DictConfig) else entry!r}; "
                "only sibling recipe names and _self_ are supported."
            )
    return out


def parse_overrides(overrides: Sequence[str]) -> list[Any]:
    """Parse Hydra-syntax overrides (``key=value``, ``+key=value``, ``~key``) with Hydra's parser."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        return OverridesParser.create().parse_overrides(list(overrides))
    except Exception as e:  # hydra.errors.OverrideParseException
        raise RecipeError(f"cannot parse the overrides {list(overrides)}: {e}") from e


_OWN_VALUE = object()


def apply_override(cfg: DictConfig, override: Any, value: Any = _OWN_VALUE) -> None:
    """Apply one parsed (non-sweep) override to a plain config, in place.

    ``value`` replaces the override's own value (used to check one value of a sweep).
    List elements are addressed by index (``settings.0.beta=0.3``).
    """
    key = override.key_or_group
    if override.is_delete():
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if node is None or leaf not in node:
            raise RecipeError(f"override ~{key}: there is no key {key!r} to delete.")
        del node[leaf]
        return
    new = override.value() if value is _OWN_VALUE else value
    try:
        OmegaConf.update(cfg, key, new, merge=True, force_add=True)
    except OmegaConfBaseException as e:
        raise RecipeError(f"override {key}={new!r}: {_first_line(e)}") from e


def _apply_overrides(cfg: DictConfig, overrides: Sequence[str]) -> DictConfig:
    for o in parse_overrides(overrides):
        if o.is_sweep_override():
            raise RecipeError(
                f"override {o.input_line!r} is a sweep; sweeps need the command line's -m (Hydra multirun)."
            )
        if o.is_hydra_override() or "/" in o.key_or_group:
            continue  # Hydra's own settings: only meaningful through the command line
        apply_override(cfg, o)
    return cfg


def load_recipe(path: str | os.PathLike[str], overrides: Sequence[str] = ()) -> DictConfig:
    """Load a recipe without Hydra, apply ``key=value`` overrides and validate it.

    Args:
        path: the recipe YAML file. A ``defaults: [other, _self_]`` list naming sibling recipes
            is honoured (the smoke recipes use it).
        overrides: Hydra-syntax overrides, e.g. ``["seed=3", "guided.ratio=1.5",
            "settings.0.beta=0.1"]`` (``+key=value`` adds, ``~key`` deletes; no sweeps).

    Returns:
        The typed, resolved configuration (see :func:`validate`).

    Raises:
        FileNotFoundError: the recipe (or a recipe it names in ``defaults``) does not exist.
        RecipeError: unknown key, wrong type, unknown environment or kind (a ``ValueError``).

    Examples:
        >>> import torchrl_recon
        >>> recipes = Path(torchrl_recon.__file__).parents[1] / "recipes"
        >>> cfg = load_recipe(recipes / "drone" / "explore_smoke.yaml", ["seed=3"])
        >>> cfg.output_dir, cfg.guided.ratio
        ('outputs/smoke/explore/drone/seed3', 1.2)
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Recipe file not found: {path}")
    cfg = compose_recipe(path)
    cfg = _apply_overrides(cfg, list(overrides))
    return validate(cfg, source=str(path))


def _first_line(msg: str) -> str:
    return str(msg).strip().splitlines()[0] if str(msg).strip() else str(msg)


def _field_names(obj_type: Any) -> list[str]:
    if isinstance(obj_type, type) and dataclasses.is_dataclass(obj_type):
        return [f.name for f in dataclasses.fields(obj_type)]
    return []


def _merge_checked(schema: Any, data: Any, *, prefix: str, source: str) -> DictConfig:
    """``OmegaConf.merge(structured(schema), data)`` with errors that name the full key."""
    try:
        return OmegaConf.merge(OmegaConf.structured(schema), data)
    except ConfigKeyError as e:
        key = f"{prefix}{e.full_key}" if e.full_key else prefix.rstrip(".")
        known = _field_names(e.object_type)
        where = f" of {e.object_type.__name__}" if isinstance(e.object_type, type) else ""
        hint = f" Known keys here: {', '.join(known)}." if known else ""
        raise RecipeError(f"{source}: unknown key '{key}' (not a field{where}).{hint}") from e
    except ValidationError as e:
        key = f"{prefix}{e.full_key}" if e.full_key else prefix.rstrip(".")
        raise RecipeError(f"{source}: wrong type for '{key}': {_first_line(e.msg)}") from e
    except OmegaConfBaseException as e:
        key = f"{prefix}{getattr(e, 'full_key', '')}"
        raise RecipeError(f"{source}: invalid value at '{key}': {_first_line(e)}") from e


def validate(cfg: DictConfig | Mapping[str, Any], *, source: str = "recipe") -> DictConfig:
    """Check a recipe against its schema and the known names; return the typed, resolved config.

    Works on a config loaded by :func:`load_recipe` or composed by Hydra (its ``hydra`` node,
    if any, is dropped). Checks: ``experiment`` is one of :data:`SCHEMAS`; no unknown key and no
    wrong type (schema merge); no missing value; ``env.name`` is a registered environment;
    planner kinds, band kinds and bounds, logger backend and mode, re-planning and validation
    modes are known; control setting names are unique.

    Raises:
        RecipeError: (a ``ValueError``) naming the offending key.
    """
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(dict(cfg))
    container = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(container, dict)
    container.pop("hydra", None)
    container.pop("defaults", None)
    experiment = container.get("experiment")
    if experiment not in SCHEMAS:
        raise RecipeError(
            f"{source}: 'experiment' must be one of {sorted(SCHEMAS)}, got {experiment!r}."
        )
    list_key, item_schema = LIST_FIELDS.get(experiment, (None, None))
    items = container.pop(list_key, None) if list_key else None
    merged = _merge_checked(SCHEMAS[experiment], container, prefix="", source=source)
    if list_key and items is not None:
        if not isinstance(items, list):
            raise RecipeError(f"{source}: '{list_key}' must be a list, got {type(items).__name__}.")
        checked = []
        for i, item in enumerate(items):
            if not isinstance(item, dict):
                raise RecipeError(f"{source}: '{list_key}[{i}]' must be a mapping, got {item!r}.")
            checked.append(
                _merge_checked(item_schema, item, prefix=f"{list_key}[{i}].", source=source)
            )
        merged[list_key] = checked
    try:
        OmegaConf.resolve(merged)
    except OmegaConfBaseException as e:
        raise RecipeError(
            f"{source}: cannot resolve an interpolation at '{getattr(e, 'full_key', '?')}': {_first_line(e)}"
        ) from e
    missing = sorted(OmegaConf.missing_keys(merged))
    if missing:
        raise RecipeError(f"{source}: no value given for {', '.join(repr(k) for k in missing)}.")
    errors = _semantic_errors(merged)
    if errors:
        raise RecipeError(f"{source}: " + "; ".join(errors))
    return merged


def _check_planner(planner: DictConfig, key: str, errors: list[str]) -> None:
    if planner.kind not in PLANNER_KINDS:
        errors.append(f"'{key}.kind' must be one of {list(PLANNER_KINDS)}, got {planner.kind!r}")
    for name in ("horizon", "num_candidates", "iterations", "num_elites", "restarts"):
        if planner[name] < 1:
            errors.append(f"'{key}.{name}' must be >= 1, got {planner[name]}")


def _estimator_errors(spec: DictConfig, key: str, window: int) -> list[str]:
    """Build the estimator a block names (tiny dims) so a bad kind or keyword fails before any work."""
    from torchrl_recon.experiments.common import build_estimator

    try:
        build_estimator(spec, 1, 1, window)
    except (ValueError, TypeError) as e:
        return [f"'{key}': {e}"]
    return []


def _semantic_errors(cfg: DictConfig) -> list[str]:
    from torchrl_recon.envs import get_entry
    from torchrl_recon.planners.objective import UncertaintyBand

    errors: list[str] = []
    try:
        get_entry(cfg.env.name)
    except ValueError as e:
        errors.append(f"'env.name': {e}")
    if cfg.logger.backend not in LOGGER_BACKENDS:
        errors.append(
            f"'logger.backend' must be one of {list(LOGGER_BACKENDS)}, got {cfg.logger.backend!r}"
        )
    if cfg.logger.mode not in LOGGER_MODES:
        errors.append(f"'logger.mode' must be one of {list(LOGGER_MODES)}, got {cfg.logger.mode!r}")
    if cfg.training.world_model_mode not in WORLD_MODEL_MODES:
        errors.append(
            f"'training.world_model_mode' must be one of {list(WORLD_MODEL_MODES)}, "
            f"got {cfg.training.world_model_mode!r}"
        )
    errors.extend(
        _estimator_errors(cfg.models.uncertainty, "models.uncertainty", cfg.models.window)
    )
    if cfg.threads < 1:
        errors.append(f"'threads' must be >= 1, got {cfg.threads}")
    if cfg.env.episode_steps < 1:
        errors.append(f"'env.episode_steps' must be >= 1, got {cfg.env.episode_steps}")
    if cfg.stop_after is not None and not _is_stage(cfg):
        errors.append(
            f"'stop_after': {cfg.stop_after!r} is not a stage of {cfg.experiment}; stages: "
            + ", ".join(_stage_list(cfg))
        )
    if cfg.experiment == "calibrate":
        errors.extend(_calibrate_errors(cfg))
    elif cfg.experiment == "explore":
        _check_planner(cfg.guided.planner, "guided.planner", errors)
        if cfg.validation.policy not in VALIDATION_POLICIES:
            errors.append(
                f"'validation.policy' must be one of {list(VALIDATION_POLICIES)}, "
                f"got {cfg.validation.policy!r}"
            )
        if cfg.retrainings < 1:
            errors.append(f"'retrainings' must be >= 1, got {cfg.retrainings}")
    else:
        if cfg.replan.mode not in REPLAN_MODES:
            errors.append(
                f"'replan.mode' must be one of {list(REPLAN_MODES)}, got {cfg.replan.mode!r}"
            )
        if cfg.replan.threshold_on not in THRESHOLD_ON:
            errors.append(
                f"'replan.threshold_on' must be one of {list(THRESHOLD_ON)}, "
                f"got {cfg.replan.threshold_on!r}"
            )
        error_threshold = cfg.replan.error_threshold
        if error_threshold is not None and not (0 < error_threshold < float("inf")):
            errors.append(
                "'replan.error_threshold' must be a positive finite number or null, "
                f"got {error_threshold!r}"
            )
        if not cfg.settings:
            errors.append("'settings' is empty: a control recipe needs at least one setting")
        seen: set[str] = set()
        for i, setting in enumerate(cfg.settings):
            key = f"settings[{i}]"
            if setting.name in seen:
                errors.append(f"'{key}.name': duplicate setting name {setting.name!r}")
            seen.add(setting.name)
            _check_planner(setting.planner, f"{key}.planner", errors)
            if setting.band is not None:
                if setting.band.kind not in BAND_KINDS:
                    errors.append(
                        f"'{key}.band.kind' must be one of {list(BAND_KINDS)}, got {setting.band.kind!r}"
                    )
                else:
                    try:
                        UncertaintyBand(
                            low=setting.band.low, high=setting.band.high, kind=setting.band.kind
                        )
                    except ValueError as e:
                        errors.append(f"'{key}.band': {e}")
    return errors


def _calibrate_errors(cfg: DictConfig) -> list[str]:
    errors: list[str] = []
    if not cfg.estimators:
        errors.append("'estimators' is empty: a calibrate recipe needs at least one estimator")
    names = [spec.name for spec in cfg.estimators]
    for name in sorted({n for n in names if names.count(n) > 1}):
        errors.append(f"'estimators': duplicate estimator name {name!r}")
    for i, spec in enumerate(cfg.estimators):
        errors.extend(_estimator_errors(spec, f"estimators[{i}]", cfg.models.window))
    if cfg.evaluation.policy not in VALIDATION_POLICIES:
        errors.append(
            f"'evaluation.policy' must be one of {list(VALIDATION_POLICIES)}, "
            f"got {cfg.evaluation.policy!r}"
        )
    for key in (
        "evaluation.trajectories",
        "evaluation.horizon",
        "evaluation.ood_windows",
        "timing.candidates",
        "timing.repeats",
        "timing.iterations",
        "timing.num_elites",
        "random_steps",
        "random_episode_steps",
    ):
        value = OmegaConf.select(cfg, key)
        if value < 1:
            errors.append(f"'{key}' must be >= 1, got {value}")
    if not cfg.timing.horizons or min(cfg.timing.horizons) < 1:
        errors.append(
            f"'timing.horizons' must be a non-empty list of ints >= 1, got {list(cfg.timing.horizons)}"
        )
    for kind in ("explore", "control"):
        recipe = cfg.outcomes[f"{kind}_recipe"]
        if recipe is not None:
            try:
                resolve_recipe_path(recipe)
            except FileNotFoundError as e:
                errors.append(f"'outcomes.{kind}_recipe': {e}")
    return errors


def resolve_recipe_path(path: str | os.PathLike[str]) -> Path:
    """A recipe path as given (absolute or relative to the working directory), else relative
    to the checkout this package runs from (where ``recipes/`` lives).

    Raises:
        FileNotFoundError: naming both places looked in.
    """
    candidates = [Path(path).expanduser(), Path(__file__).resolve().parents[2] / path]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"no recipe file {str(path)!r} (looked in {Path.cwd()} and {candidates[1].parent})"
    )


def _stage_list(cfg: DictConfig) -> list[str]:
    if cfg.experiment == "control":
        return ["random_data", "models", *(f"setting_{s.name}" for s in cfg.settings)]
    if cfg.experiment == "calibrate":
        names = [s.name for s in cfg.estimators]
        return [
            "random_data",
            "world_model",
            *(f"fit_{n}" for n in names),
            "evaluation",
            "timing",
            *(f"outcome_{n}_{k}" for n in names for k in ("explore", "control")),
        ]
    return [
        p.replace("\\d+", "<n>").replace("(random|active)", "<arm>")
        for p in STAGE_PATTERNS["explore"]
    ]


def _is_stage(cfg: DictConfig) -> bool:
    if cfg.experiment in ("control", "calibrate"):
        return cfg.stop_after in _stage_list(cfg)
    return any(re.fullmatch(p, cfg.stop_after) for p in STAGE_PATTERNS["explore"])


def experiment_name(cfg: DictConfig) -> str:
    """``<experiment>_<env>_seed<seed>``: the name of a run in loggers and tables."""
    return f"{cfg.experiment}_{cfg.env.name}_seed{cfg.seed}"
