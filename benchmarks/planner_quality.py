"""Plan quality at equal budget: the best cost each planner finds on the shipped envs' models.

Run: python benchmarks/planner_quality.py [--envs industrial_benchmark drone minitaur]
     [--frames 3000] [--fit-steps 300] [--contexts 16] [--candidates 500] [--seeds 3]
For each env: random data (``--frames`` steps in episodes of 200), a world model of the paper's
sizes fitted on it (``--fit-steps``, multi-step loss), then ``--contexts`` real contexts from
held-out episodes planned as one batch by random shooting, CEM, MPPI and iCEM at the same
budget (K candidates × iterations × H steps; shooting gets K × iterations candidates once). It
prints each planner's mean predicted Σcost of the plan it returns (lower is better; the
model's cost, not the env's) and, for MPPI and iCEM, the mean per-context difference from CEM
with its standard error over contexts × ``--seeds`` planner seeds.
"""

from __future__ import annotations

import argparse
import math

import torch
from _common import parse_device_args, setup_done

from torchrl_recon.collectors import collect_random
from torchrl_recon.data import cut_sequences, make_sequence_buffer, split_by_trajectory
from torchrl_recon.envs import get_entry, make_env
from torchrl_recon.fitting import fit_world_model
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import (
    CEMPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
)


def fitted_model(name: str, args, device: torch.device) -> tuple[PlanningModel, torch.Tensor]:
    """The env's planning model fitted on random data, and held-out windows ``[C, W + 1]``."""
    env = make_env(name, seed=0, max_episode_steps=200)
    data = collect_random(env, frames=args.frames, seed=0)
    train, val = split_by_trajectory(data, 0.2, seed=0)
    rb = make_sequence_buffer(len(train), slice_len=args.window + 10, num_slices=16)
    rb.extend(train)
    n, m = data["observation"].shape[-1], data["action"].shape[-1]
    torch.manual_seed(0)
    world = LSTMWorldModel(n, m, window=args.window)
    fit_world_model(world, rb, steps=args.fit_steps, eval_every=args.fit_steps, progress=False)
    model = PlanningModel.from_env(world.to(device), get_entry(name).cost_fn(), env)
    env.close()
    windows = cut_sequences(val, args.window + 1)[: args.contexts]
    return model, windows.to(device)


def planners(model: PlanningModel, args) -> dict:
    """The four planners at one budget: K candidates × iterations evaluations of H steps."""
    budget = dict(horizon=args.horizon, num_candidates=args.candidates, iterations=args.iterations)
    elites = max(2, args.candidates // 10)
    return {
        "random shooting": RandomShootingPlanner(
            model,
            Objective(),
            horizon=args.horizon,
            num_candidates=args.candidates * args.iterations,
        ),
        "CEM": CEMPlanner(model, Objective(), num_elites=elites, **budget),
        "MPPI": MPPIPlanner(model, Objective(), temperature=args.temperature, **budget),
        "iCEM": ICEMPlanner(model, Objective(), num_elites=elites, population_decay=1.0, **budget),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--envs", nargs="+", default=["industrial_benchmark", "drone", "minitaur"])
    parser.add_argument("--frames", type=int, default=3000)
    parser.add_argument("--fit-steps", type=int, default=300)
    parser.add_argument("--window", type=int, default=10)
    parser.add_argument("--contexts", type=int, default=16)
    parser.add_argument("--candidates", type=int, default=500)
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--horizon", type=int, default=30)
    parser.add_argument("--temperature", type=float, default=0.1)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args, device = parse_device_args(parser)
    setup_done()
    print(
        f"budget: K={args.candidates} x {args.iterations} iterations x H={args.horizon} "
        f"(iCEM without population decay, so the same rows); {args.contexts} contexts x "
        f"{args.seeds} seeds; MPPI temperature {args.temperature}"
    )
    for name in args.envs:
        model, windows = fitted_model(name, args, device)
        w = args.window
        ctx = windows["observation"][:, :w], windows["action"][:, :w], windows["observation"][:, w]
        costs: dict[str, list[torch.Tensor]] = {}
        for seed in range(args.seeds):
            for label, planner in planners(model, args).items():
                generator = torch.Generator(device=device).manual_seed(seed)
                with torch.no_grad():
                    plan = planner.plan(*ctx, generator=generator)
                costs.setdefault(label, []).append(plan.cost.sum(-1).double().cpu())
        stacked = {k: torch.cat(v) for k, v in costs.items()}
        print(f"{name} ({len(windows)} contexts, model fitted {args.fit_steps} steps):")
        for label, values in stacked.items():
            row = f"  {label:<16} mean predicted cost {values.mean():10.4f}"
            if label in ("MPPI", "iCEM"):
                diff = values - stacked["CEM"]
                se = diff.std() / math.sqrt(diff.numel())
                row += f"   vs CEM {diff.mean():+9.4f} ± {se:.4f}"
            print(row)


if __name__ == "__main__":
    main()
