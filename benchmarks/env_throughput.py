"""Environment throughput: env steps per second, gymnasium vs the TorchRL wrapper.

Run from the repository root (a few minutes on a 2-core CPU box with the defaults)::

    .venv/bin/python benchmarks/env_throughput.py
    .venv/bin/python benchmarks/env_throughput.py --envs drone industrial_benchmark --steps 5000
    .venv/bin/python benchmarks/env_throughput.py --workers 2
    .venv/bin/python benchmarks/env_throughput.py --paths torchrl torchrl-serial torchrl-par --serial-envs 10

For each environment it measures, with uniformly random actions and a reset at every episode
end, the transitions per second of

* ``gym``              ``gymnasium.make(gym_id)``, one env, python loop;
* ``gym-sync-xN``      ``gymnasium.vector.SyncVectorEnv`` of N envs (N = ``--workers``);
* ``gym-async-xN``     ``gymnasium.vector.AsyncVectorEnv`` of N envs (N worker processes);
* ``torchrl``          ``make_env(name, seed=0)`` (GymEnv + DoubleToFloat/StepCounter/InitTracker);
* ``torchrl-serial-xS`` ``make_env(name, seed=0, num_envs=S, parallel=False)`` (SerialEnv of S
  envs stepped one after the other in the main process; S = ``--serial-envs``);
* ``torchrl-par-xN``   ``make_env(name, seed=0, num_envs=N)`` (ParallelEnv, N worker processes).

``--paths`` picks some of these kinds (``gym``, ``gym-sync``, ``gym-async``, ``torchrl``,
``torchrl-serial``, ``torchrl-par``); all by default.

The torchrl loops use ``env.rand_action`` + ``env.step_and_maybe_reset`` (what a collector
does, without storing the data). Vector paths count ``N`` transitions per batched step; vector
envs reset finished sub-envs in the same step (``AutoresetMode.SAME_STEP``). Every path runs a
warm-up (``--warmup`` steps, and worker start-up) before the timed ``time.perf_counter`` loop.
Environments use their registered default constructor arguments (Minitaur with
self-collision on). The script prints one table and exits 0.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from collections.abc import Callable
from functools import partial

import gymnasium as gym
import numpy as np
import torch
import torchrl
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

import torchrl_recon  # noqa: F401  (registers the gymnasium ids)
from torchrl_recon.envs import ENVS, get_entry, make_env, register_envs

# Timed steps per (env, path kind) when --steps is not given: chosen so that every measurement
# takes seconds, not minutes, on a 2-core CPU box (Minitaur steps cost ~5 ms, IB and Drone
# steps ~0.1 ms through gymnasium and ~1 ms through TorchRL).
PATHS = ("gym", "gym-sync", "gym-async", "torchrl", "torchrl-serial", "torchrl-par")
DEFAULT_STEPS = {
    "industrial_benchmark": {"gym": 20000, "torchrl": 5000},
    "drone": {"gym": 20000, "torchrl": 5000},
    "minitaur": {"gym": 1000, "torchrl": 1000},
}


def _gym_make(gym_id: str) -> gym.Env:
    register_envs()  # a no-op unless this runs in a freshly spawned worker
    return gym.make(gym_id)


def _time_gym_single(gym_id: str, steps: int, warmup: int) -> tuple[float, int]:
    env = _gym_make(gym_id)
    env.action_space.seed(0)
    env.reset(seed=0)

    def run(n: int) -> None:
        for _ in range(n):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()

    try:
        run(warmup)
        start = time.perf_counter()
        run(steps)
        return time.perf_counter() - start, steps
    finally:
        env.close()


def _time_gym_vector(
    vector_cls: Callable, gym_id: str, n_envs: int, steps: int, warmup: int
) -> tuple[float, int]:
    env = vector_cls(
        [partial(_gym_make, gym_id) for _ in range(n_envs)],
        autoreset_mode=AutoresetMode.SAME_STEP,
    )
    env.action_space.seed(0)
    env.reset(seed=0)

    def run(n: int) -> None:
        for _ in range(n):
            env.step(env.action_space.sample())  # finished sub-envs reset inside step

    try:
        run(max(1, warmup // n_envs))
        iterations = max(1, steps // n_envs)
        start = time.perf_counter()
        run(iterations)
        return time.perf_counter() - start, iterations * n_envs
    finally:
        env.close()


def _time_torchrl(
    name: str, num_envs: int, steps: int, warmup: int, parallel: bool = True
) -> tuple[float, int]:
    env = make_env(name, seed=0, num_envs=num_envs, parallel=parallel)
    torch.manual_seed(0)  # rand_action draws from torch's global RNG

    def run(td, n: int):
        for _ in range(n):
            td = env.rand_action(td)
            _, td = env.step_and_maybe_reset(td)
        return td

    try:
        td = env.reset()  # starts the ParallelEnv workers (not timed)
        td = run(td, max(1, warmup // num_envs))
        iterations = max(1, steps // num_envs)
        start = time.perf_counter()
        run(td, iterations)
        return time.perf_counter() - start, iterations * num_envs
    finally:
        env.close()


def _load() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help="timed transitions per measurement for every env and path "
        f"(default: per env and path kind, {DEFAULT_STEPS})",
    )
    parser.add_argument(
        "--envs",
        nargs="+",
        default=list(ENVS),
        help="short names or gymnasium ids (default: all three)",
    )
    parser.add_argument(
        "--workers", type=int, default=2, help="envs / worker processes of the vector paths"
    )
    parser.add_argument(
        "--warmup", type=int, default=200, help="untimed transitions before each measurement"
    )
    parser.add_argument(
        "--serial-envs", type=int, default=10, help="envs of the torchrl-serial path (SerialEnv)"
    )
    parser.add_argument(
        "--paths",
        nargs="+",
        choices=PATHS,
        default=list(PATHS),
        help="which path kinds to measure (default: all)",
    )
    args = parser.parse_args(argv)
    if args.steps is not None and args.steps < 1:
        parser.error("--steps must be >= 1")
    if args.workers < 1 or args.serial_envs < 1:
        parser.error("--workers and --serial-envs must be >= 1")
    names = [get_entry(n).name for n in args.envs]
    n, s = args.workers, args.serial_envs

    print(
        f"# {datetime.datetime.now().isoformat(timespec='seconds')}  "
        f"{platform.platform()}  cpus={os.cpu_count()}  load(1/5/15 min)={_load()}"
    )
    print(
        f"# python {sys.version.split()[0]}  torch {torch.__version__}  "
        f"torchrl {torchrl.__version__}  gymnasium {gym.__version__}  "
        f"numpy {np.__version__}  torch threads {torch.get_num_threads()}"
    )
    rows = []
    for name in names:
        gym_id = get_entry(name).gym_id
        gym_steps = args.steps or DEFAULT_STEPS[name]["gym"]
        trl_steps = args.steps or DEFAULT_STEPS[name]["torchrl"]
        measurements = [
            ("gym", "gym", partial(_time_gym_single, gym_id, gym_steps, args.warmup)),
            (
                "gym-sync",
                f"gym-sync-x{n}",
                partial(_time_gym_vector, SyncVectorEnv, gym_id, n, gym_steps, args.warmup),
            ),
            (
                "gym-async",
                f"gym-async-x{n}",
                partial(_time_gym_vector, AsyncVectorEnv, gym_id, n, gym_steps, args.warmup),
            ),
            ("torchrl", "torchrl", partial(_time_torchrl, name, 1, trl_steps, args.warmup)),
            (
                "torchrl-serial",
                f"torchrl-serial-x{s}",
                partial(_time_torchrl, name, s, trl_steps, args.warmup, parallel=False),
            ),
            (
                "torchrl-par",
                f"torchrl-par-x{n}",
                partial(_time_torchrl, name, n, trl_steps, args.warmup),
            ),
        ]
        for kind, path, measure in measurements:
            if kind not in args.paths:
                continue
            seconds, transitions = measure()
            rows.append((name, path, transitions, seconds, transitions / seconds))
            print(
                f"# done {name:<20} {path:<16} {transitions / seconds:>10.0f} steps/s", flush=True
            )

    print(f"# load after (1/5/15 min)={_load()}")
    print()
    print("| env | path | steps | seconds | steps/s |")
    print("|---|---|---:|---:|---:|")
    for name, path, transitions, seconds, rate in rows:
        print(f"| {name} | {path} | {transitions} | {seconds:.2f} | {rate:,.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
