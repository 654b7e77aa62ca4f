"""Planning time per call: TorchRL's CEMPlanner vs ours (CEM, with and without u; gradient; shooting).

Run: python benchmarks/planner_speed.py [--candidates 1000] [--horizons 30 200] [--threads N]
All planners use the same paper-size world model (state 6, action 3, LSTM 32, dense 32) and
autoencoder (90 → 100 → 90, T = 10) and the Industrial Benchmark torch cost. The baseline is
TorchRL's own ``CEMPlanner`` on a ``ModelBasedEnvBase`` whose world model is TorchRL's
``LSTMModule`` (sharing our LSTM weights), no uncertainty term. The last two lines are the
speed-ups at the first horizon.
"""

from __future__ import annotations

import argparse

import torch
from _common import COST, context, median_seconds, paper_models
from torchrl.modules import CEMPlanner as TorchRLCEMPlanner

from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
)
from torchrl_recon.planners.model_env import WorldModelPlanningEnv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--elites", type=int, default=100)
    parser.add_argument("--horizons", type=int, nargs="+", default=[30, 200])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    world, estimator = paper_models()
    ctx = context()
    plain = PlanningModel(world, COST)
    with_u = PlanningModel(world, COST, uncertainty=estimator)
    env = WorldModelPlanningEnv(world, COST)
    start = env.initial_state(*ctx)
    cem = dict(num_candidates=args.candidates, iterations=args.iterations, num_elites=args.elites)
    print(
        f"K={args.candidates}, {args.iterations} iterations, top-k {args.elites}, threads={args.threads}, "
        f"median of {args.repeats} calls (baseline at H>30: of {max(1, args.repeats // 2)})"
    )
    first = {}
    for horizon in args.horizons:
        baseline = TorchRLCEMPlanner(
            env,
            planning_horizon=horizon,
            optim_steps=args.iterations,
            num_candidates=args.candidates,
            top_k=args.elites,
        )
        ours = {
            "ours CEM (no u)": CEMPlanner(plain, Objective(), horizon=horizon, **cem),
            "ours CEM (with u, beta=0.1)": CEMPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, **cem
            ),
            "ours random shooting (with u)": RandomShootingPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, num_candidates=args.candidates
            ),
            "ours gradient (with u, 16 restarts x 20 steps)": GradientPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, restarts=16, steps=20
            ),
        }
        repeats = args.repeats if horizon <= 30 else max(1, args.repeats // 2)
        with torch.no_grad():
            times = {
                "TorchRL CEMPlanner (no u)": median_seconds(
                    lambda b=baseline: b(start.clone()), repeats
                )
            }
        for name, planner in ours.items():
            times[name] = median_seconds(lambda planner=planner: planner.plan(*ctx), repeats)
        print(f"H={horizon}")
        for name, seconds in times.items():
            print(f"  {name:<48}{seconds * 1e3:9.1f} ms")
        first = first or times
    base = first["TorchRL CEMPlanner (no u)"]
    print(
        f"speed-up vs TorchRL CEMPlanner (no uncertainty): {base / first['ours CEM (no u)']:.1f}x"
    )
    print(
        f"speed-up vs TorchRL CEMPlanner (ours with uncertainty): {base / first['ours CEM (with u, beta=0.1)']:.1f}x"
    )


if __name__ == "__main__":
    main()
