"""A window sampler that draws every valid window start with the same probability."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

WINDOW_SAMPLINGS: tuple[str, ...] = ("trajectory", "step")
"""How training windows are drawn: ``"trajectory"`` (TorchRL's ``SliceSampler``: a trajectory, then
a window in it) or ``"step"`` (:class:`StepUniformSliceSampler`: every window equally likely)."""


class StepUniformSliceSampler(Sampler):
    """Windows of ``slice_len`` steps whose start is uniform over all steps that can start one.

    TorchRL's ``SliceSampler`` first picks a trajectory uniformly, then a start inside it, so a
    step of a short trajectory is drawn more often than a step of a long one: data made of one
    long flight and a short remainder per env trains mostly on the remainders. This sampler
    weighs every window start alike (a trajectory of length L gives L - slice_len + 1 starts),
    which is what "uniform over the data" means for a replay buffer of steps. A window never
    crosses a change of ``traj_key`` (nor the end of the filled storage), as with
    ``SliceSampler(strict_length=True)``; trajectories shorter than ``slice_len`` are never
    drawn. Starts are drawn with the global torch RNG, so ``torch.manual_seed`` fixes them.

    Returns the rows as ``SliceSampler`` does: one flat long index of
    ``num_slices * slice_len`` rows, window by window.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(20),
        ...     sampler=StepUniformSliceSampler(slice_len=4), batch_size=8)
        >>> _ = rb.extend(TensorDict({"x": torch.arange(20.0),
        ...     ("collector", "traj_ids"): torch.arange(20) // 10}, [20]))
        >>> rb.sample()["x"].view(2, 4).diff(dim=1).eq(1).all().item()
        True
    """

    def __init__(self, *, slice_len: int, traj_key: NestedKey = ("collector", "traj_ids")) -> None:
        if not isinstance(slice_len, int) or isinstance(slice_len, bool) or slice_len < 1:
            raise ValueError(f"slice_len must be an int >= 1, got {slice_len!r}.")
        super().__init__()
        self.slice_len = slice_len
        self.traj_key = traj_key

    def window_starts(self, storage: Storage) -> torch.Tensor:
        """Every storage row that starts a window of ``slice_len`` steps of one trajectory."""
        filled = storage.get(slice(None))
        if not isinstance(filled, TensorDictBase) or self.traj_key not in filled.keys(True):
            raise KeyError(
                f"StepUniformSliceSampler needs trajectory ids under {self.traj_key!r} in the "
                "stored data; a TorchRL collector writes them."
            )
        ids = filled.get(self.traj_key).reshape(-1)
        count = ids.numel() - self.slice_len + 1
        if count <= 0:
            return torch.zeros(0, dtype=torch.long, device=ids.device)
        # run[t]: how many trajectory changes come before row t; a window is one trajectory's
        # when its first and last rows lie in the same run.
        run = torch.cat([ids.new_zeros(1), (ids[1:] != ids[:-1]).long().cumsum(0)])
        return (run[:count] == run[self.slice_len - 1 :]).nonzero().squeeze(-1)

    def sample(self, storage: Storage, batch_size: int) -> tuple[tuple[torch.Tensor], dict]:
        if batch_size % self.slice_len:
            raise ValueError(
                f"batch_size {batch_size} is not a multiple of slice_len {self.slice_len}."
            )
        starts = self.window_starts(storage)
        if starts.numel() == 0:
            raise RuntimeError(
                f"No trajectory in the buffer has slice_len = {self.slice_len} steps; "
                "collect longer episodes or lower slice_len."
            )
        pick = starts[torch.randint(starts.numel(), (batch_size // self.slice_len,))]
        steps = torch.arange(self.slice_len, device=pick.device)
        return ((pick.unsqueeze(-1) + steps).reshape(-1),), {}

    def _empty(self) -> None:
        """Nothing to reset: the windows are found anew from the storage at each sample."""

    def dumps(self, path: Any) -> None:
        """Nothing to write: the sampler has no state."""

    def loads(self, path: Any) -> None:
        """Nothing to read: the sampler has no state."""

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Nothing to restore: the sampler has no state."""
