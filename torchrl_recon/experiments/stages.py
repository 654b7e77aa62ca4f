"""Resumable experiment stages: each stage writes its outputs and a marker; a re-run skips it."""

from __future__ import annotations

import json
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_recon._files import write_atomically
from torchrl_recon.data import buffer_contents, load_buffer, make_sequence_buffer, save_buffer


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

    Each stage is seeded by :func:`stage_seed`, and the torch RNG state it leaves behind is
    kept next to its marker (``stages/<name>.rng.pt``). A re-run that skips a finished stage
    restores that state, so code between stages (e.g. building the networks, whose initial
    weights come from the global RNG) draws the same numbers whether the run was stopped or not.

    Examples:
        >>> import tempfile
        >>> stages = Stages(Path(tempfile.mkdtemp()), seed=0)
        >>> stages.run("square", lambda: {"x": 4})["x"]
        4
        >>> stages.done("square")
        True
    """

    def __init__(
        self,
        run_dir: Path,
        *,
        seed: int,
        stop_after: str | None = None,
        logger: Logger | None = None,
    ):
        self.run_dir, self.seed, self.stop_after, self.logger = (
            Path(run_dir),
            seed,
            stop_after,
            logger,
        )
        (self.run_dir / "stages").mkdir(parents=True, exist_ok=True)
        self.wall_time_s: dict[str, float] = {}
        self._earlier_s: dict[str, float] = {}  # parts of a stage finished by earlier runs

    def _marker(self, name: str) -> Path:
        return self.run_dir / "stages" / f"{name}.json"

    def _rng_file(self, name: str) -> Path:
        return self.run_dir / "stages" / f"{name}.rng.pt"

    def done(self, name: str) -> bool:
        """Whether ``name`` finished in this or an earlier run."""
        return self._marker(name).exists()

    def run(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """Run ``fn`` (seeded with :func:`stage_seed`) unless ``name`` is done; return its JSON record."""
        if self.done(name):
            record = json.loads(self._marker(name).read_text())
            if self._rng_file(name).exists():  # absent in runs made before it was kept
                torch.set_rng_state(torch.load(self._rng_file(name), weights_only=True))
        else:
            torch.manual_seed(stage_seed(self.seed, name))
            start = time.perf_counter()
            record = fn() or {}
            record["wall_time_s"] = time.perf_counter() - start + self._earlier_s.pop(name, 0.0)
            rng_state = torch.get_rng_state()  # saved before the marker: a done stage has both
            write_atomically(self._rng_file(name), lambda tmp: torch.save(rng_state, tmp))
            write_atomically(
                self._marker(name), lambda tmp: tmp.write_text(json.dumps(record, indent=1))
            )
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

        Each record is written to ``stages/<name>/part_<i>.json`` as soon as it ends, so a stage
        stopped half way (e.g. after 7 of 10 control episodes) resumes at the first missing part.
        ``fn`` seeds itself: parts must not depend on the random state left by earlier ones.
        Call it inside :meth:`run` of the same ``name``: that stage's ``wall_time_s`` then
        includes the parts' time from earlier runs.

        Examples:
            >>> import tempfile
            >>> stages = Stages(Path(tempfile.mkdtemp()), seed=0)
            >>> [r["i"] for r in stages.run_parts("episodes", 3, lambda i: {"i": i})]
            [0, 1, 2]
            >>> sorted(p.name for p in (stages.run_dir / "stages" / "episodes").iterdir())
            ['part_0.json', 'part_1.json', 'part_2.json']
        """
        folder = self.run_dir / "stages" / name
        folder.mkdir(parents=True, exist_ok=True)
        records = []
        for i in progress(range(count), desc=name, enabled=show_progress):
            marker = folder / f"part_{i}.json"
            if marker.exists():
                records.append(json.loads(marker.read_text()))
                self._earlier_s[name] = self._earlier_s.get(name, 0.0) + records[-1]["wall_time_s"]
                continue
            start = time.perf_counter()
            record = fn(i)
            record["wall_time_s"] = time.perf_counter() - start
            text = json.dumps(record)
            write_atomically(marker, lambda tmp, text=text: tmp.write_text(text))
            records.append(record)
        return records

    def save_data(self, name: str, data: TensorDictBase) -> None:
        """Store transitions as a TorchRL replay buffer (``dumps``) under ``buffers/name``."""
        buffer = make_sequence_buffer(max(len(data), 1), slice_len=1, num_slices=1)
        buffer.extend(data)
        save_buffer(buffer, self.run_dir / "buffers" / name)

    def load_data(self, name: str) -> TensorDictBase:
        """Read transitions saved by :meth:`save_data` (no pickle)."""
        path = self.run_dir / "buffers" / name
        size = TensorDict.load_memmap(path / "storage").shape[0]
        return buffer_contents(
            load_buffer(make_sequence_buffer(size, slice_len=1, num_slices=1), path)
        )

    def path(self, *parts: str) -> Path:
        """A path inside the run directory (parents created)."""
        out = self.run_dir.joinpath(*parts)
        out.parent.mkdir(parents=True, exist_ok=True)
        return out


def progress(iterable, *, desc: str, enabled: bool, total: int | None = None):
    """A tqdm bar (or the plain iterable when ``enabled`` is False)."""
    return tqdm(iterable, desc=desc, disable=not enabled, total=total, leave=False)
