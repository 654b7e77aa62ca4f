"""Command line entry point: ``torchrl-recon <command> ...`` (``--help``; docs/experiments.md).

An experiment runs a YAML recipe through Hydra: any key can be overridden on the command line,
and seeds swept with Hydra's multirun (``-m``). Every failure ends in one ``error: ...`` line on
stderr (tracebacks only with ``--debug`` or ``HYDRA_FULL_ERROR=1``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import tempfile
import threading
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path
from unittest import mock

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from omegaconf import DictConfig

from torchrl_recon.devices import resolve_device
from torchrl_recon.errors import DamagedFileError, RecipeError
from torchrl_recon.experiments import summary as summaries
from torchrl_recon.experiments.compose import (
    RECIPES_DIR,
    SEARCH_PATH,
    compose_recipe,
    hydra_error_message,
    sweep_jobs,
    with_additions,
)
from torchrl_recon.experiments.recipe import resolve_recipe_path, validate
from torchrl_recon.experiments.registry import EXPERIMENT_TYPES
from torchrl_recon.experiments.run_dir import RunDirConflict, check_run_dir, read_results
from torchrl_recon.experiments.runner import interrupted_message, run
from torchrl_recon.experiments.tables import render

EXPERIMENTS = {name: t.help for name, t in EXPERIMENT_TYPES.items()}
"""Each experiment command and its help line (from the registry)."""
_ARGV_ENV, _STATUS_ENV = "TORCHRL_RECON_ARGV", "TORCHRL_RECON_STATUS"
"""The command as typed (for each job's ``meta.json``); the file each job appends its exit code
to (jobs may run in other processes)."""
_DEBUG_ENV = "TORCHRL_RECON_DEBUG"
"""``--debug``: "1" or "0" once a command has decided; unset, ``HYDRA_FULL_ERROR`` decides."""
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


def _debug() -> bool:
    return os.environ.get(_DEBUG_ENV, os.environ.get("HYDRA_FULL_ERROR")) == "1"


def report(error: BaseException, code: int | None = None, message: str | None = None) -> int:
    """Print ``error: <message>`` on stderr (after the traceback with ``--debug``); return the
    exit code: 2 for what the user can fix (recipe, missing or damaged file, run directory),
    else 1 (a bug).

    Examples:
        >>> with contextlib.redirect_stderr(sys.stdout):
        ...     report(ZeroDivisionError("division by zero"))
        error: unexpected ZeroDivisionError: division by zero (re-run with --debug for the traceback)
        1
    """
    code = (EXIT_USER if isinstance(error, _USER_ERRORS) else EXIT_BUG) if code is None else code
    if _debug():
        traceback.print_exception(type(error), error, error.__traceback__)
    message = message or str(error) or type(error).__name__
    if code != EXIT_USER:
        message = (
            f"unexpected {type(error).__name__}: {message} (re-run with --debug for the traceback)"
        )
    print(f"error: {message}", file=sys.stderr, flush=True)
    return code


def _interrupted(run_dir: Path | None) -> int:
    if _debug():
        traceback.print_exc()
    print(interrupted_message(run_dir), file=sys.stderr, flush=True)
    return EXIT_INTERRUPTED


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises ``KeyboardInterrupt`` (as Ctrl-C does), unless it is ignored or handled."""
    ours = threading.current_thread() is threading.main_thread()
    ours = ours and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    if ours:
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        if ours:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _env(name: str, value: str | None):
    """Set ``name`` (``None``: leave it) for a block; the environment is restored afterwards."""
    return mock.patch.dict(os.environ, {} if value is None else {name: value})


def hydra_settings(kind: str) -> dict[str, str]:
    """Hydra overrides that keep every output inside the run's ``output_dir``: no chdir, no
    ``.hydra/`` (the run dir holds ``config.yaml`` and ``meta.json``); a single run's Hydra dir
    (its ``<kind>.log``) is ``output_dir``; a sweep's dir (``multirun.yaml``) is the parent of the
    base ``output_dir`` and each job's dir its own ``output_dir``."""
    return {
        "hydra.job.chdir": "False",
        "hydra.output_subdir": "null",
        "hydra.job.name": kind,
        "hydra.run.dir": "${output_dir}",
        "hydra.sweep.dir": "'${trr_parent:${output_dir}}'",
        "hydra.sweep.subdir": "'${trr_abspath:${output_dir}}'",
    }


def _task(cfg: DictConfig) -> int:
    """The Hydra job. A failure prints one ``error:`` line and appends its exit code to the
    status file, so that a multirun goes on with its other jobs; an interrupt names the last
    finished stage and ends the command (130)."""
    if "TORCHRL_LOGGING_LEVEL" not in os.environ:  # one INFO line per replay buffer filled
        logging.getLogger("torchrl").setLevel(logging.WARNING)
    argv = json.loads(os.environ.get(_ARGV_ENV, "null")) or list(sys.argv)
    job = HydraConfig.get()
    extra = {"job_overrides": list(job.overrides.task), "hydra_mode": job.mode.name.lower()}
    try:
        run(cfg, argv=argv, extra_meta=extra)
    except KeyboardInterrupt:
        try:
            run_dir = Path(str(cfg.output_dir)).expanduser().resolve()
        except Exception:  # an interpolation that does not resolve: no directory to name
            run_dir = None
        raise SystemExit(_interrupted(run_dir)) from None
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
        if items and item.startswith("-") and (item in _VALUE_FLAGS or info):
            flags.append(items.pop(0))
    return flags, plain


def precheck(kind: str, recipe: Path, overrides: Sequence[str], *, here: bool = True) -> list[str]:
    """Check every job of the command (the product of its sweeps and the recipe's
    ``hydra.sweeper.params``, each composed by Hydra) and its run directory (a run there must
    have the same config) before Hydra starts anything; with ``here``, each job's ``device``
    must exist on this machine. Returns the overrides for Hydra (see ``with_additions``).

    Raises:
        FileNotFoundError / RecipeError / RunDirConflict: naming the file, key or directory.
    """
    base = compose_recipe(recipe, with_hydra=True)
    found = base.get("experiment")
    if found != kind:
        raise RecipeError(
            f"{recipe}: its experiment is {found!r}: run it with `torchrl-recon {found} {recipe}`."
            if found in EXPERIMENTS
            else f"{recipe}: 'experiment' must be {kind!r}, got {found!r}."
        )
    completed = with_additions(base, overrides)
    for job in sweep_jobs(base, completed):
        swept = [o for o in job if o not in completed]
        source = f"{recipe} with {' '.join(swept)}" if swept else str(recipe)
        checked = validate(compose_recipe(recipe, job), source=source)
        try:
            if here:
                resolve_device(checked.device)
        except ValueError as e:
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
    """Run a recipe (a path, or a shipped recipe's name) through ``hydra.main``; return the exit
    code (0, 2 a user error, 130 interrupted, 1 a bug; a multirun's worst job's).

    For the call, Hydra's ``sys.argv`` is ``[prog, *Hydra flags, <hydra settings>, *overrides]``
    (plus ``--multirun``), the recipe being the app's config. A failed job of a multirun does
    not stop the others. ``debug`` shows tracebacks (as ``HYDRA_FULL_ERROR=1``).
    """
    command = ["torchrl-recon", kind, str(recipe), *overrides] + ["--multirun"] * multirun
    flags, plain = _split_overrides(overrides)
    with _env(_DEBUG_ENV, "1" if debug or _debug() else "0"):
        try:
            path = resolve_recipe_path(recipe)
            slurm = any(o.startswith("hydra/launcher=submitit_slurm") for o in plain)
            # the jobs of a cluster check their device where they run
            plain = precheck(kind, path, plain, here=not (multirun and slurm))
        except (FileNotFoundError, ValueError, RunDirConflict) as e:
            return report(e, EXIT_USER)
        given = {o.split("=", 1)[0].lstrip("+") for o in plain if "=" in o}
        settings = [f"{k}={v}" for k, v in hydra_settings(kind).items() if k not in given]
        fd, status = tempfile.mkstemp(prefix="torchrl_recon_status_")
        os.close(fd)
        argv = ["torchrl-recon", *flags, *settings, f"++hydra.job.env_set.{_STATUS_ENV}='{status}'"]
        argv += [SEARCH_PATH, *plain] + ["--multirun"] * multirun
        config_dir = str(path.resolve().parent)
        app = hydra.main(version_base="1.3", config_path=config_dir, config_name=path.stem)(_task)
        code = EXIT_OK
        # HYDRA_FULL_ERROR=1: Hydra raises its own errors instead of printing them
        try:
            with mock.patch.object(sys, "argv", argv), _env(_ARGV_ENV, json.dumps(command)):
                with _env("HYDRA_FULL_ERROR", "1"):
                    app()
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except KeyboardInterrupt:  # outside a job (Hydra starting up): nothing to resume
            code = _interrupted(None)
        except HydraException as e:  # a bad Hydra setting or config group choice
            code = report(e, EXIT_USER, hydra_error_message(e))
        except Exception as e:
            code = report(e)
        finally:
            jobs = [int(line) for line in Path(status).read_text().split()]
            Path(status).unlink(missing_ok=True)
        return code or max(jobs, default=EXIT_OK)


def shipped_recipes(kind: str | None = None) -> list[tuple[str, str, str]]:
    """``(kind, name, first comment line)`` of each recipe shipped in the package (of ``kind``
    only, if given); a name runs from any folder (``torchrl-recon explore drone/explore``).

    Examples:
        >>> ("explore", "drone/explore_smoke") in [r[:2] for r in shipped_recipes("explore")]
        True
    """
    out = []
    for path in sorted(RECIPES_DIR.glob("*/*.yaml")):
        found = next((k for k in EXPERIMENTS if path.stem.startswith(k)), None)
        if found is not None and kind in (None, found):
            lines = path.read_text().splitlines()
            about = next((x.lstrip("#").strip() for x in lines if x.startswith("#")), "")
            out.append((found, path.relative_to(RECIPES_DIR).with_suffix("").as_posix(), about))
    return sorted(out, key=lambda r: list(EXPERIMENTS).index(r[0]))


def _experiment(args: argparse.Namespace) -> int:
    given = args.overrides  # -m and --debug after the recipe are left in the overrides
    overrides = [o for o in given if o not in ("-m", "--multirun", "--debug")]
    multirun = args.multirun or bool({"-m", "--multirun"} & set(given))
    return run_recipe(args.command, args.recipe, overrides, multirun, debug="--debug" in given)


def _summarize(args: argparse.Namespace) -> int:
    files = summaries.find_results(args.dirs)
    if not files:
        raise FileNotFoundError(f"no results.json found below {', '.join(args.dirs)}")
    results = {f: read_results(f) for f in files}
    by_kind: dict[str, list[Path]] = {}
    for f, r in results.items():
        by_kind.setdefault(str(r.get("experiment")), []).append(f)
    if args.out is not None:
        Path(args.out).mkdir(parents=True, exist_ok=True)
    for kind, kind_files in sorted(by_kind.items()):
        summary = summaries.summarize(kind_files)
        print(f"{len(kind_files)} {kind} result file(s)\n{summaries.format_table(summary)}\n")
        if args.out is not None:
            saved = summaries.save_summary(summary, [results[f] for f in kind_files], args.out)
            print(f"summary: {saved[0]}" + "".join(f"\nfigure: {f}" for f in saved[1:]))
    return EXIT_OK


def _recipes(args: argparse.Namespace) -> int:
    print(render(["kind", "recipe", "about"], [list(r) for r in shipped_recipes(args.kind)]))
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser: one command per experiment kind, ``summarize``, ``recipes``."""
    experiments = "\n".join(f"  {k:<9} {v}" for k, v in EXPERIMENTS.items())
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog="torchrl-recon",
        description="TorchRL reproduction of Di Palo & Valpola: the paper's "
        "experiments, and their summaries.",
        epilog=f"experiments (paper §3):\n{experiments}\n\n{_EXAMPLES}",
        formatter_class=raw,
    )
    debug_help = "show tracebacks (as HYDRA_FULL_ERROR=1 does); exit codes stay the same"
    parser.add_argument("--debug", action="store_true", help=debug_help)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=debug_help)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for kind, text in EXPERIMENTS.items():
        names = "\n".join(f"  {name}" for _, name, _ in shipped_recipes(kind))
        p = sub.add_parser(
            kind,
            parents=[common],
            help=text,
            description=f"{text}. Runs RECIPE through Hydra: overrides are key=value "
            "(e.g. seed=3 guided.ratio=1.5, +key=value to add one); -m sweeps "
            "comma-separated values with Hydra's multirun; Hydra flags such as "
            "`--cfg job` pass through. Re-running the same command resumes a stopped run.",
            epilog=f"recipes (by name, from any folder; or a path to your own):\n{names}",
            formatter_class=raw,
        )
        p.add_argument("recipe", metavar="RECIPE", help="a recipe YAML file or a shipped name")
        p.add_argument(
            "overrides",
            nargs=argparse.REMAINDER,
            metavar="OVERRIDE",
            help="key=value overrides of the recipe (Hydra syntax)",
        )
        p.add_argument("-m", "--multirun", action="store_true", help="run a Hydra multirun sweep")
        p.set_defaults(func=_experiment)
    summ = sub.add_parser(
        "summarize",
        parents=[common],
        help="aggregate results.json files across seeds (Table 1 statistics, control means)",
        description="Find results.json below each DIR, aggregate them per experiment kind and "
        "environment, and print the tables.",
    )
    summ.add_argument("dirs", nargs="+", metavar="DIR")
    summ.add_argument(
        "--out", default=None, help="also write summary_<kind>.json and figures to this directory"
    )
    summ.set_defaults(func=_summarize)
    rec = sub.add_parser(
        "recipes", parents=[common], help="list the shipped recipes (kind, name, what it runs)"
    )
    rec.add_argument("kind", nargs="?", choices=list(EXPERIMENTS), help="only this kind's")
    rec.set_defaults(func=_recipes)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code (0, 2 user error, 130 interrupted, 1 bug)."""
    args = build_parser().parse_args(argv)
    with _env(_DEBUG_ENV, "1" if getattr(args, "debug", False) else None), _sigterm_as_interrupt():
        try:
            torch.set_num_threads(min(2, torch.get_num_threads()))
            return args.func(args)
        except KeyboardInterrupt:
            return _interrupted(None)
        except Exception as e:
            return report(e)


if __name__ == "__main__":
    sys.exit(main())
