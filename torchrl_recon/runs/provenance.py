"""What a result was made with: the installed package versions and the git commit of the code
(``meta.json`` of every run, the GPU report).

Examples:
    >>> sorted(package_versions(("torch",)))
    ['python', 'torch']
"""

from __future__ import annotations

import os
import platform
import subprocess
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

VERSION_PACKAGES = ("torch", "torchrl", "tensordict", "gymnasium", "numpy", "pybullet")
VERSION_PACKAGES += ("torchrl-recon", "hydra-core", "omegaconf", "wandb")
"""The packages whose versions ``meta.json`` records."""


def package_versions(names: Sequence[str] = VERSION_PACKAGES) -> dict[str, str | None]:
    """Installed versions (``importlib.metadata``) of ``names``, plus ``python``; None if absent."""
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def git_info(directory: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Commit and dirty flag of the git checkout holding ``directory`` (default: this package),
    read-only; ``{"commit": "unknown", "dirty": None}`` outside a checkout or without git."""
    cwd = Path(__file__).resolve().parent if directory is None else Path(directory)

    def git(*args: str) -> str | None:
        try:
            proc = subprocess.run(
                ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=20
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return proc.stdout if proc.returncode == 0 else None

    commit = (git("rev-parse", "HEAD") or "").strip()
    if not commit:
        return {"commit": "unknown", "dirty": None}
    status = git("--no-optional-locks", "status", "--porcelain")
    return {"commit": commit, "dirty": None if status is None else bool(status.strip())}
