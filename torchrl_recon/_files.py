"""Write a file so that a run killed mid-write leaves the old file or none, never a torn one."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


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
