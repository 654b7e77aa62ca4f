"""Recipes: a YAML recipe composed with its overrides and checked before any work starts."""

from __future__ import annotations

import dataclasses
import functools
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments.compose import RECIPES_DIR, compose_recipe, sweep_jobs
from torchrl_recon.experiments.context import RecipeLoader
from torchrl_recon.experiments.recipe_checks import recipe_errors
from torchrl_recon.experiments.registry import EXPERIMENT_TYPES

_BAD_CHOICE = re.compile(r"Invalid value '(.*)', expected one of \[(.*)\]")  # an Enum field's


def load_recipe(path: str | os.PathLike[str], overrides: Sequence[str] = ()) -> DictConfig:
    """Compose the recipe file ``path`` with Hydra-syntax ``overrides`` (no sweeps) as the
    CLI's jobs are, and ``validate`` it; FileNotFoundError or RecipeError if it fails.

    Examples:
        >>> cfg = load_recipe(RECIPES_DIR / "drone" / "explore_smoke.yaml", ["seed=3"])
        >>> cfg.output_dir, cfg.guided.ratio
        ('outputs/smoke/explore/drone/seed3', 1.2)
    """
    path = Path(path)
    jobs = sweep_jobs(compose_recipe(path, with_hydra=True), overrides, recipe_params=False)
    if len(jobs) != 1:
        raise RecipeError(
            f"{path}: the overrides {list(overrides)} sweep several values; sweeps need the "
            "command line's -m (Hydra multirun)."
        )
    return validate(compose_recipe(path, jobs[0]), source=str(path))


@functools.cache
def _structured(schema: type) -> DictConfig:
    """``OmegaConf.structured(schema)``, made once per schema (``OmegaConf.merge`` copies its
    first config, so this one is never changed)."""
    return OmegaConf.structured(schema)


def _merge_checked(schema: type, data: Any, *, prefix: str, source: str) -> DictConfig:
    """``OmegaConf.merge(structured(schema), data)`` with errors that name the full key."""
    try:
        return OmegaConf.merge(_structured(schema), data)
    except OmegaConfBaseException as e:
        key = (prefix + (getattr(e, "full_key", None) or "")).rstrip(".")
        line = str(e).strip().partition("\n")[0]
        if isinstance(e, ConfigKeyError):
            t = e.object_type
            where = f" of {t.__name__}" if isinstance(t, type) else ""
            known = [f.name for f in dataclasses.fields(t)] if dataclasses.is_dataclass(t) else []
            hint = f" Known keys here: {', '.join(known)}." if known else ""
            raise RecipeError(f"{source}: unknown key '{key}' (not a field{where}).{hint}") from e
        if isinstance(e, ValidationError) and (choice := _BAD_CHOICE.fullmatch(line)):
            value, choices = choice.groups()  # an Enum field: name its choices
            raise RecipeError(
                f"{source}: '{key}' must be one of {choices.split(', ')}, got {value!r}"
            ) from e
        what = "wrong type for" if isinstance(e, ValidationError) else "invalid value at"
        raise RecipeError(f"{source}: {what} '{key}': {line}") from e


def validate(cfg: DictConfig | Mapping[str, Any], *, source: str = "recipe") -> DictConfig:
    """Check a recipe (its ``hydra`` node dropped) against its kind's schema and
    :func:`~.recipe_checks.recipe_errors`; return the typed, resolved config. Without
    ``env.name``, ``env.id`` names the run. Raises a RecipeError naming every bad key, on one line.

    Examples:
        >>> cfg = compose_recipe(RECIPES_DIR / "drone" / "explore_smoke.yaml")
        >>> cfg.guided.ratio = float("nan")
        >>> try:
        ...     validate(cfg, source="explore_smoke.yaml")
        ... except RecipeError as e:
        ...     print(e)
        explore_smoke.yaml: 'guided.ratio' must be a finite number, got nan
    """
    cfg = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(dict(cfg))
    data = {k: v for k, v in OmegaConf.to_container(cfg).items() if k not in ("hydra", "defaults")}
    experiment = data.get("experiment")
    if (kind := EXPERIMENT_TYPES.get(experiment)) is None:
        raise RecipeError(
            f"{source}: 'experiment' must be one of {sorted(EXPERIMENT_TYPES)}, got {experiment!r}."
        )
    key, item_schema = kind.list_field or ("", None)
    if (items := data.get(key)) is None:
        data.pop(key, None)  # the schema's default
    try:
        merged = _merge_checked(kind.schema, data, prefix="", source=source)
    except Exception:  # OmegaConf's errors inside a list do not name the index: an item's own
        for i, item in enumerate(items if isinstance(items, list) else []):  # merge names it
            if isinstance(item, dict):
                _merge_checked(item_schema, item, prefix=f"{key}[{i}].", source=source)
        raise
    env = OmegaConf.to_container(merged.env, resolve=False)
    if env.get("name") is None and env.get("id") is not None:  # a gymnasium id names the run
        merged.env.name = "${trr_env_name:${env.id}}"
    try:
        OmegaConf.resolve(merged)
    except OmegaConfBaseException as e:
        raise RecipeError(
            f"{source}: cannot resolve an interpolation at '{getattr(e, 'full_key', '?')}': "
            + str(e).strip().partition("\n")[0]
        ) from e
    if missing := sorted(OmegaConf.missing_keys(merged)):
        raise RecipeError(f"{source}: no value given for {', '.join(repr(k) for k in missing)}.")
    if errors := recipe_errors(merged, kind, RecipeLoader(resolve_recipe_path, load_recipe)):
        raise RecipeError(f"{source}: " + "; ".join(errors))
    return merged


def resolve_recipe_path(path: str | os.PathLike[str]) -> Path:
    """A recipe file as given, else a shipped one by name (``drone/explore``; ``.yaml`` and a
    leading ``recipes/`` optional); a FileNotFoundError names both places looked in.

    Examples:
        >>> resolve_recipe_path("drone/explore").relative_to(RECIPES_DIR).as_posix()
        'drone/explore.yaml'
    """
    given = Path(path).expanduser()
    name = Path(*given.parts[1:]) if given.parts[:1] == ("recipes",) else given
    for candidate in (given, RECIPES_DIR / name, (RECIPES_DIR / name).with_suffix(".yaml")):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"no recipe file {str(path)!r} (looked in {Path.cwd()} and among the shipped recipes, "
        "listed by `torchrl-recon recipes`)"
    )
