"""A Trainer module that checkpoints a replay buffer's steps as tensors (no pickle)."""

from __future__ import annotations

from typing import Any

from tensordict import TensorDict
from torchrl.data import ReplayBuffer
from torchrl.trainers import Trainer, TrainerHookBase

from torchrl_recon.modules.checks import check_type


class ReplayBufferSteps(TrainerHookBase):
    """The replay buffer's steps in the Trainer's checkpoint, as plain tensors: ``state_dict``
    is ``{"steps": {key: tensor}}`` and loading refills the buffer with them in the same order.
    TorchRL's ``ReplayBufferTrainer`` checkpoints the buffer's own state, which its unified
    checkpoint format writes with a ``pickle`` file beside the tensors (``prefetch.pkl``, loaded
    with ``pickle.load``); this one keeps every file of a checkpoint data, in either format
    (TorchRL's legacy format loads with ``weights_only=True``). Registered as a module only
    (``replay_buffer_steps``): the batches are written by ``ReplayBufferTrainer(buffer).extend``
    at ``batch_process``, and neither the buffer nor a ``ReplayBufferTrainer`` may be given to the
    Trainer as its ``replay_buffer`` or module ``replay_buffer``, which TorchRL checkpoints its
    own way.

    Examples:
        >>> import torch
        >>> from torchrl.data import LazyTensorStorage
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(10))
        >>> _ = rb.extend(TensorDict({"x": torch.arange(4.0), ("next", "x"): torch.ones(4)}, [4]))
        >>> state = ReplayBufferSteps(rb).state_dict()
        >>> other = ReplayBuffer(storage=LazyTensorStorage(10))
        >>> ReplayBufferSteps(other).load_state_dict(state)
        >>> other[:]["x"].tolist(), len(other)
        ([0.0, 1.0, 2.0, 3.0], 4)
    """

    def __init__(self, replay_buffer: ReplayBuffer) -> None:
        check_type("replay_buffer", replay_buffer, ReplayBuffer, "a torchrl ReplayBuffer")
        self.replay_buffer = replay_buffer

    def state_dict(self) -> dict[str, Any]:
        rb = self.replay_buffer
        return {"steps": rb[:].to_dict() if len(rb) else {}}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        steps = state_dict["steps"]
        self.replay_buffer.empty()
        if steps:
            self.replay_buffer.extend(TensorDict.from_dict(steps, batch_dims=1))

    def register(self, trainer: Trainer, name: str = "replay_buffer_steps") -> None:
        trainer.register_module(name, self)
