"""Published results, packed: one compressed archive of records per experiment folder, and a
SHA-256 manifest that ``summarize`` verifies.

A published experiment folder (``docs/results/<experiment>/``) keeps per run what is read
directly: ``results.json``, ``config.yaml``, ``meta.json`` and the figures the docs show. Every
other file (stage and part records, the other figures) is a member of ``records.tar.xz`` beside
:data:`MANIFEST` (``records_manifest.json``), which lists the SHA-256 of each member and of each
run's ``results.json``, by their paths relative to the folder.

Reading an archive never runs code and never writes a file: members are read into memory one
by one (no ``extractall``); a member that is not a regular file (a link, a device, a folder),
whose name is absolute or climbs out with ``..``, that is not in the manifest or does not match
its hash is one :class:`~torchrl_recon.errors.DamagedFileError`.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import tarfile
from collections.abc import Iterable, Mapping
from pathlib import Path, PurePosixPath
from typing import Any

from torchrl_recon.errors import DamagedFileError
from torchrl_recon.runs.files import read_json, sha256_file, write_atomically

ARCHIVE = "records.tar.xz"
"""The archive's file name inside an experiment folder."""

MANIFEST = "records_manifest.json"
"""The manifest's file name beside the archive."""

ABOUT = (
    "SHA-256 of each member of records.tar.xz (members) and of each run's results.json "
    "(results), by their paths relative to this folder; checked by `torchrl-recon summarize`."
)

_REMEDY = "restore the folder from git (`git checkout -- <folder>`) or publish the runs again"


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 of ``data``.

    Examples:
        >>> sha256_bytes(b"abc")[:12]
        'ba7816bf8f01'
    """
    return hashlib.sha256(data).hexdigest()


def member_name(name: str) -> str:
    """``name`` if it is a safe relative POSIX path inside the folder, else a DamagedFileError.

    Examples:
        >>> member_name("drone/seed0/stages/models.json")
        'drone/seed0/stages/models.json'
        >>> member_name("../etc/passwd")
        Traceback (most recent call last):
        ...
        torchrl_recon.errors.DamagedFileError: member '../etc/passwd' is not a plain relative path ...
    """
    path = PurePosixPath(name)
    if (
        not name
        or "\\" in name
        or path.is_absolute()
        or any(part in ("..", ".", "") for part in name.split("/"))
    ):
        raise DamagedFileError(
            f"member {name!r} is not a plain relative path inside its folder; {_REMEDY}."
        )
    return name


def pack(
    folder: str | os.PathLike[str], members: Mapping[str, bytes], results: Mapping[str, str]
) -> tuple[Path, Path]:
    """Write ``folder/records.tar.xz`` holding ``members`` and its manifest.

    The archive is reproducible: members sorted by name, with mode 0644, time 0 and no owner,
    so the same members give the same bytes.

    Args:
        folder: the experiment folder.
        members: ``{relative path: content}`` of the files to pack.
        results: ``{relative path of a results.json: its SHA-256}``.

    Returns:
        The paths of the archive and the manifest.
    """
    folder = Path(folder)
    names = sorted(member_name(n) for n in members)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:xz", format=tarfile.PAX_FORMAT, preset=6) as tar:
        for name in names:
            data = members[name]
            info = tarfile.TarInfo(name)
            info.size, info.mode, info.mtime = len(data), 0o644, 0
            tar.addfile(info, io.BytesIO(data))
    manifest = {
        "about": ABOUT,
        "archive": ARCHIVE,
        "members": {n: sha256_bytes(members[n]) for n in names},
        "results": {member_name(k): results[k] for k in sorted(results)},
    }
    archive = write_atomically(folder / ARCHIVE, lambda tmp: tmp.write_bytes(buffer.getvalue()))
    text = json.dumps(manifest, indent=1) + "\n"
    return archive, write_atomically(folder / MANIFEST, lambda tmp: tmp.write_text(text))


def read_manifest(folder: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest of ``folder``, its structure checked (plain JSON, never code)."""
    path = Path(folder) / MANIFEST
    manifest = read_json(path, remedy=f"{_REMEDY}.")
    ok = isinstance(manifest, dict) and all(
        isinstance(manifest.get(k), dict)
        and all(isinstance(v, str) and len(v) == 64 for v in manifest[k].values())
        for k in ("members", "results")
    )
    if not ok or manifest.get("archive") != ARCHIVE:
        raise DamagedFileError(
            f"{path} is not a records manifest (archive, members and results with SHA-256s); "
            f"{_REMEDY}."
        )
    for name in (*manifest["members"], *manifest["results"]):
        member_name(name)
    return manifest


def read_members(folder: str | os.PathLike[str]) -> dict[str, bytes]:
    """Every member of ``folder``'s archive, read into memory and checked against the manifest.

    Raises:
        DamagedFileError: the archive is not a readable tar.xz, holds a member that is not a
            regular file or has an unsafe name, holds one twice, holds one the manifest does not
            list or lacks one it lists, or a member's SHA-256 differs.
    """
    folder = Path(folder)
    manifest = read_manifest(folder)
    path = folder / ARCHIVE
    return dict(_read_members(str(path.resolve()), _stamp(path), json.dumps(manifest["members"])))


def _stamp(path: Path) -> tuple[int, int]:
    try:
        stat = path.stat()
    except FileNotFoundError:
        raise DamagedFileError(f"{path} is missing (its manifest lists it); {_REMEDY}.") from None
    return stat.st_mtime_ns, stat.st_size


@functools.lru_cache(maxsize=2)
def _read_members(path: str, _stamp: tuple[int, int], listed_json: str) -> tuple:
    listed: dict[str, str] = json.loads(listed_json)
    found: dict[str, bytes] = {}
    try:
        with tarfile.open(path, mode="r:xz") as tar:
            for info in tar:
                name = member_name(info.name)
                if not info.isreg():
                    raise DamagedFileError(
                        f"{path}: member {name!r} is not a regular file (a link, folder or "
                        f"device); {_REMEDY}."
                    )
                if name in found:
                    raise DamagedFileError(f"{path}: member {name!r} is there twice; {_REMEDY}.")
                if name not in listed:
                    raise DamagedFileError(
                        f"{path}: member {name!r} is not in its manifest {MANIFEST}; {_REMEDY}."
                    )
                data = tar.extractfile(info).read()
                if sha256_bytes(data) != listed[name]:
                    raise DamagedFileError(
                        f"{path}: member {name!r} does not match the SHA-256 in {MANIFEST}; "
                        f"{_REMEDY}."
                    )
                found[name] = data
    except (tarfile.TarError, EOFError, OSError) as err:  # lzma.LZMAError is an OSError
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise DamagedFileError(
            f"{path} is not a readable tar.xz archive ({reason}); {_REMEDY}."
        ) from None
    missing = sorted(set(listed) - set(found))
    if missing:
        raise DamagedFileError(
            f"{path} lacks {len(missing)} member(s) its manifest lists, e.g. {missing[0]!r}; "
            f"{_REMEDY}."
        )
    return tuple(found.items())


def folder_of(path: str | os.PathLike[str]) -> Path | None:
    """The nearest folder at or above ``path`` that holds a records manifest, or None.

    Examples:
        >>> import tempfile
        >>> folder_of(tempfile.mkdtemp()) is None
        True
    """
    path = _absolute(path)
    for folder in (path, *path.parents):
        if (folder / MANIFEST).is_file():
            return folder
    return None


def _absolute(path: str | os.PathLike[str]) -> Path:
    return Path(os.path.abspath(path))


def _relative(path: Path, folder: Path) -> str:
    return _absolute(path).relative_to(_absolute(folder)).as_posix()


def verify_results(files: Iterable[str | os.PathLike[str]]) -> list[dict[str, Any]]:
    """Check the published ``results.json`` files among ``files``: for each archive above one,
    all its members against the manifest, and each file's SHA-256 against the manifest's.

    Files with no manifest above them (a run directory) are left alone.

    Returns:
        One entry per archive checked: ``{"archive": path, "members": n, "results": n}``
        (the path as the files were given: relative when they were).

    Raises:
        DamagedFileError: a member or a ``results.json`` differs from the manifest, or a
            ``results.json`` is not listed in it (publish it with ``publish_run.py``).
    """
    by_folder: dict[Path, list[Path]] = {}
    shown: dict[Path, Path] = {}
    for f in map(Path, files):
        folder = folder_of(f.parent)
        if folder is not None:
            by_folder.setdefault(folder, []).append(f)
            shown.setdefault(folder, _shown_folder(f, folder))
    checked = []
    for folder, results in sorted(by_folder.items()):
        manifest = read_manifest(folder)
        members = read_members(folder)
        for f in results:
            rel = _relative(f, folder)
            recorded = manifest["results"].get(rel)
            if recorded is None:
                raise DamagedFileError(
                    f"{f} is not listed in {shown[folder] / MANIFEST}; publish it with "
                    "docs/results/publish_run.py, which adds it."
                )
            if sha256_file(f) != recorded:
                raise DamagedFileError(
                    f"{f} does not match the SHA-256 recorded in {shown[folder] / MANIFEST} "
                    f"(changed after it was published); {_REMEDY}."
                )
        checked.append(
            {
                "archive": (shown[folder] / ARCHIVE).as_posix(),
                "members": len(members),
                "results": len(results),
            }
        )
    return checked


def _shown_folder(file: Path, folder: Path) -> Path:
    """``folder`` written the way ``file`` was: relative to the current folder when it was."""
    return folder if file.is_absolute() else Path(os.path.relpath(folder))


def run_records(run_dir: str | os.PathLike[str]) -> dict[str, bytes]:
    """The files of a published run kept in its folder's archive, by their path inside the run
    (``stages/models.json``, ...); empty when there is no archive above ``run_dir``."""
    run_dir = Path(run_dir)
    folder = folder_of(run_dir)
    if folder is None:
        return {}
    prefix = _relative(run_dir, folder) + "/"
    if prefix == "./":
        prefix = ""
    return {
        name[len(prefix) :]: data
        for name, data in read_members(folder).items()
        if name.startswith(prefix)
    }
