"""Learn Pendulum-v1 online with TorchRL's own Collector, ReplayBuffer and Trainer, and the
library's hooks (docs/torchrl_trainer.md).

    python examples/torchrl_trainer.py --frames 2000 [--threads 1]

It computes on one CPU thread (``torch.set_num_threads(1)``): beside another process, more
threads than free cores make it crawl; ``--threads N`` gives it N.

The first 400 frames are random (the Collector's ``init_random_frames``), then MPC with CEM
(PETS's budget: 350 candidates x 5 iterations x 15 steps) plans every step with an LSTM world
model that ``ModelFitStepper`` refits after every batch of 200 frames. The last line is
``return <mean return of the last half of the MPC episodes> random <the random episodes' mean>``.
"""

from __future__ import annotations

import argparse

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.trainers import ReplayBufferTrainer, Trainer

from torchrl_recon.envs import make_env
from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.fitting.online import FitSchedule
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.objectives import WorldModelPredictionLoss
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.trainers import LogIteration, ModelFitStepper, TimedPolicy

FULL = dict(episode=200, batch=200, random=400, candidates=350, elites=35, cem_iterations=5)
FULL |= dict(horizon=15, fit_steps=1000, refit_steps=500, slice_len=20, num_slices=32)
SMOKE = dict(episode=20, batch=20, random=40, candidates=16, elites=4, cem_iterations=2)
SMOKE |= dict(horizon=5, fit_steps=4, refit_steps=2, slice_len=8, num_slices=4)


def main(argv: list[str] | None = None) -> tuple[float, float]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2000, help="env steps in all")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, a check of the wiring")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error(f"--threads must be an int >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    size = SMOKE if args.smoke else FULL
    torch.manual_seed(args.seed)

    env = make_env("Pendulum-v1", seed=args.seed, max_episode_steps=size["episode"])
    world = LSTMWorldModel(3, 1, window=4)
    planner = CEMPlanner(
        PlanningModel.from_env(world, pendulum, env),
        Objective(),
        horizon=size["horizon"],
        num_candidates=size["candidates"],
        iterations=size["cem_iterations"],
        num_elites=size["elites"],
    )
    policy = TimedPolicy(MPCPolicy(planner))
    env.append_transform(policy.make_tensordict_primer())  # the MPC state travels in the env
    collector = Collector(
        env,
        policy,
        frames_per_batch=size["batch"],
        total_frames=args.frames,
        init_random_frames=size["random"],
        split_trajs=False,
    )
    buffer = ReplayBuffer(storage=LazyTensorStorage(args.frames))
    schedule = FitSchedule(
        steps=size["fit_steps"],
        refit_steps=size["refit_steps"],
        slice_len=size["slice_len"],
        num_slices=size["num_slices"],
        mode="one_step",
        val_fraction=0.2,
        eval_every=min(100, size["fit_steps"]),
    )
    trainer = Trainer(
        collector=collector,
        total_frames=args.frames,
        frame_skip=1,
        optim_steps_per_batch=1,  # one whole fit (or warm refit) after each batch
        loss_module=WorldModelPredictionLoss(world, mode="one_step"),
        optimization_stepper=ModelFitStepper(
            world, None, buffer, schedule=schedule, seed=args.seed
        ),
        progress_bar=not args.smoke,
        seed=args.seed,
        log_interval=0,
    )
    trainer.register_op("batch_process", ReplayBufferTrainer(buffer).extend)
    log = LogIteration(world, slice_len=schedule.slice_len, timed_policy=policy)
    log.register(trainer)
    trainer.train()

    random = [r for rec in log.records if rec.policy == "random" for r in rec.episode_returns]
    planned = [r for rec in log.records if rec.policy == "mpc" for r in rec.episode_returns]
    late = planned[len(planned) // 2 :] or planned
    mean = sum(late) / max(len(late), 1)
    random_mean = sum(random) / max(len(random), 1)
    print(f"return {mean:.1f} random {random_mean:.1f}")
    return mean, random_mean


if __name__ == "__main__":
    main()
