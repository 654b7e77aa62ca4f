"""The library's parts in a torchrl Trainer built by hand: TorchRL's Collector, ReplayBuffer and
Trainer with ModelFitStepper, LogIteration and FitNormalization, at smoke scale."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler
from torchrl.envs import TransformedEnv
from torchrl.trainers import ReplayBufferTrainer, Trainer

from torchrl_recon.data.buffers import TRAJ_KEY
from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.fitting.online import FitSchedule
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.objectives import WorldModelPredictionLoss
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.trainers import (
    FitNormalization,
    LogIteration,
    ModelFitStepper,
    OnlineCollector,
    TimedPolicy,
)

SCHEDULE = FitSchedule(
    steps=4, refit_steps=2, eval_every=2, slice_len=8, num_slices=4, val_fraction=0.34
)


def _policy(env, world, estimator=None) -> MPCPolicy:
    model = PlanningModel.from_env(world, pendulum, env, uncertainty=estimator)
    planner = CEMPlanner(model, Objective(), horizon=4, num_candidates=16, num_elites=4)
    return MPCPolicy(planner)


def _collector(env, policy, frames: int, random_frames: int) -> Collector:
    with warnings.catch_warnings():  # TorchRL says once per process that it unwraps by default
        warnings.filterwarnings("ignore", "Nested TransformedEnvs are automatically unwrapped")
        primed = TransformedEnv(env, policy.make_tensordict_primer())  # TorchRL's default
    return Collector(
        primed,
        policy,
        frames_per_batch=20,
        total_frames=frames,
        init_random_frames=random_frames,
        split_trajs=False,
    )


def test_a_hand_built_trainer_fits_after_the_random_frames_and_records_each_batch():
    torch.manual_seed(0)
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    world = LSTMWorldModel(3, 1, window=4)
    policy = TimedPolicy(_policy(env, world))
    buffer = ReplayBuffer(storage=LazyTensorStorage(100))
    stepper = ModelFitStepper(world, None, buffer, schedule=SCHEDULE)
    trainer = Trainer(
        collector=_collector(env, policy, 100, 60),
        total_frames=100,
        frame_skip=1,
        optim_steps_per_batch=1,
        loss_module=WorldModelPredictionLoss(world),
        optimization_stepper=stepper,
        progress_bar=False,
        log_interval=0,
    )
    trainer.register_op("batch_process", ReplayBufferTrainer(buffer).extend)
    log = LogIteration(world, slice_len=8, timed_policy=policy)
    log.register(trainer)
    trainer.train()
    records = log.records
    assert [r.policy for r in records] == ["random"] * 3 + ["mpc"] * 2
    assert [r.env_steps for r in records] == [20, 40, 60, 80, 100]
    assert stepper.fits == 3 and stepper.fitted_steps == 100  # after frames 60, 80 and 100
    assert [r.fit_s > 0 for r in records] == [False, False, True, True, True]
    assert [math.isnan(r.model_error) for r in records] == [True] * 3 + [False] * 2
    assert all(r.plan_s == 0 for r in records[:3]) and all(r.plan_s > 0 for r in records[3:])
    assert all(len(r.episode_returns) == 1 for r in records)  # 20-step episodes, batches of 20
    assert sum(r.replans for r in records[3:]) > 0


def test_the_fit_step_refuses_what_it_cannot_fit_from():
    world = LSTMWorldModel(3, 1, window=4)
    small = ReplayBuffer(storage=LazyTensorStorage(10))
    small.extend(TensorDict({"observation": torch.zeros(15, 3)}, [15]))
    with pytest.raises(ValueError, match="holds 10 of the 15 steps written"):
        ModelFitStepper(world, None, small).data()
    with pytest.raises(ValueError, match="the replay buffer is empty at the first fit"):
        ModelFitStepper(world, None, ReplayBuffer(storage=LazyTensorStorage(10))).data()
    with pytest.raises(TypeError, match="schedule must be a FitSchedule or None"):
        ModelFitStepper(world, None, small, schedule={"steps": 3})
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    collector = OnlineCollector(env, None, iterations=0, steps_per_iteration=20, random_steps=40)
    with pytest.raises(ValueError, match="optim_steps_per_batch=1, got 5"):
        Trainer(
            collector=collector,
            total_frames=40,
            frame_skip=1,
            optim_steps_per_batch=5,
            loss_module=WorldModelPredictionLoss(world),
            optimization_stepper=ModelFitStepper(world, None, small),
            progress_bar=False,
        )


def test_a_trainer_with_a_plain_loss_says_what_is_missing_then_runs_with_fit_normalization():
    """The hand-built agent of the tracker: TorchRL's loss step on WorldModelPredictionLoss and
    Adam, a SliceSampler buffer. Without FitNormalization the first plan refuses in one line
    naming it; with it the normalisation is fitted from the first (random) batch and the MPC
    batches plan."""

    def trainer(with_hook: bool) -> tuple[Trainer, LSTMWorldModel]:
        torch.manual_seed(0)
        env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
        world = LSTMWorldModel(3, 1, window=4)
        estimator = ReconstructionUncertainty(3, 1, window=4)
        policy = _policy(env, world, estimator)
        buffer = ReplayBuffer(
            storage=LazyTensorStorage(80),
            sampler=SliceSampler(slice_len=8, traj_key=TRAJ_KEY),
            batch_size=32,
        )
        loss = WorldModelPredictionLoss(world, mode="one_step", slice_len=8)
        out = Trainer(
            collector=_collector(env, policy, 80, 40),
            total_frames=80,
            frame_skip=1,
            optim_steps_per_batch=3,
            loss_module=loss,
            optimizer=torch.optim.Adam(loss.parameters(), lr=1e-3),
            progress_bar=False,
        )
        if with_hook:
            FitNormalization(world, estimator).register(out)
        ReplayBufferTrainer(buffer).register(out)
        return out, world, estimator

    bare, world, _ = trainer(with_hook=False)
    unfitted_loss = "WorldModelPredictionLoss is computed with the world model's normalisation"
    with pytest.warns(UserWarning, match=unfitted_loss):  # the loss steps before the plan
        with pytest.raises(ValueError, match="never fitted") as err:
            bare.train()
    assert "FitNormalization" in str(err.value) and "\n" not in str(err.value)
    hooked, world, estimator = trainer(with_hook=True)
    hooked.train()
    assert bool(world.obs_norm.fitted) and bool(estimator.input_norm.fitted)
    assert hooked.collected_frames == 80


def test_fit_normalization_fits_once_and_leaves_a_fitted_model_alone():
    world = LSTMWorldModel(3, 1, window=4, num_members=2)
    hook = FitNormalization(world)
    obs = torch.randn(20, 3)
    batch = TensorDict(
        {"observation": obs, "action": torch.rand(20, 1), ("next", "observation"): obs + 2}, [20]
    )
    hook(batch)
    assert world.delta_norm.loc.shape == (2, 3)
    assert torch.allclose(world.delta_norm.loc, torch.full((2, 3), 2.0))
    hook(batch.apply(lambda x: x * 10))  # later batches change nothing
    assert torch.allclose(world.delta_norm.loc, torch.full((2, 3), 2.0))
    assert FitNormalization(world).state_dict() == {"done": False}


def test_the_online_collector_numbers_trajectories_on_and_resumes_at_an_iteration():
    torch.manual_seed(0)
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=10)
    world = LSTMWorldModel(3, 1, window=4)
    obs = torch.randn(30, 3)
    world.fit_normalization(obs, torch.rand(30, 1) * 4 - 2, obs)
    policy = _policy(env, world)

    def collector() -> OnlineCollector:
        return OnlineCollector(
            env, policy, iterations=2, steps_per_iteration=20, random_steps=30, seed=3
        )

    whole = list(collector())
    ids = torch.cat([b.get(TRAJ_KEY) for b in whole])
    assert ids.tolist() == sorted(ids.tolist()) and len(ids.unique()) == 3 + 2 + 2
    keys = set(whole[0].keys(True, True))
    assert all(set(b.keys(True, True)) == keys for b in whole)  # the env's keys only
    resumed = collector()
    resumed.load_state_dict(collector().state_dict() | {"iteration": 2, "next_traj_id": 5})
    (last,) = list(resumed)
    assert (last == whole[2]).all()
    assert resumed.batch_info["policy"] == "mpc" and resumed.batch_info["iteration"] == 2
