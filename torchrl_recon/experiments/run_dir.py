"""Recipes and run directories: load and check a recipe, prepare the output directory, store results.

A recipe is a YAML file holding every number of one experiment; it is merged onto the typed
schema of :mod:`torchrl_recon.experiments.config` so that an unknown key or a wrong type is an
error naming the key before any work starts. A run directory holds one run (one seed): its
resolved ``config.yaml``, ``meta.json`` (versions, git commit, host, time, command line), the
stage outputs written by the experiment, ``results.json`` and the figures.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
import platform
import re
import socket
import subprocess
import sys
from collections.abc import Iterable, Mapping, Sequence
from importlib import metadata
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

RESUME_IGNORED_KEYS = ("progress", "stop_after", "logger", "output_dir")
"""Top-level keys that may change between a run and its resumption (they do not change results)."""

VERSION_PACKAGES = (
    "torch",
    "torchrl",
    "tensordict",
    "gymnasium",
    "numpy",
    "pybullet",
    "torchrl-recon",
    "hydra-core",
    "omegaconf",
    "wandb",
)


class RecipeError(ValueError):
    """A recipe (or an override) is not valid: unknown key, wrong type, unknown name."""


class RunDirConflict(RuntimeError):
    """The run directory holds a run made with a different configuration."""


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


# ----------------------------------------------------------------------------------------------
# Run directory


def _flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Flatten nested dicts / lists into ``{"a.b.0.c": value}``."""
    out: dict[str, Any] = {}
    if isinstance(obj, Mapping):
        if not obj and prefix:
            out[prefix] = {}
        for k, v in obj.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(obj, (list, tuple)):
        if not obj and prefix:
            out[prefix] = []
        for i, v in enumerate(obj):
            out.update(_flatten(v, f"{prefix}.{i}" if prefix else str(i)))
    else:
        out[prefix] = obj
    return out


def flat_config(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as a flat ``{"guided.planner.kind": "shooting", ...}`` dict."""
    return _flatten(OmegaConf.to_container(cfg, resolve=True))


def config_differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """Keys (flattened) whose values differ between two configs, ignoring :data:`RESUME_IGNORED_KEYS`."""

    def keep(key: str) -> bool:
        return key.split(".", 1)[0] not in RESUME_IGNORED_KEYS

    a = {k: v for k, v in _flatten(dict(old)).items() if keep(k)}
    b = {k: v for k, v in _flatten(dict(new)).items() if keep(k)}
    diffs = []
    for key in sorted(set(a) | set(b)):
        if key not in a:
            diffs.append(f"{key}: (absent) -> {b[key]!r}")
        elif key not in b:
            diffs.append(f"{key}: {a[key]!r} -> (absent)")
        elif a[key] != b[key]:
            diffs.append(f"{key}: {a[key]!r} -> {b[key]!r}")
    return diffs


def package_versions(names: Iterable[str] = VERSION_PACKAGES) -> dict[str, str | None]:
    """Installed versions (``importlib.metadata``) of ``names``, plus ``python``; None if absent."""
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def git_info(directory: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Commit and dirty flag of the git checkout holding ``directory`` (default: this package).

    Read-only: ``git rev-parse HEAD`` and ``git --no-optional-locks status --porcelain``.
    ``commit`` is ``"unknown"`` (and ``dirty`` None) when it is not a checkout or git is missing.
    """
    if directory is None:
        directory = Path(__file__).resolve().parents[1]
    directory = Path(directory)
    info: dict[str, Any] = {"commit": "unknown", "dirty": None, "source_dir": str(directory)}

    def git(*args: str) -> str | None:
        try:
            proc = subprocess.run(
                ["git", *args],
                cwd=directory,
                capture_output=True,
                text=True,
                timeout=20,
                check=False,
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return proc.stdout if proc.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if commit is None or not commit.strip():
        return info
    info["commit"] = commit.strip()
    status = git("--no-optional-locks", "status", "--porcelain")
    info["dirty"] = None if status is None else bool(status.strip())
    return info


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    tmp.replace(path)


_LOCKS: dict[str, Any] = {}


def _lock(run_dir: Path) -> None:
    """Hold an exclusive lock on ``run_dir`` for this process (two jobs sharing one dir fail)."""
    key = str(run_dir)
    if key in _LOCKS:
        return
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return
    handle = open(run_dir / ".lock", "w")  # noqa: SIM115 - held until release_run_dir
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        handle.close()
        raise RunDirConflict(
            f"Another process is running in {run_dir}. Give each run its own output_dir "
            "(e.g. interpolate ${seed} in it when sweeping seeds)."
        ) from e
    _LOCKS[key] = handle


def release_run_dir(run_dir: str | os.PathLike[str]) -> None:
    """Release the lock taken by :func:`prepare_run_dir` (also released when the process exits)."""
    handle = _LOCKS.pop(str(Path(run_dir).resolve()), None)
    if handle is not None:
        handle.close()


def check_run_dir(cfg: DictConfig) -> dict[str, Any]:
    """Refuse to resume a run directory that holds a run made with a different config.

    Returns the resolved config as a dict. Compares with ``<output_dir>/config.yaml`` when it
    exists; only ``progress``, ``stop_after``, ``logger`` (and the spelling of ``output_dir``)
    may differ.

    Raises:
        RunDirConflict: naming the keys that differ.
    """
    new = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(new, dict)
    run_dir = Path(cfg.output_dir).expanduser().resolve()
    config_path = run_dir / "config.yaml"
    if not config_path.exists():
        return new
    saved = OmegaConf.load(config_path)
    schema = SCHEMAS.get(saved.get("experiment"))
    if schema is not None:
        # Keys added to the schema after the run was made compare at their defaults.
        saved = OmegaConf.merge(OmegaConf.structured(schema), saved)
    old = OmegaConf.to_container(saved, resolve=False)
    assert isinstance(old, dict)
    diffs = config_differences(old, new)
    if diffs:
        shown = "\n  ".join(diffs[:20]) + ("\n  ..." if len(diffs) > 20 else "")
        raise RunDirConflict(
            f"{run_dir} already holds a run with a different configuration:\n  {shown}\n"
            "Resuming it with this config would mix results. Use another output_dir, or "
            "delete the directory to start over. (Only progress, stop_after and logger may "
            "change between a run and its resumption.)"
        )
    return new


def prepare_run_dir(
    cfg: DictConfig,
    argv: Sequence[str] | None = None,
    extra_meta: Mapping[str, Any] | None = None,
) -> Path:
    """Create ``cfg.output_dir`` and write ``config.yaml`` (resolved) and ``meta.json``.

    A directory that already holds a ``config.yaml`` is a run to resume: its config must equal
    the new one except for ``progress``, ``stop_after``, ``logger`` (and the spelling of
    ``output_dir``), otherwise the stages already done would mix with new ones.

    ``meta.json`` holds the seed, package versions, the git commit and dirty flag of the source
    checkout, the host name, the UTC start time and the command line (plus ``extra_meta``, e.g.
    the Hydra job overrides); on a resume the earlier starts are kept under ``previous``.

    Returns:
        The absolute run directory.

    Raises:
        RunDirConflict: the directory holds a run with a different config, or another process
            is running in it.
    """
    run_dir = Path(cfg.output_dir).expanduser().resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    _lock(run_dir)
    try:
        new = check_run_dir(cfg)
    except RunDirConflict:
        release_run_dir(run_dir)
        raise
    config_path = run_dir / "config.yaml"
    resumed = config_path.exists()
    _atomic_write(config_path, OmegaConf.to_yaml(OmegaConf.create(new)))

    meta_path = run_dir / "meta.json"
    previous: list[dict[str, Any]] = []
    if resumed and meta_path.exists():
        try:
            old_meta = json.loads(meta_path.read_text())
            previous = list(old_meta.get("previous", []))
            previous.append(
                {k: old_meta.get(k) for k in ("started_utc", "git", "argv", "hostname")}
            )
        except (OSError, ValueError):
            previous = []
    meta = {
        "experiment": cfg.experiment,
        "env": cfg.env.name,
        "seed": int(cfg.seed),
        "run_dir": str(run_dir),
        "versions": package_versions(),
        "git": git_info(),
        "hostname": socket.gethostname(),
        "started_utc": _utc_now(),
        "argv": list(sys.argv if argv is None else argv),
        "resumed": resumed,
        "previous": previous,
        **dict(extra_meta or {}),
    }
    if previous and previous[-1].get("git", {}).get("commit") != meta["git"]["commit"]:
        print(
            f"warning: {run_dir} was started at commit "
            f"{previous[-1].get('git', {}).get('commit')} and is resumed at "
            f"{meta['git']['commit']}.",
            file=sys.stderr,
        )
    _atomic_write(meta_path, json.dumps(meta, indent=1))
    return run_dir


def _json_default(obj: Any) -> Any:
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist"):  # numpy arrays / scalars, torch tensors
        return obj.tolist()
    if hasattr(obj, "item"):
        return obj.item()
    if isinstance(obj, (DictConfig, ListConfig)):
        return OmegaConf.to_container(obj, resolve=True)
    raise TypeError(f"Object of type {type(obj).__name__} is not JSON serialisable")


def write_results(run_dir: str | os.PathLike[str], results: Mapping[str, Any]) -> Path:
    """Write ``results.json`` = the experiment's results dict plus ``meta`` (from ``meta.json``).

    Non-finite floats are written as JSON ``NaN`` / ``Infinity`` (Python's ``json`` reads them).
    """
    run_dir = Path(run_dir)
    meta: dict[str, Any] = {}
    meta_path = run_dir / "meta.json"
    if meta_path.exists():
        meta = json.loads(meta_path.read_text())
    meta["finished_utc"] = _utc_now()
    payload = {**dict(results), "meta": meta}
    path = run_dir / "results.json"
    _atomic_write(path, json.dumps(payload, indent=1, default=_json_default))
    return path


def read_results(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a ``results.json`` file (or the one inside a run directory)."""
    path = Path(path)
    if path.is_dir():
        path = path / "results.json"
    return json.loads(path.read_text())
