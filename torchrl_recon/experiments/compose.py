"""Compose a recipe with Hydra's own composition: defaults lists, config groups, sweeps; with the
shipped recipes on its search path (``defaults: [/drone/explore@_here_, _self_]`` anywhere)."""

from __future__ import annotations

import contextlib
import copy
import hashlib
import itertools
import math
import os
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import OverrideType
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from torchrl_recon.errors import RecipeError

RECIPES_DIR = Path(__file__).resolve().parents[1] / "recipes"
"""The recipes shipped in the package (``<env>/<kind>.yaml``; the checkout's ``recipes/``)."""
SEARCH_PATH = f"hydra.searchpath=[file://{RECIPES_DIR}]"  # the override that adds RECIPES_DIR
MAX_SWEEP_JOBS = 10_000
_ABSENT = object()

# The recipes' and the CLI's resolvers, registered by every import (a launcher's workers too).
for _name, _resolver in {
    # a gymnasium id as a run's name: without its ``module:`` prefix, "/" as "_"
    "trr_env_name": lambda i: None if i is None else str(i).rpartition(":")[2].replace("/", "_"),
    "trr_parent": lambda p: str(Path(str(p)).parent),
    "trr_abspath": lambda p: str(Path(str(p)).expanduser().resolve()),
}.items():
    OmegaConf.register_new_resolver(_name, _resolver, replace=True)


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


def compose_recipe(
    path: str | Path, overrides: Sequence[str] = (), *, with_hydra: bool = False
) -> DictConfig:
    """The config Hydra composes from the recipe file ``path`` and ``overrides`` (no sweeps),
    with its ``hydra`` node if ``with_hydra``; inside a running Hydra app too. Raises
    FileNotFoundError, or a RecipeError naming the file.

    A composition is kept (each call gets its own copy) while nothing it was made from changed:
    the YAML files of its config directories (by content), the working directory, Hydra's
    ``ConfigStore`` and the variables of ``hydra.job.env_copy``; so the CLI's precheck, its jobs
    and a calibrate recipe's outcome recipes compose each recipe once, not once per look.

    Examples:
        >>> cfg = compose_recipe(RECIPES_DIR / "drone" / "explore_smoke.yaml", ["seed=3"])
        >>> cfg.env.name, cfg.seed
        ('drone', 3)
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"Recipe file not found: {path}")
    key = (str(path.resolve()), tuple(overrides), os.getcwd())
    kept = _COMPOSED.get(key)
    if kept is not None and _inputs(*kept["made_of"]) == kept["inputs"]:
        _COMPOSED.move_to_end(key)
        if not with_hydra and "bare" not in kept:
            kept["bare"] = _without_hydra(copy.deepcopy(kept["with_hydra"]))
        return copy.deepcopy(kept["with_hydra" if with_hydra else "bare"])
    running = GlobalHydra.instance().hydra  # a running app's (a job loading another recipe)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(str(path.resolve().parent), version_base="1.3"):
            cfg = compose(path.stem, [SEARCH_PATH, *overrides], return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as e:
        raise RecipeError(f"{path}: {hydra_error_message(e)}") from e
    finally:
        GlobalHydra.instance().hydra = running
    sources = cfg.hydra.runtime.config_sources
    folders = tuple(str(s.path) for s in sources if s.schema == "file")
    made_of = (folders, tuple(cfg.hydra.job.env_copy), _store_nodes())
    if (inputs := _inputs(*made_of)) is not None:
        _COMPOSED[key] = {"with_hydra": copy.deepcopy(cfg), "made_of": made_of, "inputs": inputs}
        while len(_COMPOSED) > _KEPT:
            _COMPOSED.popitem(last=False)
    return cfg if with_hydra else _without_hydra(cfg)


def _without_hydra(cfg: DictConfig) -> DictConfig:
    """``cfg`` without its ``hydra`` node, as Hydra's ``compose`` returns it by default."""
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


_KEPT = 64  # compositions kept (the least recently used goes first)
_MAX_FILES = 2000  # files (of any kind) in a config directory beyond which it is not kept
_COMPOSED: OrderedDict[tuple, dict[str, Any]] = OrderedDict()


def _store_nodes() -> tuple:
    """Every node of Hydra's ``ConfigStore`` (the objects: one stored again is another)."""
    nodes, stack = [], [ConfigStore.instance().repo]
    while stack:
        for value in stack.pop().values():
            (stack.append if isinstance(value, dict) else nodes.append)(value)
    return tuple(nodes)


def _inputs(folders: tuple, env_keys: tuple, nodes: tuple) -> tuple | None:
    """What a composition was made from, as it is now: a digest of the YAML files (names and
    bytes) under ``folders``, the ``env_keys`` variables and whether the ConfigStore holds the
    same ``nodes``; None (not to be kept) if a folder holds too many files or a linked folder."""
    digest, count = hashlib.blake2b(digest_size=20), 0
    for folder in folders:
        for root, dirs, files in os.walk(folder):
            count += len(files)
            if count > _MAX_FILES or any(os.path.islink(os.path.join(root, d)) for d in dirs):
                return None
            dirs.sort()
            for name in sorted(f for f in files if f.endswith((".yaml", ".yml"))):
                file = os.path.join(root, name)
                digest.update(file.encode() + b"\0")
                with contextlib.suppress(OSError), open(file, "rb") as f:
                    digest.update(f.read())
                digest.update(b"\0")
    env = tuple(os.environ.get(k) for k in env_keys)
    store = _store_nodes()
    same_store = len(store) == len(nodes) and all(a is b for a, b in zip(store, nodes, strict=True))
    return digest.digest(), env, same_store


def _parse(overrides: Sequence[str]) -> list[Any]:
    """Hydra's own parse of each override (its key, type, sweep)."""
    try:
        return OverridesParser.create().parse_overrides(list(overrides))
    except HydraException as e:  # OverrideParseException
        raise RecipeError(
            f"cannot parse the overrides {list(overrides)}: {str(e).strip().splitlines()[0]} "
            "(Hydra's override syntax: key=value, +key=value, ~key; quote values holding "
            "spaces or brackets)"
        ) from e


def with_additions(base: DictConfig, overrides: Sequence[str]) -> list[str]:
    """``overrides`` with ``++`` before each ``key=value`` Hydra would refuse: a key the recipe
    lacks (the schema refuses what is not a field), or a mapping merged into one of the recipe's.

    Examples:
        >>> base = compose_recipe(RECIPES_DIR / "drone" / "control.yaml", with_hydra=True)
        >>> with_additions(base, ["seed=1", "env.kwargs={delta: 0.1}", "hydra.verbose=true"])
        ['seed=1', '++env.kwargs={delta: 0.1}', 'hydra.verbose=true']
    """
    groups = set(base.hydra.runtime.choices) if "hydra" in base else set()
    out = []
    for text, o in zip(overrides, _parse(overrides), strict=True):
        plain = o.type == OverrideType.CHANGE and o.package is None and not o.is_hydra_override()
        if plain and o.key_or_group not in groups:
            absent = OmegaConf.select(base, o.key_or_group, default=_ABSENT) is _ABSENT
            if absent or (not o.is_sweep_override() and isinstance(o.value(), dict)):
                text = f"++{text}"
        out.append(text)
    return out


def _is_sweep(o: Any) -> bool:
    return o.is_sweep_override() and not o.is_hydra_override()


def sweep_jobs(
    base: DictConfig, overrides: Sequence[str], *, recipe_params: bool = True
) -> list[list[str]]:
    """Each job's overrides: the product of the sweeps, as Hydra's basic sweeper makes them, of
    the command line (made :func:`with_additions`) and (``recipe_params``) of
    ``hydra.sweeper.params``, the command line's first; ``glob(...)`` and other sweeps that need
    the config are left to Hydra's jobs.

    Examples:
        >>> base = compose_recipe(RECIPES_DIR / "drone" / "explore_smoke.yaml", with_hydra=True)
        >>> sweep_jobs(base, ["seed=0,1", "threads=1"])
        [['threads=1', 'seed=0'], ['threads=1', 'seed=1']]
    """
    given = list(zip(with_additions(base, overrides), _parse(overrides), strict=True))
    params = (base.hydra.sweeper.get("params") or {}) if recipe_params and "hydra" in base else {}
    keys = {o.key_or_group for _, o in given}  # the command line's win over the recipe's
    texts = [f"{key}={value}" for key, value in params.items() if key not in keys]
    recipe = list(zip(texts, _parse(texts), strict=True))
    fixed = [text for text, o in given + recipe if not _is_sweep(o)]
    sweeps = {text.split("=", 1)[0]: o for text, o in recipe + given if _is_sweep(o)}
    values = []
    for key, o in sweeps.items():
        with contextlib.suppress(HydraException):  # glob() and the like: left to the jobs
            values.append([f"{key}={v}" for v in o.sweep_string_iterator()])
    count = math.prod(len(v) for v in values)
    if count > MAX_SWEEP_JOBS:
        raise RecipeError(f"the sweep has {count} jobs; at most {MAX_SWEEP_JOBS} are checked.")
    return [[*fixed, *combo] for combo in itertools.product(*values)]
