"""A control setting's episodes played one env at a time vs as one batch of envs.

The episodes of one setting of ``recipes/<env>/control.yaml`` (paper planner sizes) run with
``num_envs=1`` (one rollout per episode) and with ``num_envs=B`` (one rollout of B envs, one
planning call per step for the envs whose re-planning trigger fired), interleaved, on the same
fitted networks (fitted briefly: the networks' quality does not change the planning cost).
Re-planning is every ``--replan-every`` steps so both paths plan equally often.

Run: python benchmarks/control_batching.py [--env drone] [--settings baseline gradient_beta_0.1]
Its last lines are ``speed-up of <B> episodes as one batch (<setting>): X.Xx``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from _common import parse_args, setup_done

from torchrl_recon.experiments import control, explore
from torchrl_recon.experiments.batching import batches
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.recipe import load_recipe
from torchrl_recon.experiments.recipe_planning import build_planner, planning_model

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--env", default="drone")
    parser.add_argument("--settings", nargs="+", default=["baseline", "gradient_beta_0.1"])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--steps", type=int, default=50, help="steps per episode")
    parser.add_argument("--replan-every", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    args = parse_args(parser)
    overrides = [
        f"env.episode_steps={args.steps}",
        f"episodes={args.episodes}",
        "replan.mode=every_n",
        f"replan.every={args.replan_every}",
        "random_episodes=4",
        "random_episode_steps=250",
        "training.world_model.steps=50",
        "training.uncertainty.steps=50",
        f"device={args.device}",
        "progress=false",
        "logger.backend=none",
    ]
    cfg = load_recipe(RECIPES / args.env / "control.yaml", overrides)
    setup_done()
    with tempfile.TemporaryDirectory() as run_dir:
        ctx = RunContext(cfg, Path(run_dir))
        data = control.random_data_stage(ctx, "random_data", frames=4 * 250, episode_steps=250)
        world, estimator, _ = explore.models_stage(ctx, data, "models")
        model = planning_model(cfg, world, estimator)
        controller = control.Controller(model, 1.0, 1.0, control.state_scale(data))
        print(
            f"env={args.env}, {args.episodes} episodes x {args.steps} steps, re-plan every "
            f"{args.replan_every}, threads={args.threads}, device={ctx.device}, load average "
            f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs"
        )
        results = {}
        for name in args.settings:
            setting = next(s for s in cfg.settings if s.name == name)
            objective, _ = control.setting_objective(setting, 1.0)
            planner = build_planner(setting.planner, model, objective)
            times: dict[int, list[float]] = {1: [], args.episodes: []}
            for _ in range(args.repeats):
                for batch_size in times:
                    start = time.perf_counter()
                    for batch in batches(args.episodes, batch_size):
                        control.episode_batch(ctx, setting, planner, controller, batch)
                    times[batch_size].append(time.perf_counter() - start)
            one, batched = (min(times[b]) for b in times)
            results[name] = one / batched
            p = setting.planner
            print(
                f"{name} ({p.kind}, H={p.kwargs.horizon}): one env at a time {one:7.1f} s, "
                f"one batch of {args.episodes} {batched:7.1f} s"
            )
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    for name, ratio in results.items():
        print(f"speed-up of {args.episodes} episodes as one batch ({name}): {ratio:.1f}x")


if __name__ == "__main__":
    main()
