"""Run directories: prepare the output directory of one run, refuse a conflicting one, store results.

A run directory holds one run (one seed): its resolved ``config.yaml``, ``meta.json`` (versions,
git commit, host, time, command line), the stage outputs written by the experiment,
``results.json`` and the figures. Recipes are loaded and checked by :mod:`.recipe`.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import socket
import subprocess
import sys
from collections.abc import Iterable, Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_recon.errors import DamagedFileError
from torchrl_recon.files import read_json, write_atomically

RESUME_IGNORED_KEYS = ("progress", "stop_after", "logger", "output_dir")
# Keys added to the schema since runs were first published, with the value that reproduces the
# behaviour from before the key existed: a run directory without the key resumes when the new
# config holds that value.
KEYS_ADDED_SINCE: dict[str, Any] = {"training.window_sampling": "trajectory"}
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


class RunDirConflict(RuntimeError):
    """The run directory holds a run made with a different configuration."""


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
    """Keys (flattened) whose values differ between two configs, ignoring :data:`RESUME_IGNORED_KEYS`.

    A key the old config lacks and the new one holds as null (a schema key added since, at its
    null default, e.g. ``env.id``), or at its value in :data:`KEYS_ADDED_SINCE`, is no
    difference.

    Examples:
        >>> config_differences({"env": {"name": "drone"}}, {"env": {"name": "drone", "id": None}})
        []
    """

    def keep(key: str) -> bool:
        return key.split(".", 1)[0] not in RESUME_IGNORED_KEYS

    a = {k: v for k, v in _flatten(dict(old)).items() if keep(k)}
    b = {k: v for k, v in _flatten(dict(new)).items() if keep(k)}
    diffs = []
    for key in sorted(set(a) | set(b)):
        if key not in a:
            if b[key] is None or (key in KEYS_ADDED_SINCE and b[key] == KEYS_ADDED_SINCE[key]):
                continue
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
    info: dict[str, Any] = {"commit": "unknown", "dirty": None}

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
    write_atomically(path, lambda tmp: tmp.write_text(text))


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
    if not (run_dir / "config.yaml").exists():
        return new
    saved = read_config(run_dir)
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
    except (RunDirConflict, DamagedFileError):
        release_run_dir(run_dir)
        raise
    config_path = run_dir / "config.yaml"
    resumed = config_path.exists()
    meta_path = run_dir / "meta.json"
    previous: list[dict[str, Any]] = []
    if resumed and meta_path.exists():
        try:  # read before anything is written: a refused resume changes no file
            old_meta = read_meta(run_dir)
        except DamagedFileError:
            release_run_dir(run_dir)
            raise
        previous = list(old_meta.get("previous") or [])
        previous.append({k: old_meta.get(k) for k in ("started_utc", "git", "argv", "hostname")})
    _atomic_write(config_path, OmegaConf.to_yaml(OmegaConf.create(new)))

    meta = {
        "experiment": cfg.experiment,
        "env": cfg.env.name,
        "seed": int(cfg.seed),
        "run_dir": str(cfg.output_dir),  # as configured: no machine path in shared results
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
    if (run_dir / "meta.json").exists():
        meta = read_meta(run_dir)
    meta["finished_utc"] = _utc_now()
    payload = {**dict(results), "meta": meta}
    path = run_dir / "results.json"
    _atomic_write(path, json.dumps(payload, indent=1, default=_json_default))
    return path


def read_config(run_dir: str | os.PathLike[str]) -> DictConfig:
    """The ``config.yaml`` of a run directory, read as plain YAML (never runs code).

    Keys added to the experiment's schema after the run was made are filled with their defaults.

    Raises:
        FileNotFoundError: the directory has no ``config.yaml``.
        DamagedFileError: the file is not a YAML mapping that fits the experiment's schema.
    """
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"{Path(run_dir)} is not a run directory (no config.yaml).")
    remedy = (
        "it is the resolved recipe of the run; restore it, or delete the run directory to start "
        "over."
    )
    try:
        saved = OmegaConf.load(path)  # a YAML safe loader: tags such as !!python/object are refused
    except Exception as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DamagedFileError(f"{path} is not valid YAML ({reason}); {remedy}") from None
    if not isinstance(saved, DictConfig):
        raise DamagedFileError(f"{path} holds a YAML list, not a mapping; {remedy}")
    # Imported here: the registry imports the experiments, which import this module.
    from torchrl_recon.experiments.config import upgrade_legacy_config
    from torchrl_recon.experiments.registry import EXPERIMENT_TYPES

    saved = upgrade_legacy_config(saved)  # planner blocks written flat, before `kwargs`
    kind = EXPERIMENT_TYPES.get(saved.get("experiment"))
    if kind is not None:
        # Keys added to the schema after the run was made compare at their defaults.
        try:
            saved = OmegaConf.merge(OmegaConf.structured(kind.schema), saved)
        except Exception as err:
            reason = str(err).strip().splitlines()[0]
            raise DamagedFileError(
                f"{path} does not fit the {saved.get('experiment')!r} schema ({reason}); {remedy}"
            ) from None
    return saved


def read_meta(run_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``meta.json`` of a run directory (versions, git commit, host, command lines).

    Raises:
        DamagedFileError: the file is missing, not JSON or not a JSON object.
    """
    path = Path(run_dir) / "meta.json"
    remedy = (
        "it only records how and where the run was made: delete it to resume (the record of "
        "earlier starts is lost)."
    )
    meta = read_json(path, remedy=remedy)
    if not isinstance(meta, dict) or not isinstance(meta.get("previous", []), list):
        raise DamagedFileError(f"{path} is not the JSON object meta.json holds; {remedy}")
    return meta


def read_results(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a ``results.json`` file (or the one inside a run directory) as plain JSON.

    Raises:
        FileNotFoundError: there is no such file.
        DamagedFileError: the file is not JSON, or not the results of an experiment.

    Examples:
        >>> import tempfile
        >>> run_dir = Path(tempfile.mkdtemp())
        >>> _ = write_results(run_dir, {"experiment": "explore", "env": "drone", "seed": 0})
        >>> read_results(run_dir)["env"]
        'drone'
    """
    path = Path(path)
    if path.is_dir():
        path = path / "results.json"
    if not path.is_file():
        raise FileNotFoundError(f"No results file at {path}.")
    remedy = "re-run the experiment to write it again, or leave that run directory out."
    results = read_json(path, remedy=remedy)
    if not isinstance(results, dict) or not isinstance(results.get("experiment"), str):
        raise DamagedFileError(
            f"{path} is not the results of an experiment (no 'experiment'); {remedy}"
        )
    return results
