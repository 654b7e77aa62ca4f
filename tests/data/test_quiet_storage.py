"""A fit logs nothing: the sequence buffers' storages allocate without TorchRL's INFO line."""

from __future__ import annotations

import logging

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_recon.data import make_sequence_buffer, quiet_storage_init
from torchrl_recon.fitting import FitSchedule
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.trainers import ModelFitStepper

INIT_LINE = "Initialized LazyTensorStorage"


class _Records(logging.Handler):
    """The ``torchrl`` logger's records (it does not propagate to the root's handlers)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())

    def __enter__(self) -> _Records:
        logger = logging.getLogger("torchrl")
        self.saved_level = logger.level
        logger.setLevel(logging.INFO)
        logger.addHandler(self)
        return self

    def __exit__(self, *exc) -> None:
        logger = logging.getLogger("torchrl")
        logger.removeHandler(self)
        logger.setLevel(self.saved_level)


def _steps(n: int = 60) -> TensorDict:
    obs = torch.randn(n, 3)
    return TensorDict(
        {
            "observation": obs,
            "action": torch.rand(n, 1),
            ("next", "observation"): 0.9 * obs,
            ("collector", "traj_ids"): torch.arange(n) // 20,
        },
        [n],
    )


def test_a_plain_lazy_storage_logs_its_line_and_the_context_leaves_out_that_line_only():
    with _Records() as records:
        ReplayBuffer(storage=LazyTensorStorage(10)).extend(_steps(4))
    assert any(m.startswith(INIT_LINE) for m in records.messages)  # TorchRL still says it
    with _Records() as records:
        with quiet_storage_init():
            ReplayBuffer(storage=LazyTensorStorage(10)).extend(_steps(4))
            logging.getLogger("torchrl").info("another line")
        ReplayBuffer(storage=LazyTensorStorage(10)).extend(_steps(4))  # after it: said again
    assert records.messages.count("another line") == 1
    assert sum(m.startswith(INIT_LINE) for m in records.messages) == 1


def test_sequence_buffers_and_the_fits_log_no_storage_line():
    rb = ReplayBuffer(storage=LazyTensorStorage(100))
    with quiet_storage_init():
        rb.extend(_steps())
    with _Records() as records:
        make_sequence_buffer(100, slice_len=8, num_slices=4).extend(_steps())
        schedule = FitSchedule(steps=2, eval_every=2, slice_len=8, num_slices=4, val_fraction=0.34)
        stepper = ModelFitStepper(LSTMWorldModel(3, 1, window=4), None, rb, schedule=schedule)
        stepper.step(None, None)  # the first fit
        stepper.step(None, None)  # a refit
    assert not [m for m in records.messages if m.startswith(INIT_LINE)]


def test_the_online_trainers_buffer_fills_without_the_storage_line():
    """``OnlineTrainer`` extends its buffer through ``quiet_extend`` (a TorchRL
    ``ReplayBufferTrainer``'s extend): its first batch logs no storage line."""
    from torchrl.trainers import ReplayBufferTrainer

    from torchrl_recon.trainers.online import quiet_extend

    rb = ReplayBuffer(storage=LazyTensorStorage(100))
    with _Records() as records:
        quiet_extend(ReplayBufferTrainer(rb))(_steps())
    assert len(rb) == 60
    assert not [m for m in records.messages if m.startswith(INIT_LINE)]
