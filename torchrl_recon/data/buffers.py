"""Replay buffers of real transitions, sampled as contiguous windows that never cross an episode."""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data import LazyTensorStorage, SliceSampler, TensorDictReplayBuffer

TRAJ_KEY: tuple[str, str] = ("collector", "traj_ids")
_PREFETCH_FILE = "prefetch.pkl"


def make_sequence_buffer(
    max_size: int,
    *,
    slice_len: int,
    num_slices: int,
    traj_key: NestedKey = TRAJ_KEY,
) -> TensorDictReplayBuffer:
    """A ``TensorDictReplayBuffer`` whose samples are ``num_slices`` windows of ``slice_len`` steps.

    Samples come out flat (``[num_slices * slice_len]``); the losses reshape them with
    ``slice_len``. Trajectories are told apart by ``traj_key`` (TorchRL collectors write it).

    Examples:
        >>> rb = make_sequence_buffer(1000, slice_len=20, num_slices=8)
        >>> rb.sampler.slice_len
        20
    """
    if slice_len < 1 or num_slices < 1 or max_size < 1:
        raise ValueError(
            f"max_size, slice_len and num_slices must be >= 1, got {max_size}, {slice_len}, {num_slices}."
        )
    return TensorDictReplayBuffer(
        storage=LazyTensorStorage(max_size),
        sampler=SliceSampler(slice_len=slice_len, traj_key=traj_key, strict_length=True),
        batch_size=slice_len * num_slices,
    )


def buffer_contents(buffer: TensorDictReplayBuffer) -> TensorDictBase:
    """Everything stored in ``buffer`` as one TensorDict; raises a clear error when it is empty."""
    if len(buffer) == 0:
        raise ValueError("The replay buffer is empty; collect data before fitting.")
    return buffer[:]


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
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}.")
    ids = data.get(traj_key)
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
    if getattr(buffer, "_prefetch_cap", 0):
        raise ValueError(
            "save_buffer supports buffers without prefetch only (prefetch state is pickled)."
        )
    Path(path).mkdir(parents=True, exist_ok=True)
    buffer.dumps(path)
    Path(path, _PREFETCH_FILE).unlink(missing_ok=True)


def load_buffer(buffer: TensorDictReplayBuffer, path: str | Path) -> TensorDictReplayBuffer:
    """Restore ``buffer`` (built with the same components) from ``path`` written by :func:`save_buffer`."""
    if not Path(path, "storage").exists():
        raise FileNotFoundError(
            f"No saved replay buffer at {path} (expected a 'storage' folder from save_buffer)."
        )
    if Path(path, _PREFETCH_FILE).exists():
        raise ValueError(
            f"{Path(path, _PREFETCH_FILE)} is a pickle; refusing to load it. Buffers written by save_buffer have none."
        )
    buffer.loads(path)
    return buffer


def cut_sequences(
    data: TensorDictBase, length: int, *, traj_key: NestedKey = TRAJ_KEY
) -> TensorDictBase:
    """Cut flat transitions into non-overlapping ``[V, length]`` sequences that stay inside one trajectory.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"x": torch.arange(25.), ("collector", "traj_ids"): torch.arange(25) // 10}, [25])
        >>> cut_sequences(td, 4)["x"][:, 0].tolist()
        [0.0, 4.0, 10.0, 14.0, 20.0]
    """
    if length < 1:
        raise ValueError(f"length must be >= 1, got {length}.")
    ids = data.get(traj_key)
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
