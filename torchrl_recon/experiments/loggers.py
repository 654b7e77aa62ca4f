"""The run's TorchRL logger (``torchrl.record.loggers.get_logger``): wandb, offline by default;
CSV; or none."""

from __future__ import annotations

import os

from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import Logger, get_logger

from torchrl_recon.experiments.run_dir import flatten


def make_logger(cfg: DictConfig, run_dir: str | os.PathLike[str]) -> Logger | None:
    """TorchRL's logger of ``cfg.logger.backend`` (``none``: None) under ``run_dir``, named
    ``<experiment>_<env>_seed<seed>``, the flattened config its hparams (``None`` as "None", for
    wandb); wandb runs offline unless ``cfg.logger.mode`` is "online"."""
    kind, env, backend = cfg.experiment, cfg.env.name, cfg.logger.backend
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
    name, backend = f"{kind}_{env}_seed{cfg.seed}", "" if backend == "none" else backend
    logger = get_logger(backend, str(run_dir), name, wandb_kwargs=wandb_kwargs)
    if logger is not None:
        hparams = flatten(OmegaConf.to_container(cfg, resolve=True))
        logger.log_hparams({k: "None" if v is None else v for k, v in hparams.items()})
    return logger
