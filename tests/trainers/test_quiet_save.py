"""A legacy trainer checkpoint (``save_trainer_file`` without ``checkpoint=``) saves without
TorchRL's two warnings that the format is going away, at every save."""

from __future__ import annotations

import warnings

from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.fitting.online import FitSchedule
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.trainers import OnlineCollector, OnlineTrainer
from torchrl_recon.trainers.checkpoint import LEGACY_SAVE_WARNINGS


def test_a_legacy_save_gives_none_of_torchrls_format_warnings(tmp_path):
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world = LSTMWorldModel(3, 1, window=4, hidden_size=8, dense_size=8)
    planner = CEMPlanner(
        PlanningModel.from_env(world, pendulum, env),
        Objective(),
        horizon=3,
        num_candidates=8,
        iterations=1,
        num_elites=2,
    )
    collector = OnlineCollector(
        env, MPCPolicy(planner), iterations=1, steps_per_iteration=20, random_steps=40
    )
    trainer = OnlineTrainer(
        collector=collector,
        world_model=world,
        estimator=None,
        schedule=FitSchedule(
            steps=2, refit_steps=1, eval_every=1, slice_len=8, num_slices=2, val_fraction=0.5
        ),
        progress=False,
        save_trainer_file=tmp_path / "trainer.pt",
        save_trainer_interval=0,
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer.train()
    assert (tmp_path / "trainer.pt").exists()
    shown = [str(w.message) for w in caught]
    for start, _ in LEGACY_SAVE_WARNINGS:
        assert not [m for m in shown if m.startswith(start)], shown
