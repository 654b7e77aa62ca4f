"""Launch the online agent from TorchRL's config system, as TorchRL's ``*_trainer/train.py`` do.

    python examples/config_trainer/train.py [overrides]

It computes on one CPU thread (``torch.set_num_threads(1)``): beside another process, more
threads than free cores make it crawl; the override ``threads=N`` gives it N.
The last line is ``return <mean return of the last half of the MPC episodes> random <the
random episodes' mean>``.
"""

from __future__ import annotations

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

import torchrl_recon.trainers.configs  # noqa: F401  (stores the library's parts beside TorchRL's)


@hydra.main(config_path=".", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(cfg.threads)
    trainer = instantiate(cfg.trainer)
    trainer.train()
    records = trainer.records
    random = [r for rec in records if rec.policy == "random" for r in rec.episode_returns]
    planned = [r for rec in records if rec.policy == "mpc" for r in rec.episode_returns]
    late = planned[len(planned) // 2 :] or planned
    print(
        f"return {sum(late) / max(len(late), 1):.1f} random {sum(random) / max(len(random), 1):.1f}"
    )


if __name__ == "__main__":
    main()
