"""mbrl-lib's PETS on a gymnasium task, for the side-by-side of docs/online.md (issue 33).

Runs in its own virtual environment (mbrl 0.2.0 pins old Hydra/OmegaConf and NumPy; see
``benchmarks/peers/README.md`` for the install), not in the project's. It calls mbrl's own
``mbrl.algorithms.pets.train`` with its shipped ``pets`` algorithm and ``gaussian_mlp_ensemble``
model configs; the CEM block (``cem.yaml``, missing from the 0.2.0 wheel) and the per-task
overrides are written here, from mbrl-lib's ``v0.2.0`` examples (``pets_cartpole`` numbers
for the tasks it has no file for). Writes ``results.csv`` (mbrl's: one row per PETS episode,
its env steps counted after the random first episode, and its return) and ``timing.json``
(planning ms per step, fit s per refit) to ``--out``.

Run (from the checkout, with the peers' venv):

    /path/to/peers-venv/bin/python benchmarks/peers/pets.py --task pendulum --seed 0 --out outputs/peers/pets/pendulum/seed0
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time
from pathlib import Path

import gymnasium as gym
import mbrl.algorithms.pets as pets
import mbrl.env.termination_fns as term_fns
import mbrl.models
import mbrl.planning
import mbrl.util.common
import numpy as np
import omegaconf
import torch

CONF = Path(mbrl.__file__).parent / "examples" / "conf"

CEM = {  # mbrl-lib v0.2.0, mbrl/examples/conf/action_optimizer/cem.yaml
    "_target_": "mbrl.planning.CEMOptimizer",
    "num_iterations": "${overrides.cem_num_iters}",
    "elite_ratio": "${overrides.cem_elite_ratio}",
    "population_size": "${overrides.cem_population_size}",
    "alpha": "${overrides.cem_alpha}",
    "lower_bound": "???",
    "upper_bound": "???",
    "return_mean_elites": True,
    "device": "${device}",
    "clipped_normal": False,
}

CARTPOLE = {  # mbrl-lib v0.2.0, overrides/pets_cartpole.yaml: PETS's budget, 350 × 5 × 15
    "learned_rewards": False,
    "num_elites": 5,
    "model_lr": 7.5e-4,
    "model_wd": 3e-5,
    "model_batch_size": 256,
    "validation_ratio": 0,
    "patience": 25,
    "num_epochs_train_model": 25,
    "planning_horizon": 15,
    "cem_num_iters": 5,
    "cem_elite_ratio": 0.1,
    "cem_population_size": 350,
    "cem_alpha": 0.1,
}


def pendulum_reward(act: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """−(θ² + 0.1·θ̇² + 0.001·u²) of the state reached (mbrl's reward functions see only the
    action and the next observation), ``[N, 1]``."""
    theta = torch.atan2(next_obs[:, 1], next_obs[:, 0])
    cost = theta.pow(2) + 0.1 * next_obs[:, 2].pow(2) + 0.001 * act[:, 0].pow(2)
    return -cost[:, None]


def _our_costs():
    """``torchrl_recon/envs/gym_costs.py`` of this checkout, loaded by its path (it needs only
    torch; the package itself does not install beside mbrl 0.2.0), so both agents optimise the
    very same cost functions."""
    path = Path(__file__).resolve().parents[2] / "torchrl_recon" / "envs" / "gym_costs.py"
    spec = importlib.util.spec_from_file_location("gym_costs", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


COSTS = _our_costs()


def mountain_car_reward(act: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """−``gym_costs.mountain_car`` (it reads only the action and the next observation), ``[N, 1]``."""
    return -COSTS.mountain_car(None, act, next_obs)[:, None]


def mountain_car_termination(act: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """``gym_costs.mountain_car_termination``, the env's own end, ``[N, 1]``."""
    return COSTS.mountain_car_termination(None, act, next_obs)[:, None]


def inverted_pendulum_reward(act: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """+1 per step the pole stays up, as the env's own reward."""
    return (~term_fns.inverted_pendulum(act, next_obs)).float()


TASKS = {
    "pendulum": ("Pendulum-v1", 200, pendulum_reward, term_fns.no_termination, CARTPOLE),
    "mountain_car": (
        "MountainCarContinuous-v0",
        999,
        mountain_car_reward,
        mountain_car_termination,
        CARTPOLE,
    ),
    "inverted_pendulum": (  # overrides/pets_inv_pendulum.yaml
        "InvertedPendulum-v4",
        1000,
        inverted_pendulum_reward,
        term_fns.inverted_pendulum,
        {
            **CARTPOLE,
            "model_lr": 0.00143,
            "model_wd": 0.000033,
            "validation_ratio": 0.2,
            "patience": 50,
            "num_epochs_train_model": 31,
            "planning_horizon": 45,
            "cem_elite_ratio": 0.078,
            "cem_population_size": 480,
            "cem_alpha": 0.134484,
        },
    ),
}


def config(task: str, seed: int, num_steps: int, episode_steps: int) -> omegaconf.DictConfig:
    """PETS's config for ``task``: its shipped algorithm and model files, CEM and overrides."""
    _, _, _, _, overrides = TASKS[task]
    load = lambda name: omegaconf.OmegaConf.load(CONF / name)  # noqa: E731
    cfg = omegaconf.OmegaConf.create(
        {
            "seed": seed,
            "device": "cpu",
            "debug_mode": False,
            "algorithm": load("algorithm/pets.yaml"),
            "dynamics_model": load("dynamics_model/gaussian_mlp_ensemble.yaml"),
            "action_optimizer": CEM,
            "overrides": {
                **overrides,
                "env": task,
                "trial_length": episode_steps,
                "num_steps": num_steps,
                "freq_train_model": episode_steps,
            },
        }
    )
    # mbrl 0.2.0 with Hydra 1.3: build the model and optimizer without recursing into them
    cfg.dynamics_model._recursive_ = False
    cfg.algorithm.agent._recursive_ = False
    return cfg


class Timed:
    """Wraps ``obj.name`` to sum its wall time and count its calls."""

    def __init__(self, obj, name: str) -> None:
        self.seconds, self.calls, original = 0.0, 0, getattr(obj, name)

        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
                self.calls += 1

        setattr(obj, name, timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(TASKS), required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--episodes", type=int, default=10, help="PETS episodes after the random one"
    )
    parser.add_argument("--episode-steps", type=int, help="episode length (default: the task's)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    gym_id, episode_steps, reward_fn, term_fn, _ = TASKS[args.task]
    episode_steps = args.episode_steps or episode_steps
    env = gym.make(gym_id, max_episode_steps=episode_steps)
    env.reset(seed=args.seed)
    env.action_space.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    # PETS counts its steps after the random episode (``initial_exploration_steps``)
    cfg = config(args.task, args.seed, episode_steps * args.episodes, episode_steps)
    args.out.mkdir(parents=True, exist_ok=True)
    plan = Timed(mbrl.planning.TrajectoryOptimizerAgent, "act")
    fit = Timed(mbrl.util.common, "train_model_and_save_model_and_data")
    start = time.perf_counter()
    pets.train(env, term_fn, reward_fn, cfg, silent=False, work_dir=str(args.out))
    timing = {
        "task": args.task,
        "gym_id": gym_id,
        "seed": args.seed,
        "random_steps": episode_steps,  # PETS's random first episode (initial_exploration_steps)
        "wall_s": time.perf_counter() - start,
        "plan_ms_per_step": 1000 * plan.seconds / max(plan.calls, 1),
        "plan_calls": plan.calls,
        "fit_s_per_refit": fit.seconds / max(fit.calls, 1),
        "refits": fit.calls,
        "threads": args.threads,
        "versions": {"mbrl": mbrl.__version__, "torch": torch.__version__},
    }
    (args.out / "timing.json").write_text(json.dumps(timing, indent=1) + "\n")
    print(json.dumps(timing))


if __name__ == "__main__":
    main()
