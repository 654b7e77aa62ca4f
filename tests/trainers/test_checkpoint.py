"""An OnlineTrainer stopped after an iteration and restored from TorchRL's own checkpoint
(either format) goes on to the same records and data as an uninterrupted run; no checkpoint
file is a pickle."""

from __future__ import annotations

import warnings

import pytest
import torch
from torchrl.checkpoint import Checkpoint

from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.trainers import OnlineCollector, OnlineTrainer
from torchrl_recon.training.online import FitSchedule

SCHEDULE = FitSchedule(
    steps=4, refit_steps=2, eval_every=2, slice_len=8, num_slices=4, val_fraction=0.34
)


def _trainer(path=None, unified: bool = True) -> OnlineTrainer:
    torch.manual_seed(0)
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
        saving |= {"checkpoint": Checkpoint()} if unified else {}
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


@pytest.mark.parametrize("unified", [True, False], ids=["torchrl.checkpoint", "legacy torch"])
def test_a_stopped_trainer_resumes_from_its_checkpoint_to_the_same_numbers(tmp_path, unified):
    whole = _trainer()
    whole.train()
    path = tmp_path / "trainer.pt"
    stopped = _trainer(path, unified)
    stop = lambda: stopped.collected_frames >= 80 and stopped.request_stop("killed")  # noqa: E731
    stopped.register_op("post_steps", stop)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy format's FutureWarning
        stopped.train()
    assert len(stopped.records) == 3  # iterations 0-2 of 0-3
    resumed = _trainer(path, unified)
    resumed.load_from_file(path)
    assert resumed.collector.iteration == 3 and len(resumed.buffer) == 80
    resumed.train()
    assert _numbers(resumed) == _numbers(whole)
    assert (resumed.data() == whole.data()).all()
    if unified:
        assert not [p for p in path.rglob("*") if p.suffix in (".pkl", ".pickle", ".pt")]
