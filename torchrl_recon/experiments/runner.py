"""Run one experiment from a config: validate it, prepare its run directory and logger, run its
kind (from the registry) in a :class:`~.context.RunContext`, store the results and figures."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from functools import partial
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from torchrl_recon.devices import check_compile_support, describe_device, resolve_device
from torchrl_recon.errors import CompilerNotFoundError, RecipeError
from torchrl_recon.experiments.context import RecipeLoader, RunContext
from torchrl_recon.experiments.fit_speed import check_fit_device, compiles_fits
from torchrl_recon.experiments.loggers import make_logger
from torchrl_recon.experiments.recipe import load_recipe, resolve_recipe_path, validate
from torchrl_recon.experiments.registry import get_type
from torchrl_recon.experiments.run_dir import prepare_run_dir, release_run_dir, write_results
from torchrl_recon.experiments.stages import StopRequested, verify_run_dir
from torchrl_recon.reports import format_table, get_report, save_figures
from torchrl_recon.runs.allocator import keep_freed_memory


def run_device(cfg: DictConfig) -> torch.device:
    """The device ``cfg`` runs on, checked on this machine: it exists (``ValueError``), and where
    a fit asks for ``compile`` or the planning model for ``planning_compile``, torch.compile can
    build kernels there (:class:`~torchrl_recon.errors.CompilerNotFoundError`), and the fits'
    speed can run there (:func:`~.fit_speed.check_fit_device`, ``ValueError``)."""
    device = resolve_device(cfg.device)
    if compiles_fits(cfg) or cfg.get("planning_compile", False):
        check_compile_support(device)
    check_fit_device(cfg, device)
    return device


def _run_child(cfg: DictConfig, argv: Sequence[str] | None) -> dict[str, Any] | None:
    """Run a child experiment (calibrate's outcomes) made by ``argv``; its headline numbers."""
    results = run(cfg, argv=argv)
    if (outcome := get_report(cfg.experiment).outcome) is None:
        raise ValueError(f"experiment {cfg.experiment!r} cannot run as a child: it has no outcome.")
    return None if results is None else outcome(results)


def last_finished_stage(run_dir: str | os.PathLike[str]) -> str | None:
    """The stage whose record (``stages/<name>.json``) was written last, or None when none was.

    Examples:
        >>> import tempfile
        >>> last_finished_stage(tempfile.mkdtemp()) is None
        True
    """
    records = [p for p in Path(run_dir).glob("stages/*.json") if p.is_file()]
    return max(records, key=lambda p: p.stat().st_mtime_ns).stem if records else None


def interrupted_message(run_dir: str | os.PathLike[str] | None) -> str:
    """The line printed when a run is interrupted: the last finished stage and how to resume.

    Examples:
        >>> interrupted_message(None)
        'interrupted before any stage finished; run the same command to start again'
    """
    stage = last_finished_stage(run_dir) if run_dir is not None else None
    where = f" of {run_dir}" if run_dir is not None else ""
    if stage is None:
        return f"interrupted before any stage finished{where}; run the same command to start again"
    return f"interrupted after stage '{stage}'{where}; run the same command to resume"


def run(
    cfg: DictConfig, argv: Sequence[str] | None = None, extra_meta: Mapping[str, Any] | None = None
) -> dict[str, Any] | None:
    """Validate ``cfg``, check and prepare its run directory, run the experiment, store the
    results; return them, or None when it stopped after ``cfg.stop_after`` (re-running resumes)."""
    cfg = validate(cfg)
    try:
        device = run_device(cfg)
    except (ValueError, CompilerNotFoundError) as e:  # refused before the run directory
        raise RecipeError(str(e)) from e
    torch.set_num_threads(int(cfg.threads))
    extra_meta = {**(extra_meta or {}), "device": describe_device(device)}
    extra_meta["malloc_keeps_freed_memory"] = keep_freed_memory()
    verify_run_dir(Path(cfg.output_dir).expanduser())  # a damaged resume: refused before writing
    with ExitStack() as cleanup:  # the logger shut down, then the run directory released
        run_dir = prepare_run_dir(cfg, argv=argv, extra_meta=extra_meta)
        cleanup.callback(release_run_dir, run_dir)
        tag = f"[{cfg.experiment}]"
        print(f"{tag} {cfg.env.name} seed {cfg.seed}: run directory {run_dir}", flush=True)
        logger = make_logger(cfg, run_dir)
        if logger is not None:
            cleanup.callback(logger.shutdown)
        recipes = RecipeLoader(resolve_recipe_path, load_recipe)
        ctx = RunContext(cfg, run_dir, logger, partial(_run_child, argv=argv), recipes)
        try:
            results = get_type(cfg.experiment).run(ctx)
        except StopRequested as stop:
            stage = stop.args[0] if stop.args else cfg.stop_after
            print(
                f"{tag} stopped after stage '{stage}' (stop_after={cfg.stop_after}). Its outputs "
                f"are in {run_dir}. Re-running the same command resumes from there: stages "
                "already done are skipped (drop stop_after, or name a later stage, to go "
                "further).",
                flush=True,
            )
            return None
        results_path = write_results(run_dir, results)
        figures = [f"figure: {path}" for path in save_figures(results, run_dir)]
        if logger is not None:  # the headline numbers, as scalars under results/
            for name, value in get_report(cfg.experiment).headline(results).items():
                if isinstance(value, (int, float)):
                    logger.log_scalar(f"results/{name}", float(value), step=0)
        print(format_table(results), f"results: {results_path}", *figures, sep="\n", flush=True)
        return results
