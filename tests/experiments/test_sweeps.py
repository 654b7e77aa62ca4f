"""Sweeps through Hydra's submitit launcher: the same multirun that runs on a SLURM cluster, with
``submitit_local`` (real submitit jobs, processes on this machine)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

RECIPES = Path(__file__).resolve().parents[2] / "recipes"


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torchrl_recon.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)


@pytest.mark.slow  # 29 s of real submitit jobs; the sweeps' wiring runs in test_plumbing.py
def test_two_seeds_through_submitit_local_then_summarize(tmp_path):
    recipe = RECIPES / "industrial_benchmark" / "explore_smoke.yaml"
    out = tmp_path / "explore"
    proc = _cli(
        "explore",
        str(recipe),
        "-m",
        "seed=0,1",
        "hydra/launcher=submitit_local",
        "hydra.launcher.timeout_min=10",
        f"output_dir={out}/seed${{seed}}",
        "logger.backend=none",
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    results = [json.loads((out / f"seed{s}" / "results.json").read_text()) for s in (0, 1)]
    assert [r["seed"] for r in results] == [0, 1]
    assert results[0]["arms"]["random"]["mse"] != results[1]["arms"]["random"]["mse"]
    assert [r["meta"]["hydra_mode"] for r in results] == ["multirun", "multirun"]
    assert any((out / ".submitit").iterdir())  # submitit's own job folders: it really ran them

    summary = _cli("summarize", str(out), "--out", str(tmp_path / "summary"))
    assert summary.returncode == 0, summary.stderr
    assert "industrial_benchmark  2" in summary.stdout
    assert "made on: cpu" in summary.stdout
    saved = json.loads((tmp_path / "summary" / "summary_explore.json").read_text())
    assert saved["envs"]["industrial_benchmark"]["seeds"] == [0, 1]
