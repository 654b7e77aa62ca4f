"""Resumable experiment stages: each stage writes its outputs and a checked record; a re-run skips it."""

from __future__ import annotations

import json
import shutil
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_recon.data import load_buffer_data, make_sequence_buffer, save_buffer
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.runs.files import (
    HASH_KEY,
    file_entry,
    read_record,
    verify_files,
    with_hash,
    write_atomically,
)

FILES_KEY = "_files"
"""The key under which a stage record lists the files the stage wrote (relative path → size, SHA-256)."""


class StopRequested(Exception):
    """Raised after the stage named by ``stop_after``; re-running the same command resumes."""


def stage_seed(seed: int, name: str) -> int:
    """A seed for one stage, stable across runs and independent of what ran before it.

    Examples:
        >>> stage_seed(0, "random_data") == stage_seed(0, "random_data")
        True
    """
    return (seed * 1_000_003 + zlib.crc32(name.encode())) % (2**31 - 1)


class Stages:
    """Bookkeeping of one run directory: which stages are done, their wall times, where files go.

    A stage is seeded by :func:`stage_seed`; the RNG state it leaves (``stages/<name>.rng.pt``)
    is restored when a re-run skips it. Its record ``stages/<name>.json`` carries its SHA-256 and
    lists the files the stage wrote with size and SHA-256, checked before a done stage is used.
    Reading never writes into the run directory and never unpickles.

    Examples:
        >>> import tempfile
        >>> stages = Stages(Path(tempfile.mkdtemp()), seed=0)
        >>> stages.run("square", lambda: {"x": 4})["x"]
        4
        >>> stages.done("square"), sorted(stages.verify("square"))
        (True, ['wall_time_s', 'x'])
    """

    def __init__(
        self,
        run_dir: Path,
        *,
        seed: int,
        stop_after: str | None = None,
        logger: Logger | None = None,
    ):
        self.run_dir, self.seed = Path(run_dir), seed
        self.stop_after, self.logger = stop_after, logger
        self.wall_time_s: dict[str, float] = {}
        self._earlier_s: dict[str, float] = {}  # parts of a stage finished by earlier runs
        self._pending: dict[str, Path] = {}  # files written since the last stage boundary
        self._verified: set[str] = set()

    def _marker(self, name: str) -> Path:
        return self.run_dir / "stages" / f"{name}.json"

    def _remedy(self, name: str) -> str:
        return f"delete {self._marker(name)} to compute stage '{name}' again."

    def done(self, name: str) -> bool:
        """Whether ``name`` finished in this or an earlier run."""
        return self._marker(name).exists()

    def verify(self, name: str) -> dict[str, Any]:
        """The record of the done stage ``name``, checked with the files it lists (hashed once per
        object); :class:`DamagedFileError` naming the file, the stage and what to delete."""
        record = _read_timed(self._marker(name), self._remedy(name))
        files = record.pop(FILES_KEY, None)
        if files is not None and name not in self._verified:
            verify_files(self.run_dir, files, owner=f"stage '{name}'", remedy=self._remedy(name))
        self._verified.add(name)
        return record

    def _restore_rng(self, name: str) -> None:
        path = self.run_dir / "stages" / f"{name}.rng.pt"
        if path.exists():  # absent in runs made before it was kept
            try:
                torch.set_rng_state(torch.load(path, map_location="cpu", weights_only=True))
            except Exception as err:  # a torch RNG state is one uint8 tensor; anything else: damage
                reason = str(err).splitlines()[0] if str(err) else type(err).__name__
                raise DamagedFileError(
                    f"{path} is not a torch RNG state ({reason}); {self._remedy(name)}"
                ) from None

    def run(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """Run ``fn`` (seeded with :func:`stage_seed`) unless ``name`` is done (then checked by
        :meth:`verify`); return its record, which lists the files written since the last stage."""
        try:  # pending paths end with the stage (a done stage's belong to its earlier run)
            if self.done(name):
                record = self.verify(name)
                self._restore_rng(name)
            else:
                torch.manual_seed(stage_seed(self.seed, name))
                start = time.perf_counter()
                record = fn() or {}
                if FILES_KEY in record or HASH_KEY in record:
                    raise ValueError(
                        f"Stage {name!r} returned the reserved key {FILES_KEY!r} or {HASH_KEY!r}."
                    )
                record["wall_time_s"] = time.perf_counter() - start + self._earlier_s.pop(name, 0.0)
                rng_file = self.path("stages", f"{name}.rng.pt")  # before the record: done has both
                write_atomically(rng_file, lambda tmp: torch.save(torch.get_rng_state(), tmp))
                files = {
                    rel: file_entry(p) for rel, p in sorted(self._pending.items()) if p.is_file()
                }
                text = json.dumps(with_hash({**record, FILES_KEY: files}), indent=1)
                write_atomically(self._marker(name), lambda tmp: tmp.write_text(text))
                self._verified.add(name)
                if self.logger is not None:
                    self.logger.log_scalar(f"wall_time/{name}", record["wall_time_s"], step=0)
        finally:
            self._pending.clear()
        self.wall_time_s[name] = record["wall_time_s"]
        if self.stop_after == name:
            raise StopRequested(name)
        return record

    def run_parts(
        self,
        name: str,
        count: int,
        fn: Callable[[int], dict[str, Any]],
        *,
        show_progress: bool = False,
    ) -> list[dict[str, Any]]:
        """Run ``fn(i)`` for ``i < count`` inside :meth:`run` of stage ``name``, each part's record
        kept in ``stages/<name>/part_<i>.json``: a stopped stage resumes at the first missing part.

        ``fn`` seeds itself; after the parts the RNG is seeded from (seed, ``name``).

        Examples:
            >>> import tempfile
            >>> stages = Stages(Path(tempfile.mkdtemp()), seed=0)
            >>> [r["i"] for r in stages.run_parts("episodes", 3, lambda i: {"i": i})]
            [0, 1, 2]
        """
        folder, records = self.run_dir / "stages" / name, []
        for i in tqdm(range(count), desc=name, disable=not show_progress, leave=False):
            marker = folder / f"part_{i}.json"
            if marker.exists():
                remedy = f"delete {marker} to compute that part of stage '{name}' again."
                records.append(record := _read_timed(marker, remedy))
                self._earlier_s[name] = self._earlier_s.get(name, 0.0) + record["wall_time_s"]
                continue
            start = time.perf_counter()
            record = fn(i)
            record["wall_time_s"] = time.perf_counter() - start
            text = json.dumps(with_hash(record))
            folder.mkdir(parents=True, exist_ok=True)
            write_atomically(marker, lambda tmp, text=text: tmp.write_text(text))
            records.append(record)
        torch.manual_seed(stage_seed(self.seed, f"{name}/after_parts"))
        return records

    def save_data(self, name: str, data: TensorDictBase) -> None:
        """Store transitions as a TorchRL replay buffer (``dumps``) under ``buffers/name``,
        listed in the record of the stage that is running."""
        folder = self.run_dir / "buffers" / name
        if folder.exists():  # left by a run stopped inside this stage: replaced, not mixed
            shutil.rmtree(folder)
        buffer = make_sequence_buffer(max(len(data), 1), slice_len=1, num_slices=1)
        buffer.extend(data.cpu())  # on disk device-free, whatever device the data came from
        save_buffer(buffer, folder)
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            self.path(path.relative_to(self.run_dir).as_posix())

    def load_data(self, name: str) -> TensorDictBase:
        """Transitions saved by :meth:`save_data`, read as data once the stage that wrote them is
        checked (:meth:`verify`); :class:`DamagedFileError` for any difference."""
        prefix = f"buffers/{name}/"
        what = f"delete {self.run_dir / prefix} and the record of the stage that wrote it."
        markers = sorted(self.run_dir.glob("stages/*.json"), key=lambda p: (p.stem != name, p.stem))
        for marker in markers:  # the stage of the same name first: it usually wrote the data
            record = read_record(marker, required=(), remedy=self._remedy(marker.stem))
            if any(rel.startswith(prefix) for rel in record.get(FILES_KEY) or {}):
                self.verify(marker.stem)
                what = self._remedy(marker.stem)
                break
        try:
            data = load_buffer_data(self.run_dir / prefix)
        except DamagedFileError as err:
            raise DamagedFileError(f"{err} To recover: {what}") from None
        if len(data) == 0:
            raise ValueError(f"The replay buffer at {self.run_dir / prefix} is empty.")
        return data

    def path(self, *parts: str) -> Path:
        """A path inside the run directory (parents created); the file there, if any when the next
        stage finishes, is listed in its record and checked when a resumed run skips it."""
        out = self.run_dir.joinpath(*parts)
        out.parent.mkdir(parents=True, exist_ok=True)
        self._pending[out.relative_to(self.run_dir).as_posix()] = out
        return out


def verify_run_dir(run_dir: str | Path) -> None:
    """Check every stage record of a run directory, the files it lists and each part record.

    Examples:
        >>> import tempfile
        >>> run_dir = Path(tempfile.mkdtemp())
        >>> _ = Stages(run_dir, seed=0).run("square", lambda: {"x": 4})
        >>> marker = run_dir / "stages" / "square.json"
        >>> _ = marker.write_text(marker.read_text().replace('"x": 4', '"x": 5'))  # edited by hand
        >>> verify_run_dir(run_dir)
        Traceback (most recent call last):
        ...
        torchrl_recon.errors.DamagedFileError: ...square.json ...
    """
    stages, folder = Stages(run_dir, seed=0), Path(run_dir) / "stages"
    for marker in sorted(folder.glob("*.json")):
        stages.verify(marker.stem)
    for marker in sorted(folder.glob("*/part_*.json")):
        name = marker.parent.name
        remedy = f"delete {marker} to compute that part of stage '{name}' again."
        if stages.done(name):  # its parts are read again only when the stage runs again
            remedy = f"delete {marker} and {stages._marker(name)} to compute stage '{name}' again."
        _read_timed(marker, remedy)


def _read_timed(marker: Path, remedy: str) -> dict[str, Any]:
    """A stage or part record, checked against its SHA-256, with a numeric ``wall_time_s``."""
    record = read_record(marker, required=("wall_time_s",), remedy=remedy)
    if not isinstance(record["wall_time_s"], (int, float)):
        raise DamagedFileError(f"{marker}: wall_time_s is not a number; {remedy}")
    return record
