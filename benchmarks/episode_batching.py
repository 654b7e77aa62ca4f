"""Planning 10 envs' episodes in one planner call vs 10 calls of one env each.

Run: python benchmarks/episode_batching.py [--envs 10] [--horizon 200] [--steps 50]
     [--candidates 1000] [--repeats 3] [--threads 1] [--device cpu]

Paper sizes (recipes/industrial_benchmark/control.yaml): world model LSTM 32 + dense 32,
autoencoder 90 → 100 → 90 (T = 10) whose reconstruction uncertainty u is in the objective
(β = 0.1), H = 200; the gradient planner with 16 restarts × 50 Adam steps, CEM with K = 1000
candidates, 5 iterations, 100 elites. Each env has its own context. "one call" plans all envs
as one ``[B, ...]`` batch; "separate calls" plans them one after another (``[1, ...]`` each).
Both are timed round-robin (``torchrl_recon.runs.timing.interleaved_median_ms``), so a change of
machine load hits both alike.

For each planner the script also prints the arithmetic limit of the one-call plan: its
multiply-add FLOPs (rollout, autoencoder, and for the gradient planner their backward) over
the measured rate of a large matrix product on this device and thread count, and how far the
measured time is from it (``N.Nx its arithmetic limit``; ``_common.plan_flops``). It ends with the two lines
``speed-up of 10 episodes in one call (gradient): X.Xx`` and
``speed-up of 10 episodes in one call (CEM, K=1000): X.Xx``.
"""

from __future__ import annotations

import argparse
from functools import partial

import torch
from _common import (
    COST,
    add_device_argument,
    context,
    describe,
    gemm_gflops,
    gemm_line,
    limit_ms,
    limit_text,
    paper_models,
    parse_args,
    plan_flops,
    setup_done,
)

from torchrl_recon.devices import resolve_device
from torchrl_recon.planners import CEMPlanner, GradientPlanner, Objective, PlanningModel
from torchrl_recon.runs.timing import interleaved_median_ms


def batched_contexts(envs: int, device: torch.device) -> tuple[torch.Tensor, ...]:
    """One different start context per env, stacked ``[B, T, N]``, ``[B, T, M]``, ``[B, N]``."""
    parts = [context(seed=i, device=device) for i in range(envs)]
    return tuple(torch.stack(x) for x in zip(*parts, strict=True))


def separate_calls(planner, ctx: tuple[torch.Tensor, ...]) -> None:
    """Plan each env on its own: ``B`` calls with a batch of one."""
    for i in range(ctx[0].shape[0]):
        planner.plan(*(x[i : i + 1] for x in ctx))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--envs", type=int, default=10)
    parser.add_argument("--horizon", type=int, default=200)
    parser.add_argument("--restarts", type=int, default=16)
    parser.add_argument("--steps", type=int, default=50, help="Adam steps of the gradient planner")
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--elites", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--planners", nargs="+", choices=["gradient", "cem"], default=["gradient", "cem"]
    )
    add_device_argument(parser)
    args = parse_args(parser)
    setup_done()
    device = resolve_device(args.device)
    print(f"device: {describe(device)}, threads={args.threads}")
    world, estimator = paper_models(device=device)
    model = PlanningModel(world, COST, uncertainty=estimator)
    objective = Objective(beta=0.1)
    ctx = batched_contexts(args.envs, device)
    cem_name = f"CEM, K={args.candidates}"
    planners = {
        "gradient": GradientPlanner(
            model, objective, horizon=args.horizon, restarts=args.restarts, steps=args.steps
        ),
        cem_name: CEMPlanner(
            model,
            objective,
            horizon=args.horizon,
            num_candidates=args.candidates,
            iterations=args.iterations,
            num_elites=min(args.elites, args.candidates),
        ),
    }
    planners = {
        name: planner
        for name, planner in planners.items()
        if ("cem" if name == cem_name else name) in args.planners
    }
    rate = gemm_gflops(device)
    print(gemm_line(rate))
    speed_ups = {}
    for name, planner in planners.items():
        times = interleaved_median_ms(
            {
                "one call": partial(planner.plan, *ctx),
                "separate calls": partial(separate_calls, planner, ctx),
            },
            args.repeats,
            device=device,
        )
        flops = plan_flops(planner, envs=args.envs)
        limit = limit_ms(flops, rate)
        one, separate = times["one call"], times["separate calls"]
        print(
            f"{name}: {args.envs} envs, H={args.horizon}, median of {args.repeats} round-robin "
            f"rounds: one call {one:.0f} ms, {args.envs} separate calls {separate:.0f} ms; "
            f"arithmetic limit {limit:.0f} ms ({flops / 1e9:.1f} GFLOP), one call "
            f"{limit_text(one, limit)}"
        )
        speed_ups[name] = separate / one
    for name, ratio in speed_ups.items():
        print(f"speed-up of {args.envs} episodes in one call ({name}): {ratio:.1f}x")


if __name__ == "__main__":
    main()
