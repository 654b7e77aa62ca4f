"""TorchRL loggers for the experiments: wandb (offline by default), CSV, or none."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from torchrl.record.loggers import Logger

from torchrl_recon.experiments.recipe import experiment_name
from torchrl_recon.experiments.run_dir import flat_config


def _hparams(cfg: DictConfig) -> dict[str, Any]:
    """Flat config for ``log_hparams``; ``None`` values become the string ``"None"`` (wandb-safe)."""
    return {k: ("None" if v is None else v) for k, v in flat_config(cfg).items()}


def make_logger(cfg: DictConfig, run_dir: str | os.PathLike[str]) -> Logger | None:
    """Build the logger named by ``cfg.logger.backend`` and log the flattened config to it.

    * ``wandb``: :class:`torchrl.record.loggers.WandbLogger` writing under ``<run_dir>/wandb``;
      offline unless ``cfg.logger.mode == "online"`` (offline needs no account and no network;
      push later with ``wandb sync <run_dir>/wandb/offline-run-*``). ``WANDB_SILENT`` is set.
    * ``csv``: :class:`torchrl.record.loggers.CSVLogger`, scalars in
      ``<run_dir>/<exp_name>/scalars/<name>.csv`` and the config in ``.../texts/hparams_*.txt``.
    * ``none``: no logger (returns None).

    The experiment name is ``<experiment>_<env>_seed<seed>``.
    """
    backend = cfg.logger.backend
    run_dir = Path(run_dir)
    name = experiment_name(cfg)
    if backend == "none":
        return None
    if backend == "csv":
        from torchrl.record.loggers import CSVLogger

        logger: Logger = CSVLogger(name, log_dir=str(run_dir))
    elif backend == "wandb":
        os.environ.setdefault("WANDB_SILENT", "true")
        from torchrl.record.loggers import WandbLogger

        logger = WandbLogger(
            exp_name=name,
            offline=cfg.logger.mode != "online",
            save_dir=str(run_dir),
            project=cfg.logger.project,
            group=f"{cfg.experiment}_{cfg.env.name}",
            job_type=cfg.experiment,
            tags=[cfg.experiment, cfg.env.name, f"seed{cfg.seed}"],
            log_env_packages=False,  # versions are in meta.json and in the logged config
        )
    else:
        raise ValueError(f"logger.backend must be 'wandb', 'csv' or 'none', got {backend!r}.")
    logger.log_hparams(_hparams(cfg))
    return logger


def shutdown_logger(logger: Logger | None) -> None:
    """Flush and close ``logger`` (finishes the wandb run)."""
    if logger is not None:
        logger.shutdown()
