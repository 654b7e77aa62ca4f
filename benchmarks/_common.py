"""Shared pieces of the benchmarks: paper-size models, a start context, the IB cost, and the
arithmetic limit (FLOPs counted from the weights over the GEMM rate measured in the same run)."""

from __future__ import annotations

import argparse
import os

import torch
from torch import nn

from torchrl_recon.devices import check_device, describe_device, resolve_device
from torchrl_recon.envs.industrial_benchmark import industrial_benchmark_cost
from torchrl_recon.estimators import ReconstructionUncertainty
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    MPPIPlanner,
    PlannerBase,
    RandomShootingPlanner,
)
from torchrl_recon.runs.allocator import keep_freed_memory
from torchrl_recon.runs.timing import interleaved_median_ms

OBS_DIM, ACTION_DIM, WINDOW = 6, 3, 10  # Industrial Benchmark sizes, paper's T


SETUP_ONLY = "TORCHRL_RECON_SETUP_ONLY"
"""Set (to anything) in a benchmark's environment: it stops with ``setup done`` once its
arguments are accepted and its recipes resolved (:func:`setup_done`; gpu_check's argv test)."""


def setup_done() -> None:
    """Exit 0 here, printing ``setup done``, when :data:`SETUP_ONLY` is set; else nothing."""
    if os.environ.get(SETUP_ONLY):
        print("setup done", flush=True)
        raise SystemExit(0)


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """``--device auto|cpu|cuda|cuda:N`` (auto: CUDA when available)."""
    parser.add_argument(
        "--device", default="cpu", type=check_device, help="auto, cpu, cuda or cuda:N"
    )


def parse_args(parser: argparse.ArgumentParser) -> argparse.Namespace:
    """Parse a benchmark's arguments and set the CPU up as the experiment runner does.

    Adds ``--default-malloc`` (keep glibc's default malloc thresholds), parses, calls
    ``torch.set_num_threads(args.threads)`` and, unless ``--default-malloc``,
    :func:`~torchrl_recon.runs.allocator.keep_freed_memory`, and prints a line that says both.
    """
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="keep glibc's default malloc thresholds instead of the runner's (torchrl_recon.runs.allocator)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    kept = False if args.default_malloc else keep_freed_memory()
    malloc = "keeps freed memory (torchrl_recon.runs.allocator)" if kept else "glibc defaults"
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


# ----------------------------------------------------------------------------------------------
# Arithmetic limits: FLOPs (2 per multiply-add, GEMMs only) over the measured GEMM rate


def gemm_gflops(
    device: torch.device | str,
    shape: tuple[int, int, int, int] = (1, 1024, 1024, 1024),
    repeats: int = 5,
) -> float:
    """Measured GFLOP/s of one float32 ``baddbmm`` ``[b, m, k] @ [b, k, n]`` on ``device``.

    The default shape is one large matrix product (the device's GEMM rate); a benchmark may
    pass the shape of its own hot product instead. Timed with
    :func:`~torchrl_recon.runs.timing.interleaved_median_ms` (synchronised on CUDA).

    Examples:
        >>> gemm_gflops("cpu", (1, 64, 64, 64), repeats=1) > 0
        True
    """
    b, m, k, n = shape
    x, y, c = (torch.rand(*s, device=device) for s in ((b, m, k), (b, k, n), (b, m, n)))
    calls = {"gemm": lambda: torch.baddbmm(c, x, y)}
    ms = interleaved_median_ms(calls, repeats, device=device)["gemm"]
    return 2 * b * m * k * n / (ms * 1e-3) / 1e9


def gemm_line(gflops: float, shape: tuple[int, int, int, int] = (1, 1024, 1024, 1024)) -> str:
    """The line that prints the GEMM rate above a benchmark's table."""
    b, m, k, n = shape
    product = f"{m}x{k} @ {k}x{n}" + (f", {b} batched" if b > 1 else "")
    return f"GEMM rate (float32 {product}, measured now): {gflops:.1f} GFLOP/s"


def matmul_flops(module: nn.Module) -> int:
    """FLOPs of one input row through every weight matrix of ``module`` once (2 per weight).

    For :class:`LSTMWorldModel` that is one imagined step (LSTM gates, dense, head); for
    :class:`ReconstructionUncertainty` the score of one window (encoder and decoder).

    Examples:
        >>> matmul_flops(nn.Linear(3, 4))
        24
    """
    return 2 * sum(p.numel() for p in module.parameters() if p.dim() == 2)


def lstm_step_flops(world: LSTMWorldModel) -> int:
    """FLOPs of one LSTM step of ``world`` alone (a teacher-forced warm-up step)."""
    return 2 * (world.lstm.weight_ih_l0.numel() + world.lstm.weight_hh_l0.numel())


def plan_flops(planner: PlannerBase, envs: int = 1) -> int:
    """FLOPs of one ``plan`` call over ``envs`` contexts: candidate rows × H × a row-step.

    A row-step is a world-model step plus, with an estimator, its score of the window ending
    there (:func:`matmul_flops`). CEM evaluates K rows per iteration, random shooting K once,
    iCEM its shrinking populations, MPPI K per iteration and its final mean once,
    the gradient planner its restarts at each of ``steps`` forward + backward passes (a
    backward ≈ 2 forwards) and once more forward at the end.
    """
    model = planner.model
    step = matmul_flops(model.world_model)
    if model.uncertainty is not None:
        step += matmul_flops(model.uncertainty)
    if isinstance(planner, ICEMPlanner):  # a CEMPlanner whose population shrinks
        rows = sum(planner.population_sizes())
    elif isinstance(planner, CEMPlanner):
        rows = planner.num_candidates * planner.iterations
    elif isinstance(planner, MPPIPlanner):  # and the final mean, scored once
        rows = planner.num_candidates * planner.iterations + 1
    elif isinstance(planner, RandomShootingPlanner):
        rows = planner.num_candidates
    elif isinstance(planner, GradientPlanner):
        rows = planner.restarts * (3 * planner.steps + 1)
    else:
        raise TypeError(f"no FLOP count for {type(planner).__name__}")
    return envs * rows * planner.horizon * step


def fit_step_flops(world: LSTMWorldModel, sequences: int, slice_len: int) -> int:
    """FLOPs of one multi-step fit step of ``world`` on ``sequences`` slices of ``slice_len``.

    The forward is a teacher-forced warm-up over the window (LSTM only) and ``slice_len -
    window`` imagined steps; forward + backward ≈ 3 × forward.
    """
    imagined = slice_len - world.window
    forward = world.window * lstm_step_flops(world) + imagined * matmul_flops(world)
    return 3 * sequences * forward


def limit_ms(flops: float, gflops: float) -> float:
    """Time in ms that ``flops`` take at ``gflops`` GFLOP/s."""
    return flops / (gflops * 1e9) * 1e3


def limit_text(measured_ms: float, limit: float) -> str:
    """``N.Nx its arithmetic limit``: how far a measured time is from its limit (both in ms).

    Examples:
        >>> limit_text(40.0, 11.0)
        '3.6x its arithmetic limit'
    """
    return f"{measured_ms / limit:.1f}x its arithmetic limit"
