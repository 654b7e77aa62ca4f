"""One run context: what every stage and builder of an experiment is handed."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch
from omegaconf import DictConfig
from torchrl.record.loggers import Logger

from torchrl_recon.devices import resolve_device
from torchrl_recon.experiments.stages import Stages, stage_seed


class RecipeLoader(NamedTuple):
    """How a kind that runs other recipes finds and loads them (the recipe module's functions)."""

    resolve: Callable[[str], Path]
    load: Callable[[Path, Sequence[str]], DictConfig]


@dataclass
class RunContext:
    """The run an experiment's stages work for, built once by the runner: the validated recipe
    ``cfg``, the ``run_dir``, a TorchRL ``logger`` (or None), ``run_child`` (runs another
    experiment's config, e.g. calibrate's outcomes; returns its headline numbers, None when it
    stopped), the ``recipes`` a child run is made from; from ``cfg``, its resumable ``stages``
    (stopping after ``cfg.stop_after``) and the ``device`` of networks, planning and fitting.

    Examples:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> from torchrl_recon.experiments.config import ExploreConfig
        >>> cfg = OmegaConf.structured(ExploreConfig(output_dir="out", seed=3))
        >>> ctx = RunContext(cfg, Path(tempfile.mkdtemp()))
        >>> ctx.seed, ctx.device.type
        (3, 'cpu')
    """

    cfg: DictConfig
    run_dir: Path
    logger: Logger | None = None
    run_child: Callable[[DictConfig], Mapping[str, Any] | None] | None = None
    recipes: RecipeLoader | None = None
    stages: Stages = field(init=False)
    device: torch.device = field(init=False)

    def __post_init__(self) -> None:
        cfg, self.run_dir = self.cfg, Path(self.run_dir)
        self.stages = Stages(
            self.run_dir, seed=cfg.seed, stop_after=cfg.stop_after, logger=self.logger
        )
        self.device = resolve_device(cfg.device)

    @property
    def seed(self) -> int:
        """The run's seed (``cfg.seed``)."""
        return int(self.cfg.seed)

    def results_header(self) -> dict[str, Any]:
        """The keys every results dict opens with: ``experiment``, ``env``, ``seed``."""
        return {"experiment": self.cfg.experiment, "env": self.cfg.env.name, "seed": self.cfg.seed}

    def stage_seed(self, name: str) -> int:
        """The seed of stage ``name`` of this run (see :func:`stage_seed`)."""
        return stage_seed(self.cfg.seed, name)
