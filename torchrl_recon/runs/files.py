"""Files of a run directory: written atomically, read back as plain data, checked by size and hash."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from torchrl_recon.errors import DamagedFileError

HASH_KEY = "_sha256"
"""The key under which a JSON record keeps the SHA-256 of the rest of its content."""


def write_atomically(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Call ``write`` on ``<path>.tmp`` beside ``path``, then rename it over ``path``.

    The rename is atomic on one file system, so readers (and a resumed run) see either the
    previous file or the complete new one.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "notes.txt"
        >>> write_atomically(path, lambda tmp: tmp.write_text("done")).read_text()
        'done'
        >>> sorted(p.name for p in path.parent.iterdir())  # no temporary file left behind
        ['notes.txt']
    """
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp")
    write(tmp)
    tmp.replace(path)
    return path


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes (read only).

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "x"
        >>> _ = path.write_bytes(b"abc")
        >>> sha256_file(path)[:12]
        'ba7816bf8f01'
    """
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def json_sha256(record: Mapping[str, Any]) -> str:
    """Hex SHA-256 of ``record`` as canonical JSON (sorted keys, no spaces), ``_sha256`` left out.

    The record is first passed through JSON (tuples become lists, keys strings), so the hash of
    a record equals the hash of the same record read back from its file.

    Examples:
        >>> json_sha256({"b": 1, "a": (2, 3)}) == json_sha256({"a": [2, 3], "b": 1})
        True
    """
    plain = json.loads(json.dumps({k: v for k, v in record.items() if k != HASH_KEY}))
    text = json.dumps(plain, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def with_hash(record: Mapping[str, Any]) -> dict[str, Any]:
    """``record`` plus its own SHA-256 under ``_sha256`` (see :func:`json_sha256`).

    Examples:
        >>> sorted(with_hash({"mse": 0.5}))
        ['_sha256', 'mse']
    """
    if HASH_KEY in record:
        raise ValueError(f"A record may not hold the reserved key {HASH_KEY!r}.")
    return {**record, HASH_KEY: json_sha256(record)}


def read_json(path: str | Path, *, remedy: str) -> Any:
    """Parse a JSON file; a missing, unreadable or malformed file is one :class:`DamagedFileError`.

    ``remedy`` (what to do) ends the message. JSON never runs code; this only turns the many
    ways a file can be damaged into one error that names it.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "r.json"
        >>> _ = path.write_text('{"x": 1}')
        >>> read_json(path, remedy="write it again.")
        {'x': 1}
    """
    path = Path(path)
    try:
        return json.loads(path.read_bytes())
    except FileNotFoundError:
        raise DamagedFileError(f"{path} is missing; {remedy}") from None
    except (OSError, ValueError) as err:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise DamagedFileError(f"{path} is not valid JSON ({reason}); {remedy}") from None


def read_record(path: str | Path, *, required: tuple[str, ...], remedy: str) -> dict[str, Any]:
    """Read a JSON record, check its own ``_sha256`` (when it has one) and its ``required`` keys.

    Returns the record without ``_sha256``. Records written before hashes were kept have none
    and are accepted as they are.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "r.json"
        >>> _ = path.write_text(json.dumps(with_hash({"mse": 0.5})))
        >>> read_record(path, required=("mse",), remedy="delete it.")
        {'mse': 0.5}
        >>> _ = path.write_text(path.read_text().replace("0.5", "999"))
        >>> read_record(path, required=("mse",), remedy="delete it.")
        Traceback (most recent call last):
        ...
        torchrl_recon.errors.DamagedFileError: ... does not match the SHA-256 it was written with ...
    """
    record = read_json(path, remedy=remedy)
    if not isinstance(record, dict):
        raise DamagedFileError(
            f"{path} holds a JSON {type(record).__name__}, not a record (an object); {remedy}"
        )
    saved = record.pop(HASH_KEY, None)
    if saved is not None and saved != json_sha256(record):
        raise DamagedFileError(
            f"{path} does not match the SHA-256 it was written with (edited or damaged); {remedy}"
        )
    missing = [k for k in required if k not in record]
    if missing:
        raise DamagedFileError(f"{path} has no {', '.join(map(repr, missing))}; {remedy}")
    return record


def file_entry(path: str | Path) -> dict[str, Any]:
    """``{"size": bytes, "sha256": hex}`` of a file, as a stage record lists it.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "x"
        >>> _ = path.write_bytes(b"abc")
        >>> file_entry(path)["size"]
        3
    """
    path = Path(path)
    return {"size": path.stat().st_size, "sha256": sha256_file(path)}


def verify_files(root: str | Path, files: Mapping[str, Any], *, owner: str, remedy: str) -> None:
    """Check that each ``root/<relative path>`` still has the size, then the SHA-256, listed.

    Sizes are compared first (cheap, and they catch truncation), then hashes. ``owner`` names
    who listed the files (e.g. ``"stage 'validation' (stages/validation.json)"``).

    Raises:
        DamagedFileError: one line naming the first file that differs, its owner and ``remedy``.
    """
    root = Path(root)
    if not isinstance(files, Mapping) or not all(
        isinstance(e, Mapping)
        and isinstance(e.get("size"), int)
        and isinstance(e.get("sha256"), str)
        for e in files.values()
    ):
        raise DamagedFileError(f"The file list of {owner} is malformed; {remedy}")
    inside = root.resolve()
    for rel in files:
        if not (inside / rel).resolve().is_relative_to(inside):
            raise DamagedFileError(f"{owner} lists {rel!r}, outside {root}; {remedy}")
    for rel, entry in files.items():
        path = root / rel
        if not path.is_file():
            raise DamagedFileError(f"{path} is missing ({owner} wrote it); {remedy}")
        size = path.stat().st_size
        if size != entry["size"]:
            raise DamagedFileError(
                f"{path} has {size} bytes, but {owner} wrote {entry['size']}; {remedy}"
            )
    for rel, entry in files.items():
        path = root / rel
        if sha256_file(path) != entry["sha256"]:
            raise DamagedFileError(
                f"{path} does not match the SHA-256 that {owner} recorded (changed after it was "
                f"written); {remedy}"
            )
