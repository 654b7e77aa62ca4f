"""Shared pieces of the benchmarks: paper-size models, a start context and the IB cost."""

from __future__ import annotations

import argparse

import torch

from torchrl_recon.allocator import keep_freed_memory
from torchrl_recon.devices import check_device, describe_device, resolve_device
from torchrl_recon.envs.industrial_benchmark import industrial_benchmark_cost
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty

OBS_DIM, ACTION_DIM, WINDOW = 6, 3, 10  # Industrial Benchmark sizes, paper's T


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """``--device auto|cpu|cuda|cuda:N`` (auto: CUDA when available)."""
    parser.add_argument(
        "--device", default="cpu", type=check_device, help="auto, cpu, cuda or cuda:N"
    )


def parse_args(parser: argparse.ArgumentParser) -> argparse.Namespace:
    """Parse a benchmark's arguments and set the CPU up as the experiment runner does.

    Adds ``--default-malloc`` (keep glibc's default malloc thresholds), parses, calls
    ``torch.set_num_threads(args.threads)`` and, unless ``--default-malloc``,
    :func:`~torchrl_recon.allocator.keep_freed_memory`, and prints a line that says both.
    """
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="keep glibc's default malloc thresholds instead of the runner's (torchrl_recon.allocator)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    kept = False if args.default_malloc else keep_freed_memory()
    malloc = "keeps freed memory (torchrl_recon.allocator)" if kept else "glibc defaults"
    print(f"threads={args.threads}, malloc: {malloc}")
    return args


def parse_device_args(parser: argparse.ArgumentParser) -> tuple[argparse.Namespace, torch.device]:
    """Add ``--device``, parse as :func:`parse_args` does, and print and return the device.

    The device line reads ``device: cpu (<processor>)`` (or the GPU's name).
    """
    add_device_argument(parser)
    args = parse_args(parser)
    device = resolve_device(args.device)
    print(f"device: {describe(device)}")
    return args, device


def describe(device: torch.device) -> str:
    """The device's name as benchmark output reports it."""
    info = describe_device(device)
    return f"{info['device']} ({info['name']})"


def paper_models(
    seed: int = 0, device: torch.device | str = "cpu"
) -> tuple[LSTMWorldModel, ReconstructionUncertainty]:
    """World model (LSTM 32, dense 32) and autoencoder (90 → 100 → 90) of the paper's sizes,
    IB dims, on ``device``."""
    torch.manual_seed(seed)
    world = LSTMWorldModel(OBS_DIM, ACTION_DIM, hidden_size=32, dense_size=32, window=WINDOW)
    estimator = ReconstructionUncertainty(OBS_DIM, ACTION_DIM, window=WINDOW, hidden_size=100)
    obs, act = torch.rand(500, OBS_DIM) * 100, torch.rand(500, ACTION_DIM) * 2 - 1
    world.fit_normalization(obs, act, obs + torch.randn(500, OBS_DIM))
    estimator.fit_normalization(obs, act)
    for p in (*world.parameters(), *estimator.parameters()):
        p.requires_grad_(False)
    return world.to(device), estimator.to(device)


def context(
    seed: int = 0, device: torch.device | str = "cpu"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A start context (window of observations and actions, current observation) on ``device``."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.rand(WINDOW, OBS_DIM, generator=g) * 100
    act = torch.rand(WINDOW, ACTION_DIM, generator=g) * 2 - 1
    now = torch.rand(OBS_DIM, generator=g) * 100
    return obs.to(device), act.to(device), now.to(device)


COST = industrial_benchmark_cost
