"""A run directory (one seed): ``config.yaml``, ``meta.json``, stage outputs, ``results.json``."""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import socket
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from filelock import FileLock, Timeout
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_recon.errors import DamagedFileError
from torchrl_recon.experiments.compose import RECIPES_DIR
from torchrl_recon.runs.files import read_json, write_atomically
from torchrl_recon.runs.provenance import git_info, package_versions

RESUME_IGNORED_KEYS = ("progress", "stop_after", "logger", "output_dir")
"""Top-level keys that may change between a run and its resumption (they do not change results)."""
KEYS_ADDED_SINCE: dict[str, Any] = {
    "training.window_sampling": "trajectory",
    "training.short_episodes": "pad_if_no_window",  # runs before it left ended short ones out
    "warmup": "auto",
    "refit_uncertainty": "always",  # online runs before it refitted the estimator every time
    "renormalize": False,  # online runs before it kept the first fit's statistics
    "reward_model.hidden_size": 64,  # (no run before it learned the reward)
    "reward_model.layers": 2,
    "reward_model.activation": "relu",
}
"""Keys added to the schema since, with the value an older run directory without them ran at
(:func:`read_config` reads them so; a new default other than that is a difference)."""
_START_KEYS = ("started_utc", "git", "argv", "hostname")
"""What ``meta.json`` keeps of each earlier start of a resumed run."""
_LOCKS: dict[str, FileLock] = {}
_ABSENT = object()
_PLAIN_VALUE = re.compile(r"[\w.:/+-]+")  # an override value Hydra reads without quotes


class RunDirConflict(RuntimeError):
    """The run directory holds a run made with a different configuration, or is in use."""


def flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Flatten nested dicts / lists into ``{"a.b.0.c": value}`` (empty ones kept as values)."""
    if not isinstance(obj, (Mapping, list, tuple)) or (not obj and prefix):
        return {prefix: obj}
    out: dict[str, Any] = {}
    for k, v in obj.items() if isinstance(obj, Mapping) else enumerate(obj):
        out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def config_differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """Keys (flattened) whose values differ between two configs, :data:`RESUME_IGNORED_KEYS` aside;
    a key new since the old one is no difference at null or at its :data:`KEYS_ADDED_SINCE` value.

    Examples:
        >>> config_differences({"env": {"name": "drone"}}, {"env": {"name": "drone", "id": None}})
        []
        >>> config_differences({"seed": 0, "logger": {"backend": "csv"}}, {"seed": 1})
        ['seed: 0 -> 1']
    """
    keep = [{k: v for k, v in dict(c).items() if k not in RESUME_IGNORED_KEYS} for c in (old, new)]
    a, b = map(flatten, keep)
    diffs = []
    for key in sorted(set(a) | set(b)):
        before, after = a.get(key, _ABSENT), b.get(key, _ABSENT)
        if before is _ABSENT and after in (None, KEYS_ADDED_SINCE.get(key, _ABSENT)):
            continue
        if before is _ABSENT or after is _ABSENT or before != after:
            shown = ["(absent)" if v is _ABSENT else repr(v) for v in (before, after)]
            diffs.append(f"{key}: {shown[0]} -> {shown[1]}")
    return diffs


def portable_path(path: str | os.PathLike[str]) -> str:
    """``path`` with no machine path: a relative path as given, a shipped recipe by its name, a
    path inside the working directory relative to it, any other absolute path by its last part.

    Examples:
        >>> portable_path("out/run"), portable_path(Path.cwd() / "out" / "run")
        ('out/run', 'out/run')
        >>> portable_path(RECIPES_DIR / "drone" / "explore.yaml"), portable_path("/elsewhere/run")
        ('drone/explore.yaml', 'run')
    """
    p, cwd = Path(path), Path.cwd()
    if not p.is_absolute():
        return str(path)
    if p.resolve().is_relative_to(RECIPES_DIR):
        return p.resolve().relative_to(RECIPES_DIR).as_posix()
    return p.relative_to(cwd).as_posix() if p.is_relative_to(cwd) and p != cwd else p.name


def portable_argv(argv: Sequence[str]) -> list[str]:
    """A command line with each absolute path, alone or as a ``key=value``'s value, made
    :func:`portable_path`.

    Examples:
        >>> portable_argv(["torchrl-recon", "explore", "x.yaml", "output_dir=/scratch/run/seed3"])
        ['torchrl-recon', 'explore', 'x.yaml', 'output_dir=seed3']
    """
    split = (str(item).rpartition("=") for item in argv)  # ("", "", item) without a "="
    return [f"{k}{eq}{portable_path(v) if v.startswith('/') else v}" for k, eq, v in split]


def _write(path: Path, text: str) -> Path:
    return write_atomically(path, lambda tmp: tmp.write_text(text))


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def release_run_dir(run_dir: str | os.PathLike[str]) -> None:
    """Release the lock taken by :func:`prepare_run_dir` (also released when the process exits)."""
    if (lock := _LOCKS.pop(str(Path(run_dir).resolve()), None)) is not None:
        lock.release(force=True)


def check_run_dir(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as a dict; :class:`RunDirConflict` naming the keys that differ from
    ``<output_dir>/config.yaml`` beyond :data:`RESUME_IGNORED_KEYS`."""
    new = OmegaConf.to_container(cfg, resolve=True)
    run_dir = Path(cfg.output_dir).expanduser().resolve()
    if not (run_dir / "config.yaml").exists():
        return new
    old = OmegaConf.to_container(read_config(run_dir))
    if diffs := config_differences(old, new):
        shown = "\n  ".join(diffs[:20]) + ("\n  ..." if len(diffs) > 20 else "")
        raise RunDirConflict(
            f"{run_dir} already holds a run with a different configuration (its config.yaml):"
            f"\n  {shown}\nResuming it with this config would mix results. Use another "
            "output_dir, restore config.yaml if it was damaged, or delete the directory to "
            "start over"
            + resume_overrides(old, [d.split(": ", 1)[0] for d in diffs])
            + ". (Only progress, stop_after and logger may change between a run and its "
            "resumption.)"
        )
    return new


def resume_overrides(old: Mapping[str, Any], keys: Sequence[str]) -> str:
    """``", or resume it as it was made with key=value ..."`` for the ``keys`` (flattened) whose
    old values are plain scalars, in Hydra's override syntax; empty when none is.

    Examples:
        >>> resume_overrides({"warmup": "random", "seed": 0, "env": {"kwargs": {}}},
        ...     ["warmup", "env.kwargs", "seed"])
        ', or resume it as it was made with warmup=random seed=0'
    """
    flat, found = flatten(dict(old)), []
    for key in keys:
        value = flat.get(key, [])
        if isinstance(value, bool) or value is None:
            found.append(f"{key}={'null' if value is None else str(value).lower()}")
        elif isinstance(value, (str, int, float)):
            text = str(value)
            found.append(f"{key}={text if _PLAIN_VALUE.fullmatch(text) else repr(text)}")
    return ", or resume it as it was made with " + " ".join(found) if found else ""


def prepare_run_dir(
    cfg: DictConfig, argv: Sequence[str] | None = None, extra_meta: Mapping[str, Any] | None = None
) -> Path:
    """Lock and create ``cfg.output_dir``, write ``config.yaml`` and ``meta.json`` (a resumed
    run's earlier starts under ``previous``); return its path. :class:`RunDirConflict` when
    another process runs in it or (:func:`check_run_dir`) it holds another configuration."""
    run_dir = Path(cfg.output_dir).expanduser().resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    if str(run_dir) not in _LOCKS:  # an flock: a second process on the directory is refused
        try:
            (lock := FileLock(run_dir / ".lock", timeout=0)).acquire()
        except Timeout as e:
            raise RunDirConflict(
                f"Another process is running in {run_dir}. Give each run its own output_dir "
                "(e.g. interpolate ${seed} in it when sweeping seeds)."
            ) from e
        _LOCKS[str(run_dir)] = lock
    try:
        new = check_run_dir(cfg)
        resumed = (run_dir / "config.yaml").exists()
        previous: list[dict[str, Any]] = []
        if resumed and (run_dir / "meta.json").exists():  # read before anything is written
            old = read_meta(run_dir)
            previous = [*(old.get("previous") or []), {k: old.get(k) for k in _START_KEYS}]
    except (RunDirConflict, DamagedFileError):
        release_run_dir(run_dir)
        raise
    _write(run_dir / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(new)))
    previous = [{**s, "argv": portable_argv(s["argv"])} if s.get("argv") else s for s in previous]
    extra = dict(extra_meta or {})
    if "job_overrides" in extra:
        extra["job_overrides"] = portable_argv(extra["job_overrides"])
    meta = {
        "experiment": cfg.experiment,
        "env": cfg.env.name,
        "seed": int(cfg.seed),
        "run_dir": portable_path(cfg.output_dir),
        "versions": package_versions(),
        "git": git_info(),
        "hostname": socket.gethostname(),
        "started_utc": _utc_now(),
        "argv": portable_argv(sys.argv if argv is None else argv),
        "resumed": resumed,
        "previous": previous,
        **extra,
    }
    commit = meta["git"]["commit"]
    before = (previous[-1].get("git") or {}).get("commit", commit) if previous else commit
    if before != commit:
        print(
            f"warning: {run_dir} was started at commit {before} and is resumed at {commit}.",
            file=sys.stderr,
        )
    _write(run_dir / "meta.json", json.dumps(meta, indent=1))
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
    """Write ``results.json``: ``results`` plus ``meta`` (``meta.json``, with the finish time);
    non-finite floats as JSON ``NaN`` / ``Infinity`` (Python's ``json`` reads them)."""
    run_dir = Path(run_dir)
    meta = read_meta(run_dir) if (run_dir / "meta.json").exists() else {}
    meta["finished_utc"] = _utc_now()
    text = json.dumps({**results, "meta": meta}, indent=1, default=_json_default)
    return _write(run_dir / "results.json", text)


def read_config(run_dir: str | os.PathLike[str]) -> DictConfig:
    """The ``config.yaml`` of a run directory as plain YAML (never runs code), keys added to its
    schema since at their defaults; :class:`DamagedFileError` when it does not fit the schema."""
    # Imported here: the registry imports the experiments, which import this module.
    from torchrl_recon.experiments.config import upgrade_legacy_config
    from torchrl_recon.experiments.registry import EXPERIMENT_TYPES

    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"{Path(run_dir)} is not a run directory (no config.yaml).")
    remedy = "it is the resolved recipe of the run; restore it, or delete the run directory to "
    remedy += "start over."
    try:
        saved = OmegaConf.load(path)  # a YAML safe loader: tags such as !!python/object are refused
    except Exception as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DamagedFileError(f"{path} is not valid YAML ({reason}); {remedy}") from None
    if not isinstance(saved, DictConfig):
        raise DamagedFileError(f"{path} holds a YAML list, not a mapping; {remedy}")
    saved = upgrade_legacy_config(saved)  # planner blocks written flat, before `kwargs`
    if (kind := EXPERIMENT_TYPES.get(saved.get("experiment"))) is None:
        return saved
    schema = OmegaConf.structured(kind.schema)
    for key, value in KEYS_ADDED_SINCE.items():  # as the run was made, where the key is the kind's
        if OmegaConf.select(saved, key, default=_ABSENT) is _ABSENT:
            if OmegaConf.select(schema, key, default=_ABSENT) is not _ABSENT:
                OmegaConf.update(saved, key, value, force_add=True)
    try:  # other keys added to the schema after the run was made compare at their defaults
        return OmegaConf.merge(schema, saved)
    except Exception as err:
        reason = str(err).strip().splitlines()[0]
        raise DamagedFileError(
            f"{path} does not fit the {saved.get('experiment')!r} schema ({reason}); {remedy}"
        ) from None


def read_meta(run_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``meta.json`` of a run directory; :class:`DamagedFileError` when missing or malformed."""
    path = Path(run_dir) / "meta.json"
    remedy = "it only records how and where the run was made: delete it to resume (the record of "
    remedy += "earlier starts is lost)."
    meta = read_json(path, remedy=remedy)
    if not isinstance(meta, dict) or not isinstance(meta.get("previous", []), list):
        raise DamagedFileError(f"{path} is not the JSON object meta.json holds; {remedy}")
    return meta
