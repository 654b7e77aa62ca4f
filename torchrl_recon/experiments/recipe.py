"""Recipes: load a YAML recipe, apply overrides and check every key before any work starts.

A recipe is a YAML file holding every number of one experiment; it is merged onto the typed
schema of :mod:`torchrl_recon.experiments.config` so that an unknown key, a wrong type or an
unknown choice is an error naming the key before any work starts; the ranges declared on the
schema's fields and :mod:`.recipe_checks` (env, planner and estimator classes, sizes across
sections) then check the values. Run directories are :mod:`.run_dir`'s job.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments.compose import (
    RECIPES_DIR,
    compose_recipe,
    sweep_jobs,
    with_additions,
)
from torchrl_recon.experiments.context import RecipeLoader
from torchrl_recon.experiments.recipe_checks import recipe_errors
from torchrl_recon.experiments.registry import EXPERIMENT_TYPES


def load_recipe(path: str | os.PathLike[str], overrides: Sequence[str] = ()) -> DictConfig:
    """Compose a recipe with ``key=value`` overrides (as the CLI's jobs are) and validate it.

    Args:
        path: the recipe YAML file. Its ``defaults`` list is Hydra's: sibling recipes
            (``[explore, _self_]``, as the smoke recipes do), shipped ones
            (``[/drone/explore@_here_, _self_]``) and config groups.
        overrides: Hydra-syntax overrides, e.g. ``["seed=3", "guided.ratio=1.5",
            "settings.0.beta=0.1"]`` (a schema key the recipe lacks is added; ``~key``
            deletes; no sweeps).

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
    base = compose_recipe(path, with_hydra=True)
    jobs = sweep_jobs(base, with_additions(base, overrides), recipe_params=False)
    if len(jobs) != 1:
        raise RecipeError(
            f"{path}: the overrides {list(overrides)} sweep several values; sweeps need the "
            "command line's -m (Hydra multirun)."
        )
    return validate(compose_recipe(path, jobs[0]), source=str(path))


_BAD_CHOICE = re.compile(r"Invalid value '(.*)', expected one of \[(.*)\]")
"""OmegaConf's message for a value that is none of an ``Enum`` field's choices."""


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
        choice = _BAD_CHOICE.fullmatch(_first_line(e.msg))
        if choice:  # an Enum field: name the choices as the other range messages do
            value, choices = choice.groups()
            raise RecipeError(
                f"{source}: '{key}' must be one of {choices.split(', ')}, got {value!r}"
            ) from e
        raise RecipeError(f"{source}: wrong type for '{key}': {_first_line(e.msg)}") from e
    except OmegaConfBaseException as e:
        key = f"{prefix}{getattr(e, 'full_key', '')}"
        raise RecipeError(f"{source}: invalid value at '{key}': {_first_line(e)}") from e


def validate(cfg: DictConfig | Mapping[str, Any], *, source: str = "recipe") -> DictConfig:
    """Check a recipe against its schema and its values; return the typed, resolved config.

    Works on a config loaded by :func:`load_recipe` or composed by Hydra (its ``hydra`` node,
    if any, is dropped). Checks: ``experiment`` is a kind of the registry; no unknown key and no
    wrong type (schema merge); no missing value; then every value
    (:func:`~torchrl_recon.experiments.recipe_checks.recipe_errors`): no NaN or infinite number
    at any depth; counts, sizes, rates and ratios in their ranges (e.g. ``guided.ratio`` above
    1, ``training.val_fraction`` in (0, 1), enough random data for a held-out trajectory);
    the env (``env.id`` or ``env.name``) known, ``env.kwargs`` keywords of that env, a cost
    that imports (``env.cost``, which runs its module, or the registered env's), and for a
    gymnasium env its spaces and a call of the cost (the env is built, not stepped); without
    ``env.name``, ``env.id`` names the run (``Pendulum-v1``; ``my_module:MyEnv-v0`` →
    ``MyEnv-v0``); modes and backends among their choices; each planner and estimator class
    (``kind``: shipped or ``module:Class``) importable, of the right base class, taking the
    block's ``kwargs`` and built on a tiny model; setting and estimator names unique and usable
    as file names. Nothing is
    written: the CLI and :func:`~torchrl_recon.experiments.runner.run` call it before the run
    directory exists.

    Raises:
        RecipeError: (a ``ValueError``) naming every offending key, on one line.

    Examples:
        >>> import torchrl_recon
        >>> recipes = Path(torchrl_recon.__file__).parents[1] / "recipes"
        >>> cfg = compose_recipe(recipes / "drone" / "explore_smoke.yaml")
        >>> cfg.guided.ratio = float("nan")
        >>> try:
        ...     validate(cfg, source="explore_smoke.yaml")
        ... except RecipeError as e:
        ...     print(e)
        explore_smoke.yaml: 'guided.ratio' must be a finite number, got nan
    """
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(dict(cfg))
    container = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(container, dict)
    container.pop("hydra", None)
    container.pop("defaults", None)
    experiment = container.get("experiment")
    if experiment not in EXPERIMENT_TYPES:
        raise RecipeError(
            f"{source}: 'experiment' must be one of {sorted(EXPERIMENT_TYPES)}, got {experiment!r}."
        )
    kind = EXPERIMENT_TYPES[experiment]
    # a list field's items are checked against their own schema (OmegaConf merges lists whole)
    list_key, item_schema = kind.list_field or (None, None)
    items = container.pop(list_key, None) if list_key else None
    merged = _merge_checked(kind.schema, container, prefix="", source=source)
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
    env = OmegaConf.to_container(merged.env, resolve=False)
    if env.get("name") is None and env.get("id") is not None:  # a gymnasium id names the run
        merged.env.name = "${trr_env_name:${env.id}}"
    try:
        OmegaConf.resolve(merged)
    except OmegaConfBaseException as e:
        raise RecipeError(
            f"{source}: cannot resolve an interpolation at '{getattr(e, 'full_key', '?')}': {_first_line(e)}"
        ) from e
    missing = sorted(OmegaConf.missing_keys(merged))
    if missing:
        raise RecipeError(f"{source}: no value given for {', '.join(repr(k) for k in missing)}.")
    errors = recipe_errors(merged, kind, RecipeLoader(resolve_recipe_path, load_recipe))
    if errors:
        raise RecipeError(f"{source}: " + "; ".join(errors))
    return merged


def resolve_recipe_path(path: str | os.PathLike[str]) -> Path:
    """A recipe path as given (absolute or relative to the working directory), else a recipe
    shipped in the package, by name (``drone/explore``, ``.yaml`` optional; a leading
    ``recipes/`` is allowed, so the checkout's paths work from any folder).

    Raises:
        FileNotFoundError: naming both places looked in.

    Examples:
        >>> resolve_recipe_path("drone/explore").relative_to(RECIPES_DIR).as_posix()
        'drone/explore.yaml'
    """
    given = Path(path).expanduser()
    name = Path(*given.parts[1:]) if given.parts[:1] == ("recipes",) else given
    candidates = [given, RECIPES_DIR / name, (RECIPES_DIR / name).with_suffix(".yaml")]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"no recipe file {str(path)!r} (looked in {Path.cwd()} and among the shipped recipes, "
        "listed by `torchrl-recon recipes`)"
    )


def experiment_name(cfg: DictConfig) -> str:
    """``<experiment>_<env>_seed<seed>``: the name of a run in loggers and tables."""
    return f"{cfg.experiment}_{cfg.env.name}_seed{cfg.seed}"
