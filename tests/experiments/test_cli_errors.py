"""Every failure of the command line ends in one clear line and a documented exit code:
2 user error (recipe, file, run directory), 130 interrupted, 1 a bug; tracebacks only with
``--debug`` or ``HYDRA_FULL_ERROR=1``. Subprocess tests are few; the others run in process."""

from __future__ import annotations

import dataclasses
import fcntl
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torchrl_recon.cli import main, run_recipe
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.experiments import runner
from torchrl_recon.experiments.registry import EXPERIMENT_TYPES

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
IB_EXPLORE = RECIPES / "industrial_benchmark" / "explore_smoke.yaml"


def _cli(*args: str, **kwargs) -> subprocess.Popen:
    """The CLI in a child process; SIGINT is reset to its default (a background shell ignores it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "torchrl_recon.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        **kwargs,
    )


def _error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error:")]


def _locked(run_dir: Path):
    """Hold the run directory's lock as a second run would (another open file, so refused)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    handle = open(run_dir / ".lock", "w")  # noqa: SIM115 - closed by the caller
    fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    return handle


def test_locked_run_dir_is_one_error_line_and_exit_2(tmp_path, capsys):
    """In process (the CLI's own exit path runs in the SIGINT test below): refused at the
    precheck, before Hydra starts."""
    out = tmp_path / "run"
    handle = _locked(out)
    try:
        code = run_recipe("explore", IB_EXPLORE, [f"output_dir={out}", "logger.backend=none"])
    finally:
        handle.close()
    err = capsys.readouterr().err
    assert code == 2, err
    lines = _error_lines(err)
    assert len(lines) == 1 and "Traceback" not in err, err
    assert str(out) in lines[0] and "output_dir" in lines[0]
    assert not (out / "config.yaml").exists()


def test_sigint_mid_run_exits_130_and_the_same_command_resumes(tmp_path, capsys):
    """The CLI binary stopped by Ctrl-C; the same command resumes it (run in process: the
    resume is the library's, and a second interpreter would import torch again, ~5 s)."""
    out = tmp_path / "run"
    smaller = ("retrainings=1", "guided.steps=50", "training.world_model.steps=20")
    args = ("explore", str(IB_EXPLORE), f"output_dir={out}", "logger.backend=none", *smaller)
    proc = _cli(*args)
    # the random arm's record: the retraining is left after it; the resumed run does only it
    first = out / "stages" / "random_arm.json"
    while not first.exists() and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and not _error_lines(err), err
    stage = runner.last_finished_stage(out)
    assert err.strip().splitlines()[-1] == (
        f"interrupted after stage '{stage}' of {out}; run the same command to resume"
    )
    assert not (out / "results.json").exists()
    done_at = first.stat().st_mtime_ns
    assert main(list(args)) == 0, capsys.readouterr().err
    assert first.stat().st_mtime_ns == done_at  # read back, not recomputed
    # the finished run is the explore smoke recipe's whole output (test_recipes' explore smoke
    # on the IB runs in make test-all): results, config, a plot, provenance
    results = json.loads((out / "results.json").read_text())
    assert results["experiment"] == "explore" and results["env"] == "industrial_benchmark"
    assert math.isfinite(results["ratio"]) and set(results["arms"]) == {"random", "active"}
    assert (out / "config.yaml").is_file() and list(out.glob("*.png")), "no plot written"
    meta = results["meta"]
    assert meta["seed"] == 0 and meta["git"]["commit"] and "torchrl" in meta["versions"]


# ------------------------------------------------------------------------------------------
# in process: failures inside the Hydra job


def _failing_experiment(monkeypatch, error: Exception) -> None:
    def run(ctx):
        raise error

    explore = dataclasses.replace(EXPERIMENT_TYPES["explore"], run=run)
    monkeypatch.setitem(EXPERIMENT_TYPES, "explore", explore)


def test_damaged_file_inside_the_job_is_one_error_line_and_exit_2(tmp_path, monkeypatch, capsys):
    message = f"{tmp_path}/buffers/initial_random: truncated; delete stages/initial_random.json"
    _failing_experiment(monkeypatch, DamagedFileError(message))
    code = run_recipe("explore", IB_EXPLORE, [f"output_dir={tmp_path}/run", "logger.backend=none"])
    err = capsys.readouterr().err
    assert code == 2
    assert _error_lines(err) == [f"error: {message}"] and "Traceback" not in err


def test_a_bug_is_one_line_and_exit_1_and_shows_its_traceback_under_hydra_full_error(
    tmp_path, monkeypatch, capsys
):
    _failing_experiment(monkeypatch, ZeroDivisionError("division by zero"))
    overrides = [f"output_dir={tmp_path}/run", "logger.backend=none"]
    assert run_recipe("explore", IB_EXPLORE, overrides) == 1
    err = capsys.readouterr().err
    lines = _error_lines(err)
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "unexpected ZeroDivisionError" in lines[0] and "--debug" in lines[0]
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    assert run_recipe("explore", IB_EXPLORE, overrides) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and len(_error_lines(err)) == 1


def test_multirun_job_errors_each_print_one_line_and_the_sweep_exits_2(
    tmp_path, monkeypatch, capsys
):
    handles = [_locked(tmp_path / f"seed{s}") for s in (0, 1)]
    try:
        code = run_recipe(
            "explore",
            IB_EXPLORE,
            [f"output_dir={tmp_path}/seed${{seed}}", "logger.backend=none", "seed=0,1"],
            multirun=True,
        )
    finally:
        for h in handles:
            h.close()
    err = capsys.readouterr().err
    assert code == 2
    lines = _error_lines(err)
    assert len(lines) == 2 and "Traceback" not in err, err
    assert str(tmp_path / "seed0") in lines[0] and str(tmp_path / "seed1") in lines[1]


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_flag_shows_the_traceback(where, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    args = [str(IB_EXPLORE), f"output_dir={tmp_path}/run", "guided.ratio=nan"]
    assert main(["explore", *args]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    argv = ["--debug", "explore", *args] if where == "before" else ["explore", *args, "--debug"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "RecipeError" in err
    assert _error_lines(err) == [
        f"error: {IB_EXPLORE}: 'guided.ratio' must be a finite number, got nan"
    ]
    assert not (tmp_path / "run").exists()
    assert "HYDRA_FULL_ERROR" not in os.environ  # the switch ends with the command


def test_a_bad_hydra_setting_is_one_error_line_and_exit_2(tmp_path, capsys):
    code = run_recipe("explore", IB_EXPLORE, [f"output_dir={tmp_path}/run", "hydra/launcher=nope"])
    err = capsys.readouterr().err
    assert code == 2
    lines = _error_lines(err)
    assert len(lines) == 1 and "Could not find 'hydra/launcher/nope'" in lines[0]
    assert "Available options in 'hydra/launcher': basic, joblib" in lines[0]
    assert "Traceback" not in err and not (tmp_path / "run").exists()
