"""Compose a recipe with Hydra's own composition: defaults lists, config groups, packages, sweeps.

The CLI's jobs are composed by Hydra; checking a recipe before any work composes it the same way
(:func:`compose_recipe`), with the shipped recipes on Hydra's search path so that a recipe
anywhere can extend a shipped one (``defaults: [/drone/explore@_here_, _self_]``).
"""

from __future__ import annotations

import contextlib
import itertools
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from torchrl_recon.errors import RecipeError

RECIPES_DIR = Path(__file__).resolve().parents[1] / "recipes"
"""The recipes shipped inside the package (``<env>/<kind>.yaml``; the checkout's ``recipes/``
links here), on Hydra's search path of every recipe."""
MAX_SWEEP_JOBS = 10_000


def env_name_of(gym_id: str | None) -> str | None:
    """The name a run gives a gymnasium env (in its directory, tables and loggers): the id
    without its ``module:`` prefix, with ``/`` as ``_``; the ``${trr_env_name:...}`` resolver
    of the recipes.

    Examples:
        >>> env_name_of("Pendulum-v1"), env_name_of("my_envs:Cart-v0"), env_name_of("ALE/Pong-v5")
        ('Pendulum-v1', 'Cart-v0', 'ALE_Pong-v5')
    """
    return None if gym_id is None else str(gym_id).rpartition(":")[2].replace("/", "_")


def register_resolvers() -> None:
    """The resolvers of the recipes and of the CLI's Hydra settings: ``${trr_env_name:<id>}``
    (:func:`env_name_of`), ``${trr_parent:<path>}`` and ``${trr_abspath:<path>}`` (where a
    sweep's directories go). Called at import: every path that composes a recipe, and each
    joblib worker that unpickles a CLI job, imports this module."""
    resolvers = {
        "trr_env_name": env_name_of,
        "trr_parent": lambda p: str(Path(str(p)).parent),
        "trr_abspath": lambda p: str(Path(str(p)).expanduser().resolve()),
    }
    for name, fn in resolvers.items():
        OmegaConf.register_new_resolver(name, fn, replace=True)


register_resolvers()


def hydra_error_message(error: BaseException) -> str:
    """Hydra's own error (several lines, a list of options, its search path) on one line."""
    text = str(error)
    if error.__cause__ is not None and str(error.__cause__) not in text:
        text += "\n" + str(error.__cause__)
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    cut = next((i for i, line in enumerate(lines) if line.startswith("Config search path")), None)
    head, rest = lines[0], lines[1:cut]
    if rest and rest[0].endswith(":"):  # "Available options in 'hydra/launcher':" + one per line
        return f"{head} ({rest[0]} {', '.join(rest[1:])})"
    return " ".join([head, *rest])


def search_path_override() -> str:
    """The Hydra override that puts :data:`RECIPES_DIR` on the config search path."""
    return f"hydra.searchpath=[file://{RECIPES_DIR}]"


@contextlib.contextmanager
def _own_hydra() -> Iterator[None]:
    """Let ``hydra.compose`` run inside a running Hydra app (e.g. a calibrate job loading the
    explore recipe it runs): the app's global state is set aside and restored afterwards."""
    from hydra.core.global_hydra import GlobalHydra

    global_hydra = GlobalHydra.instance()
    running = global_hydra.hydra if global_hydra.is_initialized() else None
    global_hydra.clear()
    try:
        yield
    finally:
        global_hydra.clear()
        if running is not None:
            global_hydra.initialize(running)


def compose_recipe(
    path: str | Path, overrides: Sequence[str] = (), *, with_hydra: bool = False
) -> DictConfig:
    """The config Hydra composes from the recipe file ``path`` and ``overrides`` (no sweeps).

    Args:
        path: the recipe YAML file.
        overrides: Hydra overrides (``key=value``, ``+key=value``, ``~key``, ``group=option``).
        with_hydra: keep the ``hydra`` node (its ``runtime.choices`` and ``sweeper.params``).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        RecipeError: Hydra cannot compose it; the message names the file.

    Examples:
        >>> cfg = compose_recipe(RECIPES_DIR / "drone" / "explore_smoke.yaml", ["seed=3"])
        >>> cfg.env.name, cfg.seed
        ('drone', 3)
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"Recipe file not found: {path}")
    overrides = [search_path_override(), *overrides]
    try:
        with _own_hydra(), initialize_config_dir(str(path.resolve().parent), version_base="1.3"):
            return compose(path.stem, overrides=overrides, return_hydra_config=with_hydra)
    except (HydraException, OmegaConfBaseException) as e:
        raise RecipeError(f"{path}: {hydra_error_message(e)}") from e


def _parse(overrides: Sequence[str]) -> list[Any]:
    """Hydra's own parse of each override (its key, type, sweep)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        return OverridesParser.create().parse_overrides(list(overrides))
    except Exception as e:  # hydra.errors.OverrideParseException
        raise RecipeError(
            f"cannot parse the overrides {list(overrides)}: {str(e).strip().splitlines()[0]} "
            "(Hydra's override syntax: key=value, +key=value, ~key; quote values holding "
            "spaces or brackets)"
        ) from e


def with_additions(base: DictConfig, overrides: Sequence[str]) -> list[str]:
    """``overrides`` with ``++`` before each plain ``key=value`` Hydra would refuse as written:
    a key the recipe lacks, or a mapping merged into one of the recipe's (``env.kwargs: {}``).

    Hydra only overrides keys a recipe has, and cannot merge new keys into a mapping; the
    schema has more keys (``threads``, ``env.kwargs``, ...); the schema check afterwards refuses
    a key that is not a field. ``base`` is the composed recipe with its ``hydra`` node (for the
    config group names).

    Examples:
        >>> base = compose_recipe(RECIPES_DIR / "drone" / "control.yaml", with_hydra=True)
        >>> with_additions(base, ["seed=1", "env.kwargs={delta: 0.1}", "hydra.verbose=true"])
        ['seed=1', '++env.kwargs={delta: 0.1}', 'hydra.verbose=true']
    """
    groups = set(base.hydra.runtime.choices) if "hydra" in base else set()
    out = []
    for text, o in zip(overrides, _parse(overrides), strict=True):
        plain = o.type.name == "CHANGE" and o.package is None and not o.is_hydra_override()
        if plain and o.key_or_group not in groups:
            absent = OmegaConf.select(base, o.key_or_group, default=_ABSENT) is _ABSENT
            if absent or (not o.is_sweep_override() and isinstance(o.value(), dict)):
                text = f"++{text}"  # add the key, or merge a mapping into a closed one
        out.append(text)
    return out


_ABSENT = object()


def sweep_jobs(
    base: DictConfig, overrides: Sequence[str], *, recipe_params: bool = True
) -> list[list[str]]:
    """The overrides of each job of a multirun: the product of every sweep, Hydra's basic way.

    Sweeps come from the command line (``seed=0,1``) and from the recipe's own
    ``hydra.sweeper.params`` (unless ``recipe_params`` is False, as for a single run; a
    command-line sweep of the same key wins). A job's list holds ``key=value`` for each swept
    key plus the other overrides unchanged. Sweeps that need the config to expand
    (``glob(...)``) are left to Hydra and checked by its jobs.

    Examples:
        >>> base = compose_recipe(RECIPES_DIR / "drone" / "explore_smoke.yaml", with_hydra=True)
        >>> sweep_jobs(base, ["seed=0,1", "threads=1"])
        [['threads=1', 'seed=0'], ['threads=1', 'seed=1']]
    """
    params = (
        dict(base.hydra.sweeper.get("params") or {}) if recipe_params and "hydra" in base else {}
    )
    fixed, swept = [], {}
    for text, o in zip(overrides, _parse(overrides), strict=True):
        if o.is_sweep_override() and not o.is_hydra_override():
            swept[text.split("=", 1)[0]] = o
        else:
            fixed.append(text)
        params.pop(o.key_or_group, None)
    from_recipe = {}
    for key, value in params.items():
        o = _parse([f"{key}={value}"])[0]
        if o.is_sweep_override():
            from_recipe[key] = o
        else:
            fixed.append(f"{key}={value}")
    values = []
    for key, o in {**from_recipe, **swept}.items():
        try:
            values.append([f"{key}={_text(v)}" for v in o.sweep_iterator()])
        except Exception:  # glob() and other sweeps that need the config: left to the jobs
            continue
    count = math.prod(len(v) for v in values)
    if count > MAX_SWEEP_JOBS:
        raise RecipeError(f"the sweep has {count} jobs; at most {MAX_SWEEP_JOBS} are checked.")
    return [[*fixed, *combo] for combo in itertools.product(*values)]


def _text(value: Any) -> str:
    """A sweep value written back as override text (strings quoted when they need it)."""
    if isinstance(value, str):
        return value if value.replace("_", "").replace("-", "").isalnum() else repr(value)
    return str(value).lower() if isinstance(value, bool) else str(value)
