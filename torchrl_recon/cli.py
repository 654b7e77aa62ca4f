"""Command line entry point: ``torchrl-recon <command> ...`` (``--help``). An experiment runs a
YAML recipe through Hydra (overrides, ``-m`` sweeps); every failure ends in one ``error:`` line."""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import signal
import sys
import tempfile
import threading
import traceback
from collections.abc import Sequence
from contextlib import nullcontext
from functools import partial
from pathlib import Path
from unittest import mock

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf

from torchrl_recon.errors import CompilerNotFoundError, DamagedFileError, RecipeError
from torchrl_recon.experiments import compose
from torchrl_recon.experiments.recipe import resolve_recipe_path, validate
from torchrl_recon.experiments.registry import EXPERIMENT_TYPES
from torchrl_recon.experiments.run_dir import RunDirConflict, check_run_dir
from torchrl_recon.experiments.runner import interrupted_message, run, run_device
from torchrl_recon.reports import format_table, save_summary, summarize_by_kind
from torchrl_recon.reports.tables import render
from torchrl_recon.runs.interrupts import redeliver_dropped_interrupts

_ARGV_ENV = "TORCHRL_RECON_ARGV"  # the command as typed, for each job's meta.json
_STATUS_ENV = "TORCHRL_RECON_STATUS"  # each job appends its exit code to this file
_DEBUG_ENV = "TORCHRL_RECON_DEBUG"  # --debug: "1" or "0"; unset, HYDRA_FULL_ERROR decides
EXIT_OK, EXIT_BUG, EXIT_USER, EXIT_INTERRUPTED = 0, 1, 2, 130
_USER_ERRORS = (RecipeError, DamagedFileError, RunDirConflict, FileNotFoundError)
_EXAMPLES = """examples:
  torchrl-recon explore recipes/industrial_benchmark/explore_smoke.yaml
  torchrl-recon control drone/control seed=3 logger.backend=csv
  torchrl-recon explore recipes/drone/explore.yaml -m seed=0,1,2,3,4 hydra/launcher=joblib hydra.launcher.n_jobs=2
  torchrl-recon summarize outputs/explore/drone
  torchrl-recon recipes

exit codes: 0 done; 2 bad recipe, missing or damaged file, locked or conflicting run
directory; 130 interrupted (re-run the same command to resume); 1 a bug (see --debug).

Details: docs/experiments.md"""
_RUN_HELP = """Runs RECIPE through Hydra: overrides are key=value (e.g. seed=3 guided.ratio=1.5,
+key=value to add one); -m sweeps comma-separated values with Hydra's multirun; Hydra flags
such as `--cfg job` pass through. Re-running the same command resumes a stopped run."""
_ABOUT = "TorchRL reproduction of Di Palo & Valpola: the paper's experiments, and their summaries."
_SUMMARIZE_HELP = """Find results.json below each DIR, aggregate them per experiment kind and
environment, and print the tables."""


def _debug() -> bool:
    return os.environ.get(_DEBUG_ENV, os.environ.get("HYDRA_FULL_ERROR")) == "1"


def report(error: BaseException, code: int | None = None, message: str | None = None) -> int:
    """Print ``error: <message>`` on stderr (after the traceback with ``--debug``); return the
    exit code: 2 for what the user can fix (recipe, file, run directory), else 1 (a bug).

    Examples:
        >>> from contextlib import redirect_stderr
        >>> with redirect_stderr(sys.stdout):
        ...     report(ZeroDivisionError("division by zero"))
        error: unexpected ZeroDivisionError: division by zero (re-run with --debug for the traceback)
        1
    """
    code = (EXIT_USER if isinstance(error, _USER_ERRORS) else EXIT_BUG) if code is None else code
    if _debug():
        traceback.print_exception(type(error), error, error.__traceback__)
    message = message or str(error) or type(error).__name__
    if code != EXIT_USER:
        hint = "re-run with --debug for the traceback"
        message = f"unexpected {type(error).__name__}: {message} ({hint})"
    print(f"error: {message}", file=sys.stderr, flush=True)
    return code


def _interrupted(run_dir: Path | None) -> int:
    if _debug():
        traceback.print_exc()
    print(interrupted_message(run_dir), file=sys.stderr, flush=True)
    return EXIT_INTERRUPTED


_HYDRA_SETTINGS = {  # every output inside output_dir: a sweep's is its parent, a job's its own
    "hydra.job.chdir": "False",
    "hydra.output_subdir": "null",  # no .hydra/: the run dir holds config.yaml and meta.json
    "hydra.run.dir": "${output_dir}",
    "hydra.sweep.dir": "'${trr_parent:${output_dir}}'",
    "hydra.sweep.subdir": "'${trr_abspath:${output_dir}}'",
}


def _task(cfg: DictConfig) -> int:
    """The Hydra job. A failure prints one ``error:`` line and appends its exit code to the
    status file (a multirun goes on); an interrupt names the last finished stage (130)."""
    if "TORCHRL_LOGGING_LEVEL" not in os.environ:  # one INFO line per replay buffer filled
        logging.getLogger("torchrl").setLevel(logging.WARNING)
    argv = json.loads(os.environ.get(_ARGV_ENV, "null")) or list(sys.argv)
    job = HydraConfig.get()
    extra = {"job_overrides": list(job.overrides.task), "hydra_mode": job.mode.name.lower()}
    try:
        run(cfg, argv=argv, extra_meta=extra)
    except KeyboardInterrupt:  # name the run directory, if its path resolves
        out = OmegaConf.select(cfg, "output_dir", throw_on_resolution_failure=False)
        raise SystemExit(_interrupted(Path(out).expanduser().resolve() if out else None)) from None
    except Exception as e:
        code = report(e)
        if not os.environ.get(_STATUS_ENV):  # not started by run_recipe: end as a command would
            raise SystemExit(code) from None
        with open(os.environ[_STATUS_ENV], "a") as f:
            f.write(f"{code}\n")
        return code
    return EXIT_OK


_VALUE_FLAGS = ("--cfg", "-c", "--package", "-p", "--config-name", "-cn")
_INFO_TOPICS = ("all", "config", "defaults", "defaults-tree", "plugins", "searchpath")


def _split_overrides(items: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split Hydra command line items into flags (``--cfg job`` ...) and overrides."""
    flags, plain, items = [], [], list(items)
    while items:
        item = items.pop(0)
        (flags if item.startswith("-") else plain).append(item)
        info = item in ("--info", "-i") and items[:1] and items[0] in _INFO_TOPICS
        if items and (item in _VALUE_FLAGS or info):
            flags.append(items.pop(0))
    return flags, plain


def precheck(kind: str, recipe: Path, overrides: Sequence[str], *, here: bool = True) -> list[str]:
    """Check every job of the command (each sweep's, composed by Hydra), its run directory and
    (``here``) its device and, for a fit's ``compile``, its compiler before Hydra starts
    anything; return the overrides for Hydra. Raises FileNotFoundError, RecipeError or
    RunDirConflict naming the file, key or directory."""
    base = compose.compose_recipe(recipe, with_hydra=True)
    if (found := base.get("experiment")) != kind:
        raise RecipeError(
            f"{recipe}: its experiment is {found!r}: run it with `torchrl-recon {found} {recipe}`."
            if found in EXPERIMENT_TYPES
            else f"{recipe}: 'experiment' must be {kind!r}, got {found!r}."
        )
    completed = compose.with_additions(base, overrides)
    for job in compose.sweep_jobs(base, completed):
        swept = [o for o in job if o not in completed]
        source = f"{recipe} with {' '.join(swept)}" if swept else str(recipe)
        checked = validate(compose.compose_recipe(recipe, job), source=source)
        try:
            if here:
                run_device(checked)
        except (ValueError, CompilerNotFoundError) as e:
            raise RecipeError(f"{source}: {e}") from e
        check_run_dir(checked)
    return completed


def run_recipe(
    kind: str,
    recipe: str | os.PathLike[str],
    overrides: Sequence[str] = (),
    multirun: bool = False,
    *,
    debug: bool = False,
) -> int:
    """Run a recipe (a path or a shipped name) through ``hydra.main`` (``debug``: tracebacks);
    return :func:`main`'s exit code (a multirun's worst job's: a failed job stops no other)."""
    command = ["torchrl-recon", kind, str(recipe), *overrides] + ["--multirun"] * multirun
    flags, plain = _split_overrides(overrides)
    with mock.patch.dict(os.environ, {_DEBUG_ENV: "1" if debug or _debug() else "0"}):
        try:
            path = resolve_recipe_path(recipe)
            slurm = any(o.startswith("hydra/launcher=submitit_slurm") for o in plain)
            # the jobs of a cluster check their device where they run
            plain = precheck(kind, path, plain, here=not (multirun and slurm))
        except (FileNotFoundError, ValueError, RunDirConflict) as e:
            return report(e, EXIT_USER)
        given = {o.split("=", 1)[0].lstrip("+") for o in plain if "=" in o}
        settings = {**_HYDRA_SETTINGS, "hydra.job.name": kind}.items()
        settings = [f"{k}={v}" for k, v in settings if k not in given]
        fd, status = tempfile.mkstemp(prefix="torchrl_recon_status_")
        os.close(fd)
        argv = ["torchrl-recon", *flags, *settings, f"++hydra.job.env_set.{_STATUS_ENV}='{status}'"]
        argv += [compose.SEARCH_PATH, *plain] + ["--multirun"] * multirun
        config_dir = str(path.resolve().parent)
        app = hydra.main(version_base="1.3", config_path=config_dir, config_name=path.stem)(_task)
        code = EXIT_OK
        # HYDRA_FULL_ERROR=1: Hydra raises its own errors instead of printing them
        try:
            env = {_ARGV_ENV: json.dumps(command), "HYDRA_FULL_ERROR": "1"}
            with mock.patch.object(sys, "argv", argv), mock.patch.dict(os.environ, env):
                app()
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except KeyboardInterrupt:  # outside a job (Hydra starting up): nothing to resume
            code = _interrupted(None)
        except HydraException as e:  # a bad Hydra setting or config group choice
            code = report(e, EXIT_USER, compose.hydra_error_message(e))
        except Exception as e:
            code = report(e)
        finally:
            jobs = [int(line) for line in Path(status).read_text().split()]
            Path(status).unlink(missing_ok=True)
        return code or max(jobs, default=EXIT_OK)


def shipped_recipes(kind: str | None = None) -> list[tuple[str, str, str]]:
    """``(kind, name, what it runs)`` of each shipped recipe (of ``kind`` only, if given): the
    first sentence of its leading comment (:func:`recipe_about`).

    Examples:
        >>> ("explore", "drone/explore_smoke") in [r[:2] for r in shipped_recipes("explore")]
        True
    """
    out = []
    for found in [k for k in EXPERIMENT_TYPES if kind in (None, k)]:
        for path in sorted(compose.RECIPES_DIR.glob(f"*/{found}*.yaml")):
            about = recipe_about(path.read_text())
            out.append((found, f"{path.parent.name}/{path.stem}", about))
    return out


def recipe_about(text: str, width: int = 110) -> str:
    """The first sentence of a recipe's leading comment (its lines joined, up to an empty
    comment line or an indented command), cut at a word before ``width`` characters.

    Examples:
        >>> recipe_about("# Pendulum-v1 learned online: PETS's sizes. The rest.")
        "Pendulum-v1 learned online: PETS's sizes."
    """
    words = []
    for line in text.splitlines():
        if not line.startswith("#") or line.startswith("#  ") or not line.strip("# "):
            break
        words.append(line.lstrip("#").strip())
    about = " ".join(words)
    end = re.search(r"(?<!\bFig)(?<!\beq)(?<!e\.g)(?<!i\.e)\. ", about)  # not "Fig. 3", "eq. 4"
    about = about if end is None else about[: end.start() + 1]
    if len(about) > width:
        about = about[: about.rfind(" ", 0, width - 1)].rstrip(",;:") + " …"
    return about


def _experiment(args: argparse.Namespace) -> int:
    given = args.overrides  # -m and --debug after the recipe are left in the overrides
    overrides = [o for o in given if o not in ("-m", "--multirun", "--debug")]
    multirun = args.multirun or bool({"-m", "--multirun"} & set(given))
    return run_recipe(args.command, args.recipe, overrides, multirun, debug="--debug" in given)


def _summarize(args: argparse.Namespace) -> int:
    try:  # files of several kinds, or of one env and seed twice: the user's choice of folders
        summaries = summarize_by_kind(args.dirs)
    except ValueError as e:
        return report(e, EXIT_USER)
    for found, results in summaries:
        print(f"{len(results)} {found['experiment']} result file(s)\n{format_table(found)}\n")
        if args.out is not None:
            saved = save_summary(found, results, args.out)
            print(f"summary: {saved[0]}" + "".join(f"\nfigure: {f}" for f in saved[1:]))
    return EXIT_OK


def _recipes(args: argparse.Namespace) -> int:
    print(render(["kind", "recipe", "about"], [list(r) for r in shipped_recipes(args.kind)]))
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser: one command per experiment kind, ``summarize``, ``recipes``."""
    raw = {"formatter_class": argparse.RawDescriptionHelpFormatter}
    kinds = "\n".join(f"  {k:<9} {t.help}" for k, t in EXPERIMENT_TYPES.items())
    epilog = f"experiments (paper §3):\n{kinds}\n\n{_EXAMPLES}"
    parser = argparse.ArgumentParser("torchrl-recon", description=_ABOUT, epilog=epilog, **raw)
    common = argparse.ArgumentParser(add_help=False)
    debug_help = "show tracebacks (as HYDRA_FULL_ERROR=1 does); exit codes stay the same"
    for p, default in ((parser, False), (common, argparse.SUPPRESS)):
        p.add_argument("--debug", action="store_true", default=default, help=debug_help)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add = partial(sub.add_parser, parents=[common])
    for kind, t in EXPERIMENT_TYPES.items():
        names = "".join(f"\n  {name}" for _, name, _ in shipped_recipes(kind))
        epilog = f"recipes (by name, from any folder; or a path to your own):{names}"
        p = add(kind, help=t.help, description=f"{t.help}. {_RUN_HELP}", epilog=epilog, **raw)
        p.add_argument("recipe", metavar="RECIPE", help="a recipe YAML file or a shipped name")
        about = "key=value overrides of the recipe (Hydra syntax)"
        p.add_argument("overrides", nargs=argparse.REMAINDER, metavar="OVERRIDE", help=about)
        p.add_argument("-m", "--multirun", action="store_true", help="run a Hydra multirun sweep")
        p.set_defaults(func=_experiment)
    about = "aggregate results.json files across seeds (Table 1 statistics, control means)"
    p = add("summarize", help=about, description=_SUMMARIZE_HELP)
    p.add_argument("dirs", nargs="+", metavar="DIR")
    p.add_argument("--out", help="also write summary_<kind>.json and figures to this directory")
    p.set_defaults(func=_summarize)
    p = add("recipes", help="list the shipped recipes (kind, name, what it runs)")
    p.add_argument("kind", nargs="?", choices=list(EXPERIMENT_TYPES), help="only this kind's")
    p.set_defaults(func=_recipes)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code (0, 2 user error, 130 interrupted, 1 bug)."""
    args = build_parser().parse_args(argv)
    # SIGTERM interrupts as Ctrl-C does (unless it is ignored or handled)
    in_main = threading.current_thread() is threading.main_thread()
    sigterm = in_main and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    if sigterm:
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    # an interrupt that lands in a finaliser stops the run all the same
    redelivery = redeliver_dropped_interrupts() if in_main else nullcontext()
    with mock.patch.dict(os.environ, {_DEBUG_ENV: "1"} if args.debug else {}), redelivery:
        try:
            torch.set_num_threads(min(2, torch.get_num_threads()))
            return args.func(args)
        except KeyboardInterrupt:
            return _interrupted(None)
        except Exception as e:
            return report(e)
        finally:
            if sigterm:
                signal.signal(signal.SIGTERM, signal.SIG_DFL)


if __name__ == "__main__":
    sys.exit(main())
