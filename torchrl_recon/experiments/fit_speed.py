"""How fast a recipe's fits run, read from the recipe in one place: each fit's speed keywords
(``compile``: ``training.<fit>.compile``; ``cuda_graph``: ``fit_cuda_graph``), their recipe
checks and the check of the machine's device. The fits take plain keywords
(:func:`~torchrl_recon.fitting.fit_population`); no other module of the experiments reads these
keys from a recipe."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from omegaconf import DictConfig, OmegaConf

if TYPE_CHECKING:
    from torchrl_recon.experiments.recipe_checks import RecipeErrors

FITS = ("world_model", "uncertainty")
"""A recipe's fit blocks, ``training.<fit>``."""


def _graph(cfg: DictConfig) -> bool:
    """The recipe's ``fit_cuda_graph`` (a run made before the key: off)."""
    return bool(cfg.get("fit_cuda_graph", False))


def fit_speed(
    cfg: DictConfig, fit: str = "world_model", *, population: bool = False
) -> dict[str, bool]:
    """The speed keywords of the recipe's fit ``fit`` (``world_model``, ``uncertainty``, or
    ``reward``, a learned reward's fit, which takes the world model's block uncompiled):
    ``compile`` from ``training.<fit>.compile`` and, for a ``population`` fit (world-model
    members, :func:`~torchrl_recon.fitting.fit_population`), ``cuda_graph`` from
    ``fit_cuda_graph``. A key that a run made before it lacks is off.

    Examples:
        >>> cfg = OmegaConf.create({"training": {"world_model": {"compile": True}}})
        >>> fit_speed(cfg), fit_speed(cfg, "uncertainty"), fit_speed(cfg, "reward")
        ({'compile': True}, {'compile': False}, {'compile': False})
        >>> fit_speed(OmegaConf.merge(cfg, {"fit_cuda_graph": True}), population=True)
        {'compile': True, 'cuda_graph': True}
    """
    compile = fit != "reward" and OmegaConf.select(cfg, f"training.{fit}.compile", default=False)
    speed = {"compile": bool(compile)}
    if population:
        speed["cuda_graph"] = _graph(cfg)
    return speed


def compiles_fits(cfg: DictConfig) -> bool:
    """Whether a fit of the recipe runs under ``torch.compile`` (a ``training.<fit>.compile``).

    Examples:
        >>> compiles_fits(OmegaConf.create({"training": {"uncertainty": {"compile": True}}}))
        True
    """
    return any(fit_speed(cfg, fit)["compile"] for fit in FITS)


def check_fit_device(cfg: DictConfig, device: torch.device) -> None:
    """Refuse ``fit_cuda_graph`` where ``device`` (the run's, on this machine) is not CUDA.

    Raises:
        ValueError: naming the key and the device.

    Examples:
        >>> cfg = OmegaConf.create({"device": "cpu", "fit_cuda_graph": True})
        >>> check_fit_device(cfg, torch.device("cpu"))
        Traceback (most recent call last):
        ValueError: 'fit_cuda_graph' needs a CUDA device; device=cpu is cpu here.
    """
    if _graph(cfg) and device.type != "cuda":
        raise ValueError(
            f"'fit_cuda_graph' needs a CUDA device; device={cfg.device} is {device} here."
        )


def fit_speed_errors(errors: RecipeErrors, *, members: bool = False) -> None:
    """The recipe checks of ``fit_cuda_graph: true`` (explore, online): a device other than the
    CPU (the machine's is checked at the start, :func:`check_fit_device`), no
    ``training.world_model.compile`` and, with ``members`` (online), ``world_model_members`` of
    at least 2 (it captures a population fit's step)."""
    cfg = errors.cfg
    if not _graph(cfg):
        return
    errors.need("device", str(cfg.device) != "cpu", "a CUDA device with fit_cuda_graph")
    errors.need(
        "training.world_model.compile",
        not cfg.training.world_model.compile,
        "false with fit_cuda_graph (one graph or the other)",
    )
    if members:
        errors.need(
            "world_model_members",
            cfg.world_model_members >= 2,
            "at least 2 with fit_cuda_graph (it captures a population fit's step)",
        )
