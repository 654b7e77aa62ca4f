"""An OnlineTrainer stopped after an iteration and restored from TorchRL's own checkpoint
(either format; the unified one as a directory or an archive) goes on to the same records and
data as an uninterrupted run; the checkpoint carries a manifest its load checked; no checkpoint
file is a pickle. Damaged checkpoints: test_verified_checkpoint.py."""

from __future__ import annotations

import warnings

import pytest
import torch
from torchrl.checkpoint import Checkpoint

from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.fitting.online import FitSchedule
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.trainers import OnlineCollector, OnlineTrainer, verify_checkpoint

SCHEDULE = FitSchedule(
    steps=4, refit_steps=2, eval_every=2, slice_len=8, num_slices=4, val_fraction=0.34
)


FORMATS = {"directory": "torchrl.checkpoint", "archive": "torchrl.checkpoint archive"}
FORMATS |= {"legacy": "legacy torch"}


def _trainer(path=None, fmt: str = "directory", seed: int = 0) -> OnlineTrainer:
    """The small Trainer of these tests; with ``path``, saving there after every batch in
    ``fmt``: a unified ``Checkpoint`` (``"directory"``, ``"archive"``) or ``"legacy"``."""
    torch.manual_seed(seed)
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world = LSTMWorldModel(3, 1, window=4)
    estimator = ReconstructionUncertainty(3, 1, window=4)
    model = PlanningModel.from_env(world, pendulum, env, uncertainty=estimator)
    planner = CEMPlanner(model, Objective(beta=0.1), horizon=4, num_candidates=16, num_elites=4)
    collector = OnlineCollector(
        env, MPCPolicy(planner), iterations=3, steps_per_iteration=20, random_steps=40
    )
    saving = {}
    if path is not None:
        saving = dict(save_trainer_file=path, save_trainer_interval=0)
        saving |= {"checkpoint": Checkpoint(format=fmt)} if fmt != "legacy" else {}
    return OnlineTrainer(
        collector=collector,
        world_model=world,
        estimator=estimator,
        schedule=SCHEDULE,
        progress=False,
        **saving,
    )


def _numbers(trainer: OnlineTrainer) -> list[tuple]:
    return [
        (r.iteration, r.env_steps, r.episode_returns, r.model_error, r.mean_uncertainty, r.replans)
        for r in trainer.records[1:]  # iteration 0's model error is NaN
    ]


@pytest.fixture(scope="module")
def whole() -> OnlineTrainer:
    """The uninterrupted run every format's resume is compared with (the same for all three:
    trained once per worker, not once per format)."""
    trainer = _trainer()
    trainer.train()
    return trainer


@pytest.mark.parametrize("fmt", list(FORMATS), ids=list(FORMATS.values()))
def test_a_stopped_trainer_resumes_from_its_checkpoint_to_the_same_numbers(tmp_path, fmt, whole):
    path = tmp_path / "trainer.pt"
    stopped = _trainer(path, fmt)
    stop = lambda: stopped.collected_frames >= 80 and stopped.request_stop("killed")  # noqa: E731
    stopped.register_op("post_steps", stop)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy format's FutureWarning
        stopped.train()
    assert len(stopped.records) == 3  # iterations 0-2 of 0-3
    assert verify_checkpoint(path) is True  # checked against the manifest saved with it
    resumed = _trainer(path, fmt)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "loaded without checking" warning
        resumed.load_from_file(path)
    assert resumed.collector.iteration == 3 and len(resumed.buffer) == 80
    resumed.train()
    assert _numbers(resumed) == _numbers(whole)
    assert (resumed.data() == whole.data()).all()
    if fmt == "directory":
        assert not [p for p in path.rglob("*") if p.suffix in (".pkl", ".pickle", ".pt")]
