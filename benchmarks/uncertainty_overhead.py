"""Cost of adding u to an imagined rollout: world-model-only vs world model + u for every window.

Run: python benchmarks/uncertainty_overhead.py [--candidates 1000] [--horizons 30 200] [--repeats 7]
Prints each time, then the ratio at the first horizon last, as ``ratio: X``.
"""

from __future__ import annotations

import argparse

import torch
from _common import (
    ACTION_DIM,
    COST,
    context,
    paper_models,
    parse_device_args,
    setup_done,
)

from torchrl_recon.planners import PlanningModel
from torchrl_recon.runs.timing import interleaved_median_ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--horizons", type=int, nargs="+", default=[30, 200])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args, device = parse_device_args(parser)
    setup_done()
    world, estimator = paper_models(device=device)
    rollout_only = PlanningModel(world, COST)
    with_u = PlanningModel(world, COST, uncertainty=estimator)
    ctx = context(device=device)
    print(
        f"K={args.candidates}, threads={args.threads}, median of {args.repeats} round-robin calls"
    )
    ratios = []
    for horizon in args.horizons:
        actions = torch.rand(args.candidates, horizon, ACTION_DIM, device=device) * 2 - 1
        with torch.inference_mode():
            ms = interleaved_median_ms(
                {
                    "rollout": lambda a=actions: rollout_only(*ctx, a),
                    "with_u": lambda a=actions: with_u(*ctx, a),
                },
                args.repeats,
                device=device,
            )
        ratios.append(ms["with_u"] / ms["rollout"])
        print(
            f"H={horizon:4d}  rollout {ms['rollout']:8.1f} ms   rollout + u {ms['with_u']:8.1f} ms   ratio {ratios[-1]:.2f}"
        )
    print(f"ratio: {ratios[0]:.2f}")


if __name__ == "__main__":
    main()
