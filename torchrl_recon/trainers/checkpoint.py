"""Verified Trainer checkpoints: TorchRL's own formats plus a manifest of every file's size and
SHA-256, checked before any state is loaded.

TorchRL's unified ``torchrl.checkpoint.Checkpoint`` and the legacy ``torch.save`` file of
``Trainer(save_trainer_file=...)`` record no hashes: a truncated tensor file of a unified
checkpoint loads without complaint and gives different weights. Here:

- :class:`VerifiedCheckpoint` is a ``Checkpoint`` that, once TorchRL has written its files,
  adds ``files.json`` (relative path → size and SHA-256 of every other file) inside the
  checkpoint, in the same atomic publish; its ``load`` checks the files first.
- :class:`VerifiedTrainer` is a ``torchrl.trainers.Trainer`` that checkpoints through a
  :class:`VerifiedCheckpoint` (a plain ``Checkpoint`` given is upgraded), writes a sidecar
  manifest ``<file>.files.json`` beside a legacy ``torch.save`` file, and checks either before
  ``load_from_file`` loads anything.
- :func:`verify_checkpoint` is the check itself, for any of these paths.

A damaged, truncated, swapped or planted file is one :class:`~torchrl_recon.errors.DamagedFileError`
(a ``ValueError``) naming the file and what was expected. Nothing is unpickled.
"""

from __future__ import annotations

import json
import pickle
import sys
import uuid
import warnings
import zipfile
import zlib
from collections.abc import Collection, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from torchrl.checkpoint import (
    Checkpoint,
    CheckpointError,
    CheckpointFormat,
    CheckpointLoadResult,
    CheckpointOptions,
    CheckpointStrictness,
)
from torchrl.trainers import Trainer

from torchrl_recon.errors import DamagedFileError
from torchrl_recon.runs.archive import sha256_bytes
from torchrl_recon.runs.files import (
    HASH_KEY,
    file_entry,
    json_sha256,
    read_record,
    verify_files,
    with_hash,
    write_atomically,
)

FILES = "files.json"
"""The manifest's name inside a checkpoint directory or archive; a legacy file ``x.pt`` has its
own beside it, ``x.pt.files.json``."""

FORMAT = "torchrl_recon.verified_checkpoint"
"""The ``format`` field of a manifest."""

# A fixed key, not the module's path (the module is torchrl_recon.runs.files now): checkpoints
# already written carry it.
_MARKER = "torchrl_recon.files"  # key of TorchRL's manifest metadata: "this one has a FILES"

_REMEDY = "resume from an intact checkpoint, or start again"


def sidecar(path: str | Path) -> Path:
    """The manifest of a legacy single-file checkpoint: ``<path>.files.json`` beside it.

    Examples:
        >>> sidecar("runs/trainer.pt").as_posix()
        'runs/trainer.pt.files.json'
    """
    path = Path(path)
    return path.with_name(f"{path.name}.files.json")


def _manifest_text(files: Mapping[str, Mapping[str, Any]]) -> str:
    return json.dumps(with_hash({"format": FORMAT, "files": dict(files)}), indent=1)


def _read_manifest(path: Path) -> dict[str, Any]:
    """The ``files`` of a manifest file (its own hash and format checked)."""
    record = read_record(path, required=("format", "files"), remedy=_REMEDY)
    if record["format"] != FORMAT or not isinstance(record["files"], dict):
        raise DamagedFileError(f"{path} is not a {FORMAT} manifest; {_REMEDY}")
    return record["files"]


def write_manifest(path: str | Path) -> Path:
    """Write the manifest of a saved checkpoint: ``<path>/files.json`` listing every file of a
    directory, or the sidecar ``<path>.files.json`` of a single file; returns it.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "trainer.pt"
        >>> torch.save({"w": torch.ones(2)}, path)
        >>> write_manifest(path).name
        'trainer.pt.files.json'
        >>> verify_checkpoint(path)
        True
    """
    path = Path(path)
    if path.is_dir():
        files = {
            p.relative_to(path).as_posix(): file_entry(p)
            for p in sorted(path.rglob("*"))
            if p.is_file() and p.relative_to(path).as_posix() != FILES
        }
        target = path / FILES
    else:
        files, target = {path.name: file_entry(path)}, sidecar(path)
    text = _manifest_text(files)
    return write_atomically(target, lambda tmp: tmp.write_text(text))


def verify_checkpoint(path: str | Path) -> bool:
    """Check a Trainer checkpoint against its manifest before anything is loaded from it.

    ``path`` is a unified checkpoint (directory or archive) or a legacy ``torch.save`` file.
    With a manifest, the files must be exactly those it lists (none missing, none added), each
    of the size, then the SHA-256, recorded. Without one (a checkpoint made by plain TorchRL),
    what its format allows is checked: a zip archive's CRC-32 of each member, a unified
    checkpoint's own manifest; a unified checkpoint made by :class:`VerifiedCheckpoint` whose
    manifest was deleted is refused.

    Returns:
        True when checked against a manifest, False for a checkpoint that has none.

    Raises:
        DamagedFileError: one line naming the first file that differs and what was expected.
        FileNotFoundError: ``path`` does not exist.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "ckpt"
        >>> _ = VerifiedCheckpoint(model=torch.nn.Linear(2, 1)).save(path)
        >>> verify_checkpoint(path)
        True
        >>> _ = (path / "planted.txt").write_text("x")
        >>> verify_checkpoint(path)
        Traceback (most recent call last):
        ...
        torchrl_recon.errors.DamagedFileError: .../planted.txt is not one of the ... files ...
    """
    path = Path(path)
    if path.is_dir():
        return _verify_directory(path)
    if sidecar(path).is_file():
        files = _read_manifest(sidecar(path))
        if set(files) != {path.name}:
            raise DamagedFileError(
                f"{sidecar(path)} lists {sorted(files)}, not {path.name!r}; {_REMEDY}"
            )
        verify_files(path.parent, files, owner=str(sidecar(path)), remedy=_REMEDY)
        return True
    if not path.exists():
        raise FileNotFoundError(f"No checkpoint at {path}.")
    return _verify_zip(path)


def _verify_directory(path: Path) -> bool:
    manifest = path / FILES
    if not manifest.is_file():
        if (path / "manifest.json").exists():  # a unified checkpoint: was it saved verified?
            if _torchrl_metadata(path).get(_MARKER):
                raise DamagedFileError(
                    f"{manifest} is missing; {path} was saved by VerifiedCheckpoint, which writes "
                    f"it; {_REMEDY}"
                )
        return False
    files = _read_manifest(manifest)
    present = {p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file()} - {FILES}
    planted = sorted(present - set(files))
    if planted:
        raise DamagedFileError(
            f"{path / planted[0]} is not one of the {len(files)} files {manifest} lists (planted, "
            f"or left by another save); expected only those; {_REMEDY}"
        )
    verify_files(path, files, owner=str(manifest), remedy=_REMEDY)
    return True


def _torchrl_metadata(path: Path) -> Mapping[str, Any]:
    """TorchRL's manifest metadata of a unified checkpoint, its damage one line."""
    try:
        metadata = Checkpoint.manifest(path).get("metadata")
    except (CheckpointError, OSError, ValueError) as err:
        raise DamagedFileError(
            f"{path} is not a readable TorchRL checkpoint ({_first_line(err)}); {_REMEDY}"
        ) from None
    return metadata if isinstance(metadata, Mapping) else {}


def _verify_zip(path: Path) -> bool:
    """A unified archive (with or without ``files.json``) or a legacy ``torch.save`` file."""
    expected = "an intact zip archive, as torch.save and TorchRL's Checkpoint write"
    try:
        with zipfile.ZipFile(path) as archive:
            names = [i.filename for i in archive.infolist() if not i.is_dir()]
            if FILES not in names:
                if "manifest.json" in names and _torchrl_metadata(path).get(_MARKER):
                    raise DamagedFileError(
                        f"{path} has no member {FILES}; it was saved by VerifiedCheckpoint, "
                        f"which writes it; {_REMEDY}"
                    )
                bad = archive.testzip()  # reads every member: CRC-32 and the archive's structure
                if bad is not None:
                    raise DamagedFileError(
                        f"{path}: member {bad!r} fails its CRC-32 (damaged); expected {expected}; "
                        f"{_REMEDY}"
                    )
                return False
            files = _read_manifest_member(archive, path)
            planted = sorted(set(names) - set(files) - {FILES})
            if planted:
                raise DamagedFileError(
                    f"{path}: member {planted[0]!r} is not one of the {len(files)} its {FILES} "
                    f"lists (planted); expected only those; {_REMEDY}"
                )
            for name, entry in files.items():
                if name not in names:
                    raise DamagedFileError(f"{path}: member {name!r} is missing; {_REMEDY}")
                size = archive.getinfo(name).file_size
                if size != entry.get("size"):
                    raise DamagedFileError(
                        f"{path}: member {name!r} has {size} bytes, but {FILES} lists "
                        f"{entry.get('size')}; {_REMEDY}"
                    )
            for name, entry in files.items():
                if sha256_bytes(archive.read(name)) != entry.get("sha256"):
                    raise DamagedFileError(
                        f"{path}: member {name!r} does not match the SHA-256 its {FILES} "
                        f"records; {_REMEDY}"
                    )
            return True
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, OSError, EOFError) as err:
        raise DamagedFileError(
            f"{path} is not a readable zip archive ({_first_line(err)}); expected {expected}; "
            f"{_REMEDY}"
        ) from None


def _read_manifest_member(archive: zipfile.ZipFile, path: Path) -> dict[str, Any]:
    try:
        record = json.loads(archive.read(FILES))
    except ValueError as err:
        raise DamagedFileError(
            f"{path}: member {FILES} is not valid JSON ({_first_line(err)}); {_REMEDY}"
        ) from None
    if not isinstance(record, dict):
        raise DamagedFileError(f"{path}: member {FILES} is not a {FORMAT} manifest; {_REMEDY}")
    saved = record.pop(HASH_KEY, None)
    files = record.get("files")
    if (
        saved != json_sha256(record)
        or record.get("format") != FORMAT
        or not isinstance(files, dict)
        or not all(isinstance(e, dict) for e in files.values())
    ):
        raise DamagedFileError(
            f"{path}: member {FILES} is not an intact {FORMAT} manifest; {_REMEDY}"
        )
    return files


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


class VerifiedCheckpoint(Checkpoint):
    """TorchRL's ``Checkpoint`` with a manifest of every file's size and SHA-256, checked on load.

    Saving is TorchRL's (same components, adapters and layout); the manifest ``files.json``
    is added inside the directory (or archive) before it is published, in the same atomic
    rename. :meth:`load` first runs :func:`verify_checkpoint`: a truncated, altered, swapped,
    missing or extra file is one :class:`~torchrl_recon.errors.DamagedFileError` naming it,
    before any component is loaded. A checkpoint saved by plain TorchRL (no manifest) loads
    with a warning. Pass it as any TorchRL Trainer's ``checkpoint=``.

    Args and Keyword Args: those of ``torchrl.checkpoint.Checkpoint``.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "ckpt"
        >>> source, target = torch.nn.Linear(2, 1), torch.nn.Linear(2, 1)
        >>> _ = VerifiedCheckpoint(policy=source).save(path)
        >>> VerifiedCheckpoint(policy=target).load(path).loaded
        {'policy'}
        >>> torch.equal(source.weight, target.weight)
        True
    """

    @classmethod
    def from_checkpoint(cls, checkpoint: Checkpoint) -> VerifiedCheckpoint:
        """A :class:`VerifiedCheckpoint` with ``checkpoint``'s settings, sharing its registered
        components and adapters (what is registered on one is registered on both).

        Examples:
            >>> plain = Checkpoint(format="archive", step={"n": 1})
            >>> verified = VerifiedCheckpoint.from_checkpoint(plain)
            >>> verified.format, "step" in verified
            ('archive', True)
        """
        if not isinstance(checkpoint, Checkpoint):
            raise TypeError(
                f"checkpoint must be a torchrl.checkpoint.Checkpoint, got {type(checkpoint).__name__}."
            )
        verified = cls.__new__(cls)
        verified.__dict__.update(checkpoint.__dict__)
        return verified

    def save(
        self,
        path: str | Path,
        *,
        components: Collection[str] | None = None,
        component_options: Mapping[str, CheckpointOptions] | None = None,
        format: CheckpointFormat | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> Path:
        """TorchRL's ``save`` to a staging path, the manifest added, then one atomic publish."""
        destination = self._local_path(path)
        output_format = self.format if format is None else format
        self._validate_format(output_format)
        stage = destination.with_name(f".{destination.name}.verified-{uuid.uuid4().hex}")
        try:
            super().save(
                stage,
                components=components,
                component_options=component_options,
                format=output_format,
                metadata={**(metadata or {}), _MARKER: FILES},
            )
            if output_format == "directory":
                write_manifest(stage)
            else:
                with zipfile.ZipFile(stage) as archive:
                    files = {
                        i.filename: {"size": i.file_size, "sha256": sha256_bytes(archive.read(i))}
                        for i in archive.infolist()
                        if not i.is_dir()
                    }
                with zipfile.ZipFile(stage, "a") as archive:
                    archive.writestr(FILES, _manifest_text(files))
            self._publish_path(stage, destination)
        finally:
            self._remove_path(stage)
        return destination

    def load(
        self,
        path: str | Path,
        *,
        components: Collection[str] | None = None,
        component_options: Mapping[str, CheckpointOptions] | None = None,
        map_location: Any = None,
        tensor_load_kwargs: Mapping[str, Any] | None = None,
        strict: CheckpointStrictness | None = None,
    ) -> CheckpointLoadResult:
        """:func:`verify_checkpoint`, then TorchRL's ``load`` (same keywords)."""
        source = self._local_path(path)
        if self.__dict__.get("_checked") != source and not verify_checkpoint(source):
            _warn_unverified(source)
        return super().load(
            source,
            components=components,
            component_options=component_options,
            map_location=map_location,
            tensor_load_kwargs=tensor_load_kwargs,
            strict=strict,
        )

    @contextmanager
    def _checked_already(self, path: Path) -> Iterator[None]:
        """Within: ``load(path)`` skips the check (its caller has just made it)."""
        self._checked = self._local_path(path)
        try:
            yield
        finally:
            self._checked = None


LEGACY_SAVE_WARNINGS: tuple[tuple[str, type[Warning]], ...] = (
    ("The default Trainer checkpoint format will change from the legacy", FutureWarning),
    ("The legacy CKPT_BACKEND trainer checkpoint path is deprecated", DeprecationWarning),
)
"""The two warnings TorchRL 0.14's ``Trainer`` gives at every legacy (``save_trainer_file``
without ``checkpoint=``) save, which :class:`VerifiedTrainer` leaves out: the format is
documented, and ``checkpoint=Checkpoint()`` is the way to TorchRL's unified one."""


def _warn_unverified(path: str | Path) -> None:
    warnings.warn(
        f"{path} has no {FILES} manifest (saved by plain TorchRL): loaded without checking its "
        "files' sizes and hashes.",
        UserWarning,
        stacklevel=3,
    )


class VerifiedTrainer(Trainer):
    """TorchRL's ``Trainer`` whose checkpoints are checked before anything is loaded from them.

    Same keywords as ``torchrl.trainers.Trainer``. With ``checkpoint=`` (TorchRL's unified
    format) the checkpoint is a :class:`VerifiedCheckpoint` (a plain ``Checkpoint`` given is
    upgraded, sharing its components); with ``save_trainer_file`` alone (TorchRL's legacy
    ``torch.save`` file) each save also writes the sidecar manifest ``<file>.files.json``.
    :meth:`load_from_file` runs :func:`verify_checkpoint` first, so a damaged, truncated,
    swapped or planted file is one :class:`~torchrl_recon.errors.DamagedFileError` (a
    ``ValueError``) naming it, before any state is loaded. A checkpoint without a manifest (made
    by plain TorchRL) still loads, with a warning, after what its format allows is checked; a
    legacy file torch cannot read is one line too. Nothing is unpickled (``weights_only=True``).
    A legacy save gives none of TorchRL's two warnings that the legacy format is going away
    (``LEGACY_SAVE_WARNINGS`` in this module; each save gave them before): pass
    ``checkpoint=Checkpoint()`` for the unified format.

    Subclass it instead of ``Trainer`` (``OnlineTrainer`` does) or pass it the same keywords.

    Examples:
        >>> import tempfile
        >>> from torchrl_recon.envs import make_env
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
        >>> from torchrl_recon.policies import MPCPolicy
        >>> from torchrl_recon.trainers import OnlineCollector, OnlineTrainer
        >>> from torchrl_recon.fitting.online import FitSchedule
        >>> from torchrl_recon.envs.gym_costs import pendulum
        >>> def trainer(path):
        ...     env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
        ...     world = LSTMWorldModel(3, 1, window=4)
        ...     planner = CEMPlanner(PlanningModel.from_env(world, pendulum, env), Objective(),
        ...                          horizon=4, num_candidates=8, iterations=1, num_elites=2)
        ...     collector = OnlineCollector(env, MPCPolicy(planner), iterations=1,
        ...                                 steps_per_iteration=20, random_steps=40)
        ...     return OnlineTrainer(collector=collector, world_model=world, estimator=None,
        ...         schedule=FitSchedule(steps=2, refit_steps=1, eval_every=1, slice_len=8,
        ...                              num_slices=2, val_fraction=0.5),
        ...         progress=False, save_trainer_file=path, save_trainer_interval=0,
        ...         checkpoint=Checkpoint())  # upgraded to a VerifiedCheckpoint
        >>> path = Path(tempfile.mkdtemp()) / "trainer"
        >>> done = trainer(path)
        >>> done.train()
        >>> isinstance(done, VerifiedTrainer), (path / FILES).is_file()
        (True, True)
        >>> _ = trainer(path).load_from_file(path)  # checked, then loaded
    """

    def __init__(self, **kwargs: Any) -> None:
        checkpoint = kwargs.get("checkpoint")
        if checkpoint is not None and not isinstance(checkpoint, VerifiedCheckpoint):
            if type(checkpoint) is not Checkpoint:
                raise TypeError(
                    f"checkpoint must be a torchrl Checkpoint or a VerifiedCheckpoint, got "
                    f"{type(checkpoint).__name__}: subclass VerifiedCheckpoint to keep the "
                    "verified files."
                )
            kwargs["checkpoint"] = VerifiedCheckpoint.from_checkpoint(checkpoint)
        super().__init__(**kwargs)

    def _save_trainer(self) -> None:
        with warnings.catch_warnings():
            for message, category in LEGACY_SAVE_WARNINGS:
                warnings.filterwarnings("ignore", message=message, category=category)
            super()._save_trainer()
        if self.checkpoint is None and self.save_trainer_file is not None:
            write_manifest(self.save_trainer_file)  # legacy file: its sidecar; memmap: inside

    def load_from_file(self, file: str | Path, **kwargs: Any) -> VerifiedTrainer:
        """:func:`verify_checkpoint`, then TorchRL's ``load_from_file`` (same keywords); a
        legacy file is read by ``torch.load(weights_only=True)``, its errors one line."""
        if kwargs.get("weights_only", True) is not True:
            raise ValueError(
                f"weights_only={kwargs['weights_only']!r}: {type(self).__name__} never unpickles "
                f"{file}; expected weights_only=True (the default)."
            )
        path = Path(file)
        if not verify_checkpoint(path):
            _warn_unverified(path)
        if path.is_dir() or Checkpoint.is_checkpoint(path):
            if isinstance(self.checkpoint, VerifiedCheckpoint):
                with self.checkpoint._checked_already(path):
                    super().load_from_file(path, **kwargs)
            else:
                super().load_from_file(path, **kwargs)
            return self
        kwargs = {"weights_only": True, "mmap": sys.platform != "win32", **kwargs}
        try:  # TorchRL's legacy branch, with torch's long zip/unpickler messages made one line
            state = torch.load(str(path), **kwargs)
        except (RuntimeError, EOFError, OSError, pickle.UnpicklingError) as err:
            raise DamagedFileError(
                f"{path} cannot be read by torch.load ({_first_line(err)}); expected a complete "
                f"Trainer checkpoint saved by torch.save; {_REMEDY}"
            ) from None
        self.load_state_dict(state)
        return self
