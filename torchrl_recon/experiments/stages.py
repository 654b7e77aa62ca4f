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
from torchrl_recon.files import (
    HASH_KEY,
    file_entry,
    read_record,
    verify_files,
    with_hash,
    write_atomically,
)


class StopRequested(Exception):
    """Raised after the stage named by ``stop_after``; re-running the same command resumes."""


def stage_seed(seed: int, name: str) -> int:
    """A seed for one stage, stable across runs and independent of what ran before it.

    Examples:
        >>> stage_seed(0, "random_data") == stage_seed(0, "random_data")
        True
    """
    return (seed * 1_000_003 + zlib.crc32(name.encode())) % (2**31 - 1)


FILES_KEY = "_files"
"""The key under which a stage record lists the files the stage wrote (relative path → size, SHA-256)."""


class Stages:
    """Bookkeeping of one run directory: which stages are done, their wall times, where files go.

    Each stage is seeded by :func:`stage_seed`, and the torch RNG state it leaves behind is
    kept next to its record (``stages/<name>.rng.pt``). A re-run that skips a finished stage
    restores that state, so code between stages (e.g. building the networks, whose initial
    weights come from the global RNG) draws the same numbers whether the run was stopped or not.

    A finished stage's record (``stages/<name>.json``) lists every file the stage wrote (the
    buffers of :meth:`save_data`, the files named through :meth:`path`, its RNG state) with size
    and SHA-256, and carries the SHA-256 of its own content. Before a done stage is used, its
    record and files are checked (:meth:`verify`); a difference is a :class:`DamagedFileError`
    naming the file and the stage. Records written before files were listed are used as they are.
    Reading never writes into the run directory and never unpickles.

    Examples:
        >>> import tempfile
        >>> stages = Stages(Path(tempfile.mkdtemp()), seed=0)
        >>> stages.run("square", lambda: {"x": 4})["x"]
        4
        >>> stages.done("square")
        True
        >>> sorted(stages.verify("square"))
        ['wall_time_s', 'x']
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
        self._owner: dict[str, str] = {}  # relative file path -> the stage that wrote it
        self._verified: set[str] = set()

    def _marker(self, name: str) -> Path:
        return self.run_dir / "stages" / f"{name}.json"

    def _rng_file(self, name: str) -> Path:
        return self.run_dir / "stages" / f"{name}.rng.pt"

    def _relative(self, path: Path) -> str:
        return path.relative_to(self.run_dir).as_posix()

    def _remedy(self, name: str) -> str:
        return f"delete {self._marker(name)} to compute stage '{name}' again."

    def done(self, name: str) -> bool:
        """Whether ``name`` finished in this or an earlier run."""
        return self._marker(name).exists()

    def verify(self, name: str) -> dict[str, Any]:
        """Check the record of the done stage ``name`` and the files it lists; return the record.

        The record must match its own SHA-256 and have a numeric ``wall_time_s``; each listed
        file must have its recorded size (all are checked first) and then its SHA-256. Files
        are hashed once per :class:`Stages` object. Nothing is written.

        Raises:
            DamagedFileError: one line naming the file, the stage and what to delete.
        """
        record = _read_timed(self._marker(name), self._remedy(name))
        files = record.pop(FILES_KEY, None)
        if files is not None and name not in self._verified:
            verify_files(self.run_dir, files, owner=f"stage '{name}'", remedy=self._remedy(name))
            self._owner.update(dict.fromkeys(files, name))
        self._verified.add(name)
        return record

    def _restore_rng(self, name: str) -> None:
        path = self._rng_file(name)
        if not path.exists():  # absent in runs made before it was kept
            return
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            torch.set_rng_state(state)
        except Exception as err:  # a torch RNG state is one uint8 tensor; anything else is damage
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise DamagedFileError(
                f"{path} is not a torch RNG state ({reason}); {self._remedy(name)}"
            ) from None

    def run(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """Run ``fn`` (seeded with :func:`stage_seed`) unless ``name`` is done; return its JSON record.

        A done stage is checked first (:meth:`verify`). A stage that runs lists the files written
        through :meth:`save_data` and :meth:`path` since the previous stage, plus its RNG state.
        """
        if self.done(name):
            self._pending.clear()  # paths named for this stage belong to its earlier run
            record = self.verify(name)
            self._restore_rng(name)
        else:
            try:
                torch.manual_seed(stage_seed(self.seed, name))
                start = time.perf_counter()
                record = fn() or {}
                if FILES_KEY in record or HASH_KEY in record:
                    raise ValueError(
                        f"Stage {name!r} returned the reserved key {FILES_KEY!r} or {HASH_KEY!r}."
                    )
                record["wall_time_s"] = time.perf_counter() - start + self._earlier_s.pop(name, 0.0)
                rng_state = torch.get_rng_state()  # saved before the record: a done stage has both
                self._rng_file(name).parent.mkdir(parents=True, exist_ok=True)
                write_atomically(self._rng_file(name), lambda tmp: torch.save(rng_state, tmp))
                self._pending[self._relative(self._rng_file(name))] = self._rng_file(name)
                pending = sorted(self._pending.items())
                files = {rel: file_entry(path) for rel, path in pending if path.is_file()}
                text = json.dumps(with_hash({**record, FILES_KEY: files}), indent=1)
                write_atomically(self._marker(name), lambda tmp: tmp.write_text(text))
            finally:
                self._pending.clear()
            self._owner.update(dict.fromkeys(files, name))
            self._verified.add(name)
            if self.logger is not None:
                self.logger.log_scalar(f"wall_time/{name}", record["wall_time_s"], step=0)
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
        """Run ``fn(i)`` for ``i < count`` inside stage ``name``, keeping each part's record.

        Each record is written to ``stages/<name>/part_<i>.json`` (with the SHA-256 of its
        content) as soon as it ends, so a stage stopped half way (e.g. after 7 of 10 control
        episodes) resumes at the first missing part; a part record that does not match its
        SHA-256 is refused. ``fn`` seeds itself: parts must not depend on the random state left
        by earlier ones. After the parts the global torch RNG is seeded from (seed, ``name``),
        so what follows does not depend on which parts ran here and which were read back. Call
        it inside :meth:`run` of the same ``name``: that stage's ``wall_time_s`` then includes
        the parts' time from earlier runs.

        Examples:
            >>> import tempfile
            >>> stages = Stages(Path(tempfile.mkdtemp()), seed=0)
            >>> [r["i"] for r in stages.run_parts("episodes", 3, lambda i: {"i": i})]
            [0, 1, 2]
            >>> sorted(p.name for p in (stages.run_dir / "stages" / "episodes").iterdir())
            ['part_0.json', 'part_1.json', 'part_2.json']
        """
        folder = self.run_dir / "stages" / name
        records = []
        for i in progress(range(count), desc=name, enabled=show_progress):
            marker = folder / f"part_{i}.json"
            if marker.exists():
                remedy = f"delete {marker} to compute that part of stage '{name}' again."
                record = _read_timed(marker, remedy)
                records.append(record)
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
        """Store transitions as a TorchRL replay buffer (``dumps``) under ``buffers/name``.

        Its files are listed in the record of the stage that is running.
        """
        folder = self.run_dir / "buffers" / name
        if folder.exists():  # left by a run stopped inside this stage: replaced, not mixed
            shutil.rmtree(folder)
        buffer = make_sequence_buffer(max(len(data), 1), slice_len=1, num_slices=1)
        buffer.extend(data.cpu())  # on disk device-free, whatever device the data came from
        save_buffer(buffer, folder)
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                self._pending[self._relative(path)] = path

    def load_data(self, name: str) -> TensorDictBase:
        """Read transitions saved by :meth:`save_data`: checked, as data (no pickle), nothing written.

        The files are first checked against the record of the stage that wrote them (once per
        :class:`Stages` object), then read by :func:`~torchrl_recon.data.load_buffer_data`.

        Raises:
            DamagedFileError: a file differs from its record, or is missing, truncated or a pickle.
            ValueError: the stored buffer is empty.
        """
        prefix = f"buffers/{name}/"
        owner = self._owner_of(prefix, name)
        if owner is not None and owner not in self._verified:
            self.verify(owner)
        try:
            data = load_buffer_data(self.run_dir / "buffers" / name)
        except DamagedFileError as err:
            what = (
                self._remedy(owner)
                if owner
                else f"delete {self.run_dir / prefix} and the record of the stage that wrote it."
            )
            raise DamagedFileError(f"{err} To recover: {what}") from None
        if len(data) == 0:
            raise ValueError(f"The replay buffer at {self.run_dir / prefix} is empty.")
        return data

    def _owner_of(self, prefix: str, name: str) -> str | None:
        """The done stage whose record lists files under ``prefix`` (``name`` is tried first)."""
        owner = next((s for rel, s in self._owner.items() if rel.startswith(prefix)), None)
        if owner is not None:
            return owner
        folder = self.run_dir / "stages"
        others = sorted(p.stem for p in folder.glob("*.json")) if folder.is_dir() else []
        for stage in [name, *(s for s in others if s != name)]:
            if not self.done(stage):
                continue
            record = read_record(self._marker(stage), required=(), remedy=self._remedy(stage))
            if any(rel.startswith(prefix) for rel in record.get(FILES_KEY) or {}):
                return stage
        return None

    def path(self, *parts: str) -> Path:
        """A path inside the run directory (parents created), listed by the stage that runs next.

        The file at that path, if it exists when that stage finishes, goes into the stage's
        record (size and SHA-256) and is checked when a resumed run skips the stage.
        """
        out = self.run_dir.joinpath(*parts)
        out.parent.mkdir(parents=True, exist_ok=True)
        self._pending[self._relative(out)] = out
        return out


def verify_run_dir(run_dir: str | Path) -> None:
    """Check every finished stage of an existing run directory before a resumed run writes
    anything: each stage record, the files it lists, and each part record.

    A run directory without ``stages/`` (a new run) passes. Nothing is written.

    Raises:
        DamagedFileError: one line naming the damaged file and the record to delete.

    Examples:
        >>> import tempfile
        >>> run_dir = Path(tempfile.mkdtemp())
        >>> _ = Stages(run_dir, seed=0).run("square", lambda: {"x": 4})
        >>> verify_run_dir(run_dir)  # intact: no error
        >>> marker = run_dir / "stages" / "square.json"
        >>> record = json.loads(marker.read_text())
        >>> record["x"] = 5  # edited by hand: no longer matches its own SHA-256
        >>> _ = marker.write_text(json.dumps(record))
        >>> verify_run_dir(run_dir)
        Traceback (most recent call last):
        ...
        torchrl_recon.errors.DamagedFileError: ...square.json ...
    """
    folder = Path(run_dir) / "stages"
    if not folder.is_dir():
        return
    stages = Stages(run_dir, seed=0)
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


def progress(iterable, *, desc: str, enabled: bool, total: int | None = None):
    """A tqdm bar (or the plain iterable when ``enabled`` is False)."""
    return tqdm(iterable, desc=desc, disable=not enabled, total=total, leave=False)
