"""Cost of the run directory's integrity checks at paper scale (Minitaur explore: 40,000 steps).

A run directory of the size of a paper-scale Minitaur explore run is written through
:class:`~torchrl_recon.experiments.stages.Stages` (10,000 initial + 15,000 random + 3 × 5,000
guided steps of 34-dim observations and 8-dim actions, 100 validation trajectories of 110 steps,
three checkpoints of the paper's networks, 2 × 10 retrainings). It then times what a resumed
run adds: checking every stage record and hashing every file it lists (:meth:`Stages.verify`),
next to reading the buffers back (:meth:`Stages.load_data`), which a resume does anyway.

Run: python benchmarks/run_dir_integrity.py [--scale 1.0] [--repeats 5]
Prints the sizes, the median times, and ``ratio: X`` = verify time / load time.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path

import torch
from _common import parse_args
from tensordict import TensorDict

from torchrl_recon.estimators import ReconstructionUncertainty
from torchrl_recon.experiments.stages import Stages
from torchrl_recon.fitting import save_checkpoint
from torchrl_recon.modules import LSTMWorldModel

OBS_DIM, ACTION_DIM, WINDOW, EPISODE = 34, 8, 10, 100  # Minitaur dims, paper's T


def transitions(steps: int, episode: int = EPISODE) -> TensorDict:
    """Random transitions with the keys an explore run stores."""
    return TensorDict(
        {
            "observation": torch.randn(steps, OBS_DIM),
            "action": torch.rand(steps, ACTION_DIM) * 2 - 1,
            "is_init": torch.arange(steps)[:, None] % episode == 0,
            "step_count": (torch.arange(steps)[:, None] % episode),
            ("next", "observation"): torch.randn(steps, OBS_DIM),
            ("next", "reward"): torch.randn(steps, 1),
            ("next", "done"): torch.zeros(steps, 1, dtype=torch.bool),
            ("next", "terminated"): torch.zeros(steps, 1, dtype=torch.bool),
            ("next", "truncated"): torch.zeros(steps, 1, dtype=torch.bool),
            ("collector", "traj_ids"): torch.arange(steps) // episode,
        },
        [steps],
    )


def build(run_dir: Path, scale: float) -> list[str]:
    """Write the stages of a paper-scale explore run; return the names of its data stages."""
    stages = Stages(run_dir, seed=0)
    n = lambda steps: max(EPISODE, int(steps * scale))  # noqa: E731
    world = LSTMWorldModel(OBS_DIM, ACTION_DIM, window=WINDOW, hidden_size=32, dense_size=32)
    estimator = ReconstructionUncertainty(OBS_DIM, ACTION_DIM, window=WINDOW, hidden_size=100)

    def data(name: str, steps: int, episode: int = EPISODE) -> None:
        stages.run(name, lambda: stages.save_data(name, transitions(steps, episode)) or {})

    def models(name: str) -> None:
        path = stages.path("checkpoints", f"{name}.pt")
        stages.run(name, lambda: save_checkpoint(path, {"w": world, "u": estimator}) or {})

    data("initial_random", n(10_000))
    models("initial_models")
    data("validation", 100 * (WINDOW + 100), WINDOW + 100)
    names = ["initial_random", "validation"]
    for r in range(3):
        data(f"guided_data_{r}", n(5_000))
        names.append(f"guided_data_{r}")
        if r < 2:
            models(f"guided_refit_{r}")
    data("random_arm", n(15_000))
    names.append("random_arm")
    stages.run("retrain_0", lambda: {"random": {"mse": [1.0] * 10}, "active": {"mse": [1.0] * 10}})
    return names


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scale", type=float, default=1.0, help="fraction of the paper's steps")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parse_args(parser)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp)
        start = time.perf_counter()
        data_stages = build(run_dir, args.scale)
        write_s = time.perf_counter() - start
        stage_names = sorted(p.stem for p in (run_dir / "stages").glob("*.json"))
        files = [p for p in run_dir.rglob("*") if p.is_file()]
        size = sum(p.stat().st_size for p in files)
        verify_ms, load_ms = [], []
        for _ in range(args.repeats):
            stages = Stages(run_dir, seed=0)  # a fresh object hashes again, as a resumed run does
            start = time.perf_counter()
            for name in stage_names:
                stages.verify(name)
            verify_ms.append((time.perf_counter() - start) * 1e3)
            start = time.perf_counter()
            for name in data_stages:
                stages.load_data(name)  # already verified: reads only
            load_ms.append((time.perf_counter() - start) * 1e3)
    verify, load = statistics.median(verify_ms), statistics.median(load_ms)
    print(
        f"run directory: {len(stage_names)} stages, {len(files)} files, {size / 2**20:.1f} MiB "
        f"(written with records in {write_s:.2f} s)"
    )
    print(f"verify every stage (sizes + SHA-256 of every file): {verify:.1f} ms median")
    print(f"read every buffer back (load_data): {load:.1f} ms median")
    print(f"hash throughput: {size / 2**20 / (verify / 1e3):.0f} MiB/s")
    print(f"ratio: {verify / load:.2f}")


if __name__ == "__main__":
    main()
