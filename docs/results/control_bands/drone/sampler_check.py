"""Refit a control run's autoencoder on its own random data, optionally with every trajectory
cut into pieces of about ``--chunk`` steps or with step-uniform windows (``--window-sampling
step``), and print the re-planning threshold it gives.

The check behind docs/reproduction.md ("Why: the fit's sampler weighs trajectories, not
steps"): TorchRL's ``SliceSampler`` draws a trajectory uniformly, then a window inside it, so
cutting long trajectories into equal pieces makes the windows about uniform over steps.
Needs a run directory that has finished its ``models`` stage, e.g.

    torchrl-recon control recipes/all_envs/control_bands.yaml control_env=drone seed=1 \
        stop_after=models output_dir=runs/drone_seed1
    python docs/results/control_bands/drone/sampler_check.py runs/drone_seed1 --chunk 100
    python docs/results/control_bands/drone/sampler_check.py runs/drone_seed1 --window-sampling step
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from omegaconf import OmegaConf

from torchrl_recon.experiments import control
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.fit_stages import fit_module
from torchrl_recon.experiments.recipe_models import build_models
from torchrl_recon.experiments.runner import validate
from torchrl_recon.planners.beta import window_uncertainty


def cut_trajectories(ids: torch.Tensor, chunk: int) -> torch.Tensor:
    """New trajectory ids: every trajectory split into ``max(1, len // chunk)`` equal pieces."""
    new, next_id = torch.empty_like(ids), 0
    for traj in torch.unique_consecutive(ids):
        rows = (ids == traj).nonzero().squeeze(-1)
        for piece in torch.tensor_split(rows, max(1, rows.numel() // chunk)):
            new[piece] = next_id
            next_id += 1
    return new


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument(
        "--chunk", type=int, default=0, help="piece length; 0 keeps the trajectories"
    )
    parser.add_argument("--fit-seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument(
        "--window-sampling",
        choices=["trajectory", "step"],
        default=None,
        help="the fit's training.window_sampling (default: the run's)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    raw = OmegaConf.load(args.run_dir / "config.yaml")
    raw.stop_after = None
    if args.window_sampling is not None:
        raw.training.window_sampling = args.window_sampling
    ctx = RunContext(validate(raw), args.run_dir, None)
    data = ctx.stages.load_data("random_data")
    train = data.clone()
    if args.chunk > 0:
        train["collector", "traj_ids"] = cut_trajectories(data["collector", "traj_ids"], args.chunk)
    obs_dim, action_dim = data["observation"].shape[-1], data["action"].shape[-1]
    for seed in args.fit_seeds:
        torch.manual_seed(seed)  # the initial weights
        _, estimator = build_models(ctx.cfg, obs_dim, action_dim, ctx.device)
        val = fit_module(ctx, estimator, train, seed=seed, prefix="sampler_check/")
        length = max(ctx.cfg.models.window, ctx.cfg.training.slice_len)  # as control.run
        u = window_uncertainty(data, estimator, sequence_length=length)
        threshold = control.replan_threshold(ctx.cfg, u)
        sampling = ctx.cfg.training.window_sampling
        print(
            f"chunk {args.chunk} sampling {sampling} fit seed {seed}: val loss {val:.4f}, "
            f"threshold {threshold:.4f}"
        )


if __name__ == "__main__":
    main()
