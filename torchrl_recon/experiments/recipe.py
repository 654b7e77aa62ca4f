"""Recipes: load a YAML recipe, apply overrides and check every key before any work starts.

A recipe is a YAML file holding every number of one experiment; it is merged onto the typed
schema of :mod:`torchrl_recon.experiments.config` so that an unknown key or a wrong type is an
error naming the key before any work starts; :mod:`.recipe_checks` then checks the values
(names, ranges, finite numbers, env keywords). Run directories are :mod:`.run_dir`'s job.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

from torchrl_recon.experiments.config import SCHEMAS, ControlSetting, EstimatorSpec
from torchrl_recon.experiments.recipe_checks import recipe_errors

LIST_FIELDS = {"control": ("settings", ControlSetting), "calibrate": ("estimators", EstimatorSpec)}
"""List fields whose items are checked against their own schema (OmegaConf merges lists whole)."""


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
        raise RecipeError(
            f"cannot parse the overrides {list(overrides)}: {_first_line(e)} (Hydra's override "
            "syntax: key=value, +key=value, ~key; quote values holding spaces or brackets)"
        ) from e


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
    """Check a recipe against its schema and its values; return the typed, resolved config.

    Works on a config loaded by :func:`load_recipe` or composed by Hydra (its ``hydra`` node,
    if any, is dropped). Checks: ``experiment`` is one of :data:`SCHEMAS`; no unknown key and no
    wrong type (schema merge); no missing value; then every value
    (:func:`~torchrl_recon.experiments.recipe_checks.recipe_errors`): no NaN or infinite number
    at any depth; counts, sizes, rates and ratios in their ranges (e.g. ``guided.ratio`` above
    1, ``training.val_fraction`` in (0, 1), enough random data for a held-out trajectory);
    ``env.name`` registered and ``env.kwargs`` keywords of that env's class; kinds, modes and
    backends known; setting and estimator names unique and usable as file names. Nothing is
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
    errors = recipe_errors(merged)
    if errors:
        raise RecipeError(f"{source}: " + "; ".join(errors))
    return merged


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


def experiment_name(cfg: DictConfig) -> str:
    """``<experiment>_<env>_seed<seed>``: the name of a run in loggers and tables."""
    return f"{cfg.experiment}_{cfg.env.name}_seed{cfg.seed}"
