"""Command line entry point: ``torchrl-recon <command> ...``."""

from __future__ import annotations

import argparse
import sys

import torch


def _demo(args: argparse.Namespace) -> int:
    from torchrl_recon.collectors import collect_random
    from torchrl_recon.envs import ENVS, make_env

    print(f"{'env':<22}{'steps':>7}{'episodes':>10}{'mean reward':>14}  obs dim")
    for name in ENVS:
        kwargs = {"self_collision": False} if name == "minitaur" else {}
        env = make_env(name, seed=args.seed, max_episode_steps=100, **kwargs)
        data = collect_random(env, frames=args.steps, seed=args.seed)
        env.close()
        episodes = int(data["collector", "traj_ids"].unique().numel())
        reward = float(data["next", "reward"].mean())
        print(
            f"{name:<22}{data.numel():>7}{episodes:>10}{reward:>14.3f}  {data['observation'].shape[-1]}"
        )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchrl-recon", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo", help="collect random data in each environment and print a summary"
    )
    demo.add_argument("--steps", type=int, default=200)
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    args = build_parser().parse_args(argv)
    torch.set_num_threads(min(2, torch.get_num_threads()))
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
