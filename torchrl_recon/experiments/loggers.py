"""The run's TorchRL logger (``torchrl.record.loggers.get_logger``): wandb, offline by default;
CSV; or none."""

from __future__ import annotations

import os

from omegaconf import DictConfig
from torchrl.record.loggers import Logger, get_logger

from torchrl_recon.experiments.recipe import experiment_name
from torchrl_recon.experiments.run_dir import flat_config


def make_logger(cfg: DictConfig, run_dir: str | os.PathLike[str]) -> Logger | None:
    """TorchRL's logger of ``cfg.logger.backend``, with the flattened config logged to it
    (``None`` values as the string ``"None"``, which wandb takes); ``none``: no logger.

    * ``wandb``: :class:`~torchrl.record.loggers.WandbLogger` writing under ``<run_dir>/wandb``;
      offline unless ``cfg.logger.mode == "online"`` (offline needs no account and no network;
      push later with ``wandb sync <run_dir>/wandb/offline-run-*``). ``WANDB_SILENT`` is set.
    * ``csv``: :class:`~torchrl.record.loggers.CSVLogger`, scalars in
      ``<run_dir>/<exp_name>/scalars/<name>.csv`` and the config in ``.../texts/hparams_*.txt``.

    The experiment name is ``<experiment>_<env>_seed<seed>``.
    """
    backend, kind, env = cfg.logger.backend, cfg.experiment, cfg.env.name
    if backend == "wandb":
        os.environ.setdefault("WANDB_SILENT", "true")
    wandb_kwargs = dict(
        offline=cfg.logger.mode != "online",
        project=cfg.logger.project,
        group=f"{kind}_{env}",
        job_type=kind,
        tags=[kind, env, f"seed{cfg.seed}"],
        log_env_packages=False,  # versions are in meta.json and in the logged config
    )
    backend = "" if backend == "none" else backend
    logger = get_logger(backend, str(run_dir), experiment_name(cfg), wandb_kwargs=wandb_kwargs)
    if logger is not None:
        logger.log_hparams({k: "None" if v is None else v for k, v in flat_config(cfg).items()})
    return logger


def shutdown_logger(logger: Logger | None) -> None:
    """Flush and close ``logger`` (finishes the wandb run)."""
    if logger is not None:
        logger.shutdown()
