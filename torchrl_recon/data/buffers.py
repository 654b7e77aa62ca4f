"""Replay buffers of real transitions, sampled as contiguous windows that never cross an episode."""

from __future__ import annotations

import contextlib
import logging
import math
import numbers
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler, TensorDictReplayBuffer

from torchrl_recon.data.step_sampler import WINDOW_SAMPLINGS, StepUniformSliceSampler
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.modules.checks import check_int, check_type
from torchrl_recon.runs.files import read_json

TRAJ_KEY: tuple[str, str] = ("collector", "traj_ids")
"""Where TorchRL's collectors write each step's trajectory id; windows never cross a change of it."""
FIT_KEYS: tuple[NestedKey, ...] = ("observation", "action", ("next", "observation"))
"""What the fits' losses read of a transition (with :data:`TRAJ_KEY`, which the sampler reads)."""
REWARD_FIT_KEYS: tuple[NestedKey, ...] = (*FIT_KEYS, ("next", "reward"), ("next", "terminated"))
""":data:`FIT_KEYS` and what a learned reward and termination read (``RewardLoss``)."""
MASK_KEY: tuple[str, str] = ("collector", "mask")
"""Where TorchRL's ``SliceSampler(pad_output=True)`` marks a sample's real (True) and padded steps."""
_PREFETCH_FILE = "prefetch.pkl"
_TD_TYPE = "<class 'tensordict._td.TensorDict'>"
_META_KEYS = ("shape", "device", "_type", "names")
_DTYPES = {
    f"torch.{name}": getattr(torch, name)
    for name in (
        "bool",
        "uint8",
        "int8",
        "int16",
        "int32",
        "int64",
        "float16",
        "bfloat16",
        "float32",
        "float64",
        "complex64",
        "complex128",
    )
}
_PLAIN_KEY = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]*")


class _DropStorageInit(logging.Filter):
    """Drops TorchRL's ``Initialized LazyTensorStorage with <shape> shape`` INFO record."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Initialized LazyTensorStorage")


@contextlib.contextmanager
def quiet_storage_init() -> Iterator[None]:
    """Leave out the INFO line that TorchRL logs when a storage's first write allocates it.

    That line is ``Initialized LazyTensorStorage with <shape> shape``, which a
    ``LazyTensorStorage`` logs at its first write; every other record of the ``torchrl`` logger
    passes, and only the writes inside the context are quiet.

    :class:`GatherTensorStorage` (the storage of :func:`make_sequence_buffer`, which every fit
    builds) allocates inside it, so a fit logs nothing; wrap a first ``extend`` of a plain
    ``LazyTensorStorage`` buffer in it for the same.

    Examples:
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(10))
        >>> with quiet_storage_init():
        ...     _ = rb.extend(TensorDict({"x": torch.zeros(4)}, [4]))
        >>> len(rb)
        4
    """
    logger, drop = logging.getLogger("torchrl"), _DropStorageInit()
    logger.addFilter(drop)
    try:
        yield
    finally:
        logger.removeFilter(drop)


class GatherTensorStorage(LazyTensorStorage):
    """A ``LazyTensorStorage`` that gathers flat integer indices with ``index_select``.

    A ``SliceSampler`` asks the storage for ``num_slices * slice_len`` rows as one 1-D index
    tensor. ``LazyTensorStorage`` reads them with advanced indexing (``x[index]``), which on
    the CPU costs about three times ``x.index_select(0, index)`` for the same rows; a fit step
    of a population reads tens of thousands of rows a key. Any other index (a slice, an int,
    negative or multi-dim indices) goes through ``LazyTensorStorage.get`` unchanged, and the
    rows are the same either way. Its first write allocates it without TorchRL's INFO line
    (:func:`quiet_storage_init`).

    Examples:
        >>> storage = GatherTensorStorage(10)
        >>> storage.set(torch.arange(4), TensorDict({"x": torch.arange(4.0)}, [4]))
        >>> storage.get(torch.tensor([3, 1]))["x"]
        tensor([3., 1.])
    """

    def __init__(self, max_size: int, *args: Any, **kwargs: Any) -> None:
        check_int("max_size", max_size)
        super().__init__(max_size, *args, **kwargs)

    def _init(self, data: Any) -> None:
        with quiet_storage_init():
            super()._init(data)

    def get(self, index: Any) -> Any:
        # SliceSampler passes its rows as a 1-tuple of one long tensor.
        rows = index[0] if isinstance(index, tuple) and len(index) == 1 else index
        if (
            not isinstance(rows, torch.Tensor)
            or rows.dim() != 1
            or rows.dtype != torch.long
            or not self.initialized
            or (rows.numel() > 0 and bool(rows.min() < 0))
        ):
            return super().get(index)
        filled = super().get(slice(None))  # a view of the filled part
        if not isinstance(filled, TensorDictBase):
            return super().get(index)
        return filled.apply(
            lambda x: x.index_select(0, rows.to(x.device)),
            batch_size=[rows.numel(), *filled.batch_size[1:]],
        )


def make_sequence_buffer(
    max_size: int,
    *,
    slice_len: int,
    num_slices: int,
    traj_key: NestedKey = TRAJ_KEY,
    sampling: str = "trajectory",
    pad_short: bool = False,
) -> TensorDictReplayBuffer:
    """A ``TensorDictReplayBuffer`` whose samples are ``num_slices`` windows of ``slice_len`` steps.

    Samples come out flat (``[num_slices * slice_len]``); the losses reshape them with
    ``slice_len``. Trajectories are told apart by ``traj_key`` (TorchRL collectors write it).
    ``sampling="trajectory"`` is TorchRL's ``SliceSampler`` (a trajectory uniformly, then a
    window in it); ``"step"`` is :class:`StepUniformSliceSampler` (every window start alike, so
    long and short trajectories count by their steps). Both leave out the trajectories shorter
    than ``slice_len``.

    ``pad_short=True`` (``sampling="trajectory"`` only) keeps them, for envs whose episodes are
    shorter than a slice: TorchRL's ``SliceSampler(strict_length=False, pad_output=True)`` draws
    any trajectory and pads a slice of a shorter one (the whole episode) with copies of its last
    step; while the buffer holds such a trajectory, every sample marks its real steps in
    :data:`MASK_KEY` ``("collector", "mask")``, which the losses read (padding counts in no
    loss; the normalisation statistics are fitted on the stored steps, never on samples).

    Examples:
        >>> rb = make_sequence_buffer(1000, slice_len=20, num_slices=8)
        >>> rb.sampler.slice_len
        20
        >>> from tensordict import TensorDict
        >>> rb = make_sequence_buffer(10, slice_len=4, num_slices=2, pad_short=True)
        >>> _ = rb.extend(TensorDict({"x": torch.arange(3.0), TRAJ_KEY: torch.zeros(3, dtype=torch.long)}, [3]))
        >>> sample = rb.sample()
        >>> sample["x"].tolist(), sample[MASK_KEY].tolist()
        ([0.0, 1.0, 2.0, 2.0, 0.0, 1.0, 2.0, 2.0], [True, True, True, False, True, True, True, False])
    """
    if slice_len < 1 or num_slices < 1 or max_size < 1:
        raise ValueError(
            f"max_size, slice_len and num_slices must be >= 1, got {max_size}, {slice_len}, {num_slices}."
        )
    if pad_short and sampling != "trajectory":
        raise ValueError(
            f"pad_short=True pads slices of TorchRL's SliceSampler: it needs sampling='trajectory', "
            f"got {sampling!r} (whose windows all have slice_len steps)."
        )
    if sampling == "trajectory":
        sampler = SliceSampler(
            slice_len=slice_len,
            traj_key=traj_key,
            strict_length=not pad_short,
            pad_output=pad_short,
            cache_values=True,  # trajectory bounds read once per extend, not once per sample
        )
    elif sampling == "step":
        sampler = StepUniformSliceSampler(slice_len=slice_len, traj_key=traj_key)
    else:
        raise ValueError(f"sampling must be one of {WINDOW_SAMPLINGS}, got {sampling!r}.")
    return TensorDictReplayBuffer(
        storage=GatherTensorStorage(max_size),
        sampler=sampler,
        batch_size=slice_len * num_slices,
    )


def _trajectory_ids(data: TensorDictBase, traj_key: NestedKey, caller: str) -> torch.Tensor:
    """The trajectory ids of flat transitions; a clear error when the key is missing."""
    check_type("data", data, TensorDictBase, "a TensorDict of flat transitions")
    ids = data.get(traj_key, None)
    if ids is None:
        raise ValueError(
            f"{caller} needs trajectory ids under {traj_key!r}, which the data lacks; a TorchRL "
            "collector writes them (env.rollout does not): collect with a Collector, or set them "
            f"yourself with td.set({traj_key!r}, ids) (one int id per step, constant within an "
            "episode)."
        )
    return ids


def buffer_contents(buffer: TensorDictReplayBuffer) -> TensorDictBase:
    """Everything stored in ``buffer`` as one TensorDict; raises a clear error when it is empty."""
    check_type("buffer", buffer, ReplayBuffer, "a torchrl ReplayBuffer")
    if len(buffer) == 0:
        raise ValueError("The replay buffer is empty; collect data before fitting.")
    return buffer[:]


def long_trajectories(
    data: TensorDictBase, length: int, *, ended: bool = False, traj_key: NestedKey = TRAJ_KEY
) -> int:
    """How many trajectories of flat transitions have ``length`` steps or more; with ``ended``,
    also those shorter that ended (``("next", "done")`` at their last step), so that only a
    piece cut short by the end of a collection is left out.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({TRAJ_KEY: torch.tensor([0, 0, 0, 1, 2, 2, 2, 2])}, [8])
        >>> td["next", "done"] = torch.tensor([0, 0, 1, 1, 0, 0, 0, 0]).bool().unsqueeze(-1)
        >>> long_trajectories(td, 3), long_trajectories(td, 4), long_trajectories(td, 4, ended=True)
        (2, 1, 3)
    """
    check_int("length", length)
    ids = _trajectory_ids(data, traj_key, "long_trajectories")
    _, inverse, counts = torch.unique(ids, return_inverse=True, return_counts=True)
    counted = counts >= length
    if ended:
        done = data["next", "done"].reshape(len(ids), -1).any(-1)
        steps = torch.arange(len(ids), device=ids.device)
        last = torch.zeros_like(counts).scatter_reduce(0, inverse, steps, "amax")
        counted |= done[last]
    return int(counted.sum())


SHORT_EPISODES = ("pad", "pad_if_no_window")
"""What the fits do with episodes that ended before ``slice_len`` steps (:func:`needs_padding`):
``pad`` every such episode and keep it; ``pad_if_no_window`` pad them only where a part holds no
episode of ``slice_len`` steps, else TorchRL's strict sampler leaves them out (the rule before
2026-11-29, which run directories made before it resume with)."""


def needs_padding(
    slice_len: int,
    *parts: TensorDictBase,
    short_episodes: str = "pad",
    traj_key: NestedKey = TRAJ_KEY,
) -> bool:
    """Whether sequence buffers of ``parts`` (e.g. a training and a validation split) need
    ``make_sequence_buffer(pad_short=True)``: True when one of them holds no trajectory of
    ``slice_len`` steps, so that a buffer leaving shorter ones out could not draw one slice;
    with ``short_episodes="pad"`` (default) also when one holds a trajectory that ended
    (``("next", "done")``) shorter than that, which a strict sampler would silently leave out
    (an env's early terminations: on InvertedDoublePendulum-v5 it drew 55 of 229 episodes,
    ``benchmarks/fit_comparison.py``). A piece cut short by the end of a collection is not an
    ended episode: data without terminations pad as before.

    Examples:
        >>> from tensordict import TensorDict
        >>> train = TensorDict({TRAJ_KEY: torch.tensor([0, 0, 0, 1])}, [4])
        >>> val = TensorDict({TRAJ_KEY: torch.tensor([2, 2, 3])}, [3])
        >>> needs_padding(3, train), needs_padding(3, train, val)
        (False, True)
        >>> train["next", "done"] = torch.tensor([[0], [0], [1], [1]]).bool()  # 1 ended at 1 step
        >>> needs_padding(3, train), needs_padding(3, train, short_episodes="pad_if_no_window")
        (True, False)
    """
    check_int("slice_len", slice_len)
    if short_episodes not in SHORT_EPISODES:
        raise ValueError(
            f"short_episodes must be one of {list(SHORT_EPISODES)}, got {short_episodes!r}."
        )

    def pads(part: TensorDictBase) -> bool:
        long = long_trajectories(part, slice_len, traj_key=traj_key)
        if long == 0:
            return True
        if short_episodes != "pad" or ("next", "done") not in part.keys(True):
            return False
        return long_trajectories(part, slice_len, ended=True, traj_key=traj_key) > long

    return any(pads(part) for part in parts)


def sequence_buffers(
    parts: tuple[TensorDictBase, ...],
    *,
    slice_len: int,
    num_slices: int,
    sampling: str = "trajectory",
    keys: tuple[NestedKey, ...] | None = None,
    short_episodes: str = "pad",
) -> tuple[TensorDictReplayBuffer, ...]:
    """One :func:`make_sequence_buffer` holding each of ``parts`` (e.g. a training and a
    validation split), all padded (``pad_short=True``) when :func:`needs_padding` says so for
    ``short_episodes`` (default: an episode that ended shorter than ``slice_len``, or a part
    with no trajectory of ``slice_len`` steps). ``keys``: store only these and the
    trajectory ids (:data:`FIT_KEYS`, what the world model's and the estimators' losses read:
    a sample then gathers 4 keys instead of a collection's 15, the same rows either way).

    Examples:
        >>> from tensordict import TensorDict
        >>> train = TensorDict({TRAJ_KEY: torch.tensor([0, 0, 0, 1])}, [4])
        >>> val = TensorDict({TRAJ_KEY: torch.tensor([2, 2, 3])}, [3])
        >>> [rb.sampler.pad_output for rb in sequence_buffers((train, val), slice_len=3, num_slices=1)]
        [True, True]
    """
    if not isinstance(parts, tuple | list) or not parts:
        raise ValueError(
            f"parts must be a non-empty tuple of TensorDicts (e.g. a train and a validation "
            f"split), got {type(parts).__name__} of length {len(parts) if hasattr(parts, '__len__') else '?'}."
        )
    pad = needs_padding(slice_len, *parts, short_episodes=short_episodes)
    sizes = dict(slice_len=slice_len, num_slices=num_slices, sampling=sampling, pad_short=pad)
    buffers = tuple(make_sequence_buffer(len(part), **sizes) for part in parts)
    for buffer, part in zip(buffers, parts, strict=True):
        buffer.extend(part if keys is None else part.select(*keys, TRAJ_KEY))
    return buffers


def check_val_fraction(val_fraction: object) -> None:
    """Refuse a validation fraction that is not a number in (0, 1).

    Examples:
        >>> check_val_fraction(1.0)
        Traceback (most recent call last):
        ...
        ValueError: val_fraction must be in (0, 1), got 1.0.
    """
    if (
        isinstance(val_fraction, bool)
        or not isinstance(val_fraction, numbers.Real)
        or not 0 < val_fraction < 1
    ):
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction!r}.")


def split_by_trajectory(
    data: TensorDictBase, val_fraction: float, *, seed: int, traj_key: NestedKey = TRAJ_KEY
) -> tuple[TensorDictBase, TensorDictBase]:
    """Split flat transitions into train and validation sets by whole trajectories.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({("collector", "traj_ids"): torch.arange(40) // 10}, [40])
        >>> train, val = split_by_trajectory(td, 0.25, seed=0)
        >>> len(train), len(val)
        (30, 10)
    """
    check_val_fraction(val_fraction)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed must be an int, got {type(seed).__name__} {seed!r}.")
    ids = _trajectory_ids(data, traj_key, "split_by_trajectory")
    unique = torch.unique(ids)
    if len(unique) < 2:
        raise ValueError(f"Need at least 2 trajectories to split, got {len(unique)}.")
    generator = torch.Generator().manual_seed(seed)
    perm = unique[torch.randperm(len(unique), generator=generator)]
    num_val = max(1, round(val_fraction * len(unique)))
    is_val = torch.isin(ids, perm[:num_val])
    return data[~is_val], data[is_val]


def save_buffer(buffer: TensorDictReplayBuffer, path: str | Path) -> None:
    """Save with TorchRL's own ``dumps``: memory-mapped tensors and JSON metadata.

    TorchRL also writes ``prefetch.pkl`` (the prefetch queue, a pickle); our buffers never
    prefetch, so that file is removed and :func:`load_buffer` never unpickles anything.
    """
    check_type("buffer", buffer, ReplayBuffer, "a torchrl ReplayBuffer")
    if getattr(buffer, "_prefetch_cap", 0):
        raise ValueError(
            "save_buffer supports buffers without prefetch only (prefetch state is pickled)."
        )
    if len(buffer) == 0:
        raise ValueError(f"The replay buffer is empty: nothing to save to {path}.")
    Path(path).mkdir(parents=True, exist_ok=True)
    buffer.dumps(path)
    Path(path, _PREFETCH_FILE).unlink(missing_ok=True)


def load_buffer_data(path: str | Path) -> TensorDictBase:
    """The transitions a buffer saved by :func:`save_buffer` holds, checked, in memory.

    Every file is read as data: JSON metadata, and memory-mapped tensors whose files must have
    exactly the size their ``meta.json`` gives (a truncated file is refused, never grown back).
    Only plain tensors are accepted: a non-tensor entry (TensorDict stores those as a pickle
    sidecar), a nested tensor or any file ``save_buffer`` does not write is refused, and
    ``TensorDict.load_memmap`` runs with ``allow_pickle=False``. Nothing in ``path`` is written.

    Raises:
        FileNotFoundError: ``path`` has no ``storage`` folder.
        DamagedFileError: a file is missing, malformed, truncated, unexpected or a pickle.

    Examples:
        >>> import tempfile
        >>> from tensordict import TensorDict
        >>> rb = make_sequence_buffer(10, slice_len=2, num_slices=1)
        >>> _ = rb.extend(TensorDict({"x": torch.arange(10.0)}, [10]))
        >>> path = Path(tempfile.mkdtemp()) / "rb"
        >>> save_buffer(rb, path)
        >>> load_buffer_data(path)["x"][:3].tolist()
        [0.0, 1.0, 2.0]
    """
    data, _ = _read_saved_buffer(Path(path))
    return data


def load_buffer(buffer: TensorDictReplayBuffer, path: str | Path) -> TensorDictReplayBuffer:
    """Restore ``buffer`` (built with the same components) from ``path`` written by :func:`save_buffer`.

    The stored transitions and the writer's position are restored through the storage's and
    the writer's public API; the buffer keeps its own sampler, batch size and transforms. The
    files are checked and read as data, never unpickled (see :func:`load_buffer_data`).

    Raises:
        FileNotFoundError: ``path`` has no ``storage`` folder.
        DamagedFileError: a file is missing, malformed, truncated, unexpected or a pickle.
        ValueError: the saved transitions do not fit in ``buffer``, or ``buffer`` is not
            empty (restoring over held transitions would mix the two).

    Examples:
        >>> import tempfile
        >>> from tensordict import TensorDict
        >>> rb = make_sequence_buffer(10, slice_len=2, num_slices=1)
        >>> _ = rb.extend(TensorDict({"x": torch.arange(10.0)}, [10]))
        >>> path = Path(tempfile.mkdtemp()) / "rb"
        >>> save_buffer(rb, path)
        >>> len(load_buffer(make_sequence_buffer(10, slice_len=2, num_slices=1), path))
        10
    """
    check_type("buffer", buffer, ReplayBuffer, "a torchrl ReplayBuffer")
    path = Path(path)
    if len(buffer):
        raise ValueError(
            f"load_buffer restores {path} into an empty buffer; the one given holds "
            f"{len(buffer)} transitions (call its empty() first, or make a new one)."
        )
    data, writer_state = _read_saved_buffer(path)
    room = buffer.storage.max_size
    if len(data) > room or writer_state["_cursor"] > room:
        raise ValueError(
            f"The buffer saved at {path} holds {len(data)} transitions (writer at "
            f"{writer_state['_cursor']}); the buffer given has room for {room}."
        )
    if len(data):
        buffer.storage.set(torch.arange(len(data)), data)
    buffer.writer.load_state_dict(writer_state)
    return buffer


# ----------------------------------------------------------------------------------------------
# Reading a saved buffer as data


def _damaged(file: Path, problem: str) -> DamagedFileError:
    return DamagedFileError(
        f"{file}: {problem}; refusing to load the replay buffer (save_buffer never writes this)."
    )


def _json(file: Path) -> Any:
    return read_json(file, remedy="refusing to load the replay buffer.")


def _int_list(value: Any) -> bool:
    return isinstance(value, list) and all(type(v) is int and v >= 0 for v in value)


def _check_tensordict_dir(
    folder: Path, batch: list[int] | None, extra: tuple[str, ...] = ()
) -> list[int]:
    """Check a memory-mapped TensorDict folder as data; return its batch shape.

    Each entry must be a plain tensor (known dtype, not nested, a ``.memmap`` file of exactly
    its size) or a nested TensorDict folder; nothing else may be in the folder but ``extra``.
    """
    meta_file = folder / "meta.json"
    meta = _json(meta_file)
    if not isinstance(meta, dict) or meta.get("_type") != _TD_TYPE:
        raise _damaged(
            meta_file, f"not the metadata of a plain TensorDict (expected _type {_TD_TYPE})"
        )
    shape = meta.get("shape")
    if not _int_list(shape) or (batch is not None and shape[: len(batch)] != batch):
        raise _damaged(meta_file, f"batch shape {shape!r} does not extend its parent's {batch}")
    expected = {"meta.json", *extra}
    for key, entry in meta.items():
        if key in _META_KEYS:
            continue
        if not isinstance(entry, dict) or not _PLAIN_KEY.fullmatch(key) or key in (".", ".."):
            raise _damaged(meta_file, f"entry {key!r} is not a tensor or TensorDict entry")
        if "type" in entry:
            if entry["type"] != "TensorDict":
                raise _damaged(
                    meta_file,
                    f"entry {key!r} is a {entry['type']!r} (non-tensor data is stored as a pickle)",
                )
            _check_tensordict_dir(folder / key, shape)
            expected.add(key)
            continue
        dtype, dims = _DTYPES.get(entry.get("dtype")), entry.get("shape")
        if dtype is None or not _int_list(dims) or entry.get("is_nested", False):
            raise _damaged(meta_file, f"entry {key!r} is not a plain tensor of a known dtype")
        if dims[: len(shape)] != shape:
            raise _damaged(meta_file, f"entry {key!r} has shape {dims}, not batch shape {shape}")
        file = folder / f"{key}.memmap"
        nbytes = math.prod(dims) * dtype.itemsize
        if nbytes:
            size = file.stat().st_size if file.is_file() else None
            if size != nbytes:
                problem = "missing" if size is None else f"{size} bytes"
                raise _damaged(file, f"{problem}, expected {nbytes} ({dims} of {entry['dtype']})")
            expected.add(file.name)
    for child in folder.iterdir():
        if child.name not in expected:
            raise _damaged(child, "not part of the saved TensorDict")
    return shape


def _read_saved_buffer(path: Path) -> tuple[TensorDictBase, dict[str, int]]:
    """The stored transitions (in memory) and the writer state of a saved buffer folder."""
    storage = path / "storage"
    if not storage.is_dir():
        raise FileNotFoundError(
            f"No saved replay buffer at {path} (expected a 'storage' folder from save_buffer)."
        )
    if (path / _PREFETCH_FILE).exists():
        raise _damaged(path / _PREFETCH_FILE, "a pickle (TorchRL's prefetch queue)")
    for child in path.iterdir():
        empty_dir = child.is_dir() and not any(child.iterdir())
        if child.name not in ("storage", "writer", "buffer_metadata.json") and not empty_dir:
            raise _damaged(child, "not a file save_buffer writes (it may be a pickle)")
    buffer_meta = _json(path / "buffer_metadata.json")
    if not isinstance(buffer_meta, dict):
        raise _damaged(path / "buffer_metadata.json", "not a JSON object")
    writer_dir = path / "writer"
    writer_meta = _json(writer_dir / "metadata.json")
    for child in writer_dir.iterdir():
        if child.name != "metadata.json":
            raise _damaged(child, "not a file of a round-robin writer")
    if (
        not isinstance(writer_meta, dict)
        or set(writer_meta) - {"cursor", "write_count"}
        or type(writer_meta.get("cursor")) is not int
        or type(writer_meta.get("write_count", 0)) is not int
    ):
        raise _damaged(writer_dir / "metadata.json", "not a round-robin writer's cursor and count")
    storage_meta_file = storage / "storage_metadata.json"
    storage_meta = _json(storage_meta_file)
    if (
        not isinstance(storage_meta, dict)
        or storage_meta.get("is_pytree") is not False
        or type(storage_meta.get("len")) is not int
    ):
        raise _damaged(storage_meta_file, "not the metadata of a TensorDict storage")
    shape = _check_tensordict_dir(storage, None, extra=("storage_metadata.json",))
    length = storage_meta["len"]
    if not shape or not 0 <= length <= shape[0]:
        raise _damaged(storage_meta_file, f"length {length} does not fit storage shape {shape}")
    try:
        stored = TensorDict.load_memmap(storage, device="cpu", allow_pickle=False)
    except Exception as err:  # checked above; anything left is damage
        raise _damaged(storage, f"could not be read ({err})") from None
    data = stored[:length].clone()  # in memory: the files are never written through
    del stored
    state = {"_cursor": writer_meta["cursor"]}
    if "write_count" in writer_meta:
        state["_write_count"] = writer_meta["write_count"]
    return data, state


def cut_sequences(
    data: TensorDictBase, length: int, *, traj_key: NestedKey = TRAJ_KEY, pad_short: bool = False
) -> TensorDictBase:
    """Cut flat transitions into non-overlapping ``[V, length]`` sequences that stay inside one trajectory.

    ``pad_short=True`` is for envs whose episodes end early: when no trajectory has ``length``
    steps, each trajectory is one sequence instead (:func:`padded_trajectories`: padded with
    copies of its last step, its real steps marked in :data:`MASK_KEY`, as
    ``make_sequence_buffer(pad_short=True)`` samples them); data that hold a trajectory of
    ``length`` steps are cut as without it.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"x": torch.arange(25.), ("collector", "traj_ids"): torch.arange(25) // 10}, [25])
        >>> cut_sequences(td, 4)["x"][:, 0].tolist()
        [0.0, 4.0, 10.0, 14.0, 20.0]
        >>> cut_sequences(td, 12, pad_short=True)[MASK_KEY].sum(-1).tolist()
        [10, 10, 5]
    """
    if length < 1:
        raise ValueError(f"length must be >= 1, got {length}.")
    if pad_short and long_trajectories(data, length, traj_key=traj_key) == 0:
        return padded_trajectories(data, length, traj_key=traj_key)
    ids = _trajectory_ids(data, traj_key, "cut_sequences")
    starts = []
    for traj in torch.unique_consecutive(ids):
        idx = (ids == traj).nonzero().squeeze(-1)
        first, count = int(idx[0]), idx.numel()
        if count != int(idx[-1]) - first + 1:
            raise ValueError(
                f"Trajectory {int(traj)} is not contiguous in the data; sort it by time first."
            )
        starts.extend(range(first, first + count - length + 1, length))
    if not starts:
        raise ValueError(f"No trajectory has {length} steps; collect longer episodes.")
    index = torch.tensor(starts)[:, None] + torch.arange(length)
    return data[index]


def padded_trajectories(
    data: TensorDictBase, length: int, *, traj_key: NestedKey = TRAJ_KEY
) -> TensorDictBase:
    """Each trajectory of flat transitions as one ``[V, length]`` sequence: its first ``length``
    steps, a shorter one padded with copies of its last step; :data:`MASK_KEY` marks the real
    steps (the layout of ``SliceSampler(pad_output=True)``, which the losses honour).

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"x": torch.arange(5.), TRAJ_KEY: torch.tensor([0, 0, 0, 1, 1])}, [5])
        >>> seqs = padded_trajectories(td, 4)
        >>> seqs["x"].tolist(), seqs[MASK_KEY].int().tolist()
        ([[0.0, 1.0, 2.0, 2.0], [3.0, 4.0, 4.0, 4.0]], [[1, 1, 1, 0], [1, 1, 0, 0]])
    """
    if length < 1:
        raise ValueError(f"length must be >= 1, got {length}.")
    ids = _trajectory_ids(data, traj_key, "padded_trajectories")
    runs, counts = torch.unique_consecutive(ids, return_counts=True)
    if len(runs) != len(torch.unique(ids)):
        raise ValueError("A trajectory is not contiguous in the data; sort it by time first.")
    starts = counts.cumsum(0) - counts
    t = torch.arange(length)
    index = starts[:, None] + torch.minimum(t, counts[:, None] - 1)
    seqs = data[index]
    seqs.set(MASK_KEY, t < counts[:, None])
    return seqs
