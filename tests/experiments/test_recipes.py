"""Every recipe at smoke scale, end to end through the command line, as a user runs it."""

from __future__ import annotations

import io
import json
import math
import subprocess
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest
import torch
import yaml

from torchrl_recon.cli import main
from torchrl_recon.reports.control import result_table

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
# make test runs control on the IB (test_cli_errors' SIGINT test checks the IB explore smoke's
# output); the rest (50 s) in make test-all
SMOKE = [
    (kind, env)
    if (kind, env) == ("control", "industrial_benchmark")
    else pytest.param(kind, env, marks=pytest.mark.slow)
    for env in ("industrial_benchmark", "drone", "minitaur")
    for kind in ("explore", "control")
]


def _run(kind: str, recipe: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``torchrl-recon kind recipe overrides`` run by the command line's ``main`` in this
    process (a subprocess would import torch again for each run; ``test_cli_errors`` runs the
    installed entry point itself), its exit code and printed output as a finished process's."""
    argv = [kind, str(recipe), *overrides]
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(argv)
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


def _finite_numbers(obj) -> bool:
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, dict):
        return all(
            _finite_numbers(v)
            for k, v in obj.items()
            if k not in ("test", "feasible_fraction", "active_feasible_fraction")
        )
    if isinstance(obj, list):
        return all(_finite_numbers(v) for v in obj)
    return True


def _check_env_returns(results: dict) -> None:
    """The control table's env return and its random policy (one run serves both tests)."""
    random = results["random_policy"]
    assert len(random["env_returns"]) == 2 and all(math.isfinite(x) for x in random["env_returns"])
    for setting in results["settings"].values():
        assert setting["ended_in_warmup"] == 0
        assert all(math.isfinite(e["env_return"]) for e in setting["episodes"])
    table = result_table(results)
    assert "env_return" in table and "random policy" in table


@pytest.mark.parametrize("kind, env", SMOKE)
def test_smoke_recipe_runs_end_to_end(kind, env, tmp_path):
    out = tmp_path / "run"
    proc = _run(kind, RECIPES / env / f"{kind}_smoke.yaml", f"output_dir={out}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["experiment"] == kind and results["env"] == env
    assert (out / "config.yaml").is_file()
    assert list(out.glob("*.png")), "no plot written"
    if kind == "explore":
        assert _finite_numbers(results["arms"]) and math.isfinite(results["ratio"])
    else:
        assert _finite_numbers({k: v["mean"] for k, v in results["settings"].items()})
        _check_env_returns(results)
    meta = results["meta"]
    assert (
        meta["seed"] == 0
        and meta["git"]["commit"]
        and {"torch", "torchrl", "tensordict"} <= set(meta["versions"])
    )


@pytest.mark.slow  # 15 s; test_experiments' explore resume covers stop_after
def test_stopped_recipe_resumes_to_the_same_results(tmp_path):
    recipe = RECIPES / "industrial_benchmark" / "explore_smoke.yaml"
    assert _run("explore", recipe, f"output_dir={tmp_path / 'full'}").returncode == 0
    stopped = _run(
        "explore", recipe, f"output_dir={tmp_path / 'resumed'}", "stop_after=guided_data_1"
    )
    assert stopped.returncode == 0, stopped.stderr[-3000:]
    assert not (tmp_path / "resumed" / "results.json").exists()
    assert _run("explore", recipe, f"output_dir={tmp_path / 'resumed'}").returncode == 0
    full = json.loads((tmp_path / "full" / "results.json").read_text())
    resumed = json.loads((tmp_path / "resumed" / "results.json").read_text())
    assert resumed["arms"] == full["arms"]
    assert resumed["data"] == full["data"]


CALIBRATION_METRICS = (
    "spearman",
    "auroc_error_above_median",
    "ood_auroc_state_shift",
    "ood_auroc_action_bound",
)


@pytest.mark.parametrize(  # IB's (19 s) and the Minitaur's (13 s) in make test-all; the Drone's here
    "env",
    [pytest.param(e, marks=pytest.mark.slow) for e in ("industrial_benchmark", "minitaur")]
    + ["drone"],
)
def test_calibrate_smoke_recipe_runs_end_to_end(env, tmp_path):
    """All five estimators fitted, judged and timed; the outcome runs on IB only (time)."""
    out = tmp_path / "run"
    skip = [] if env == "industrial_benchmark" else ["outcomes.explore_recipe=null"]
    recipe = RECIPES / env / "calibrate_smoke.yaml"
    proc = _run("calibrate", recipe, f"output_dir={out}", "outcomes.control_recipe=null", *skip)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["experiment"] == "calibrate" and results["env"] == env
    assert list(results["estimators"]) == [
        "reconstruction",
        "ensemble",
        "mc_dropout",
        "rnd",
        "world_model_ensemble",
    ]
    for name, row in results["estimators"].items():
        for key in CALIBRATION_METRICS:
            assert -1.0 <= row[key] <= 1.0, (name, key, row[key])
        assert row["score_ms_H10"] > 0 and row["cem_ms_H10"] > 0
        assert ("explore_ratio" in row) == (env == "industrial_benchmark")
    assert results["estimators"]["reconstruction"]["score_ratio_H10"] == 1.0
    assert (out / "calibration.png").is_file()
    assert "OOD AUROC" in proc.stdout
    if env == "industrial_benchmark":
        sub = json.loads((out / "outcomes" / "rnd" / "explore" / "results.json").read_text())
        assert sub["experiment"] == "explore"
        sub_cfg = yaml.safe_load((out / "outcomes" / "rnd" / "explore" / "config.yaml").read_text())
        assert sub_cfg["models"]["uncertainty"]["kind"] == "rnd"
        feasible = results["estimators"]["rnd"]["outcomes"]["explore"]["active_feasible_fraction"]
        assert 0.0 <= feasible <= 1.0  # the explore run's share of plans above the Σu threshold
        # the world models' disagreement guides exploration like the other estimators
        wme = out / "outcomes" / "world_model_ensemble" / "explore" / "results.json"
        assert json.loads(wme.read_text())["arms"]["active"]["mean"] > 0


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@CUDA
@pytest.mark.parametrize(
    "kind, env",
    [*SMOKE, *(("calibrate", e) for e in ("industrial_benchmark", "drone", "minitaur"))],
)
def test_smoke_recipe_runs_on_cuda(kind, env, tmp_path):
    """Every smoke recipe end to end with the networks on the GPU (envs on the CPU)."""
    out = tmp_path / "run"
    extra = ["outcomes.control_recipe=null", "outcomes.explore_recipe=null"] * (kind == "calibrate")
    proc = _run(
        kind, RECIPES / env / f"{kind}_smoke.yaml", f"output_dir={out}", "device=cuda", *extra
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["meta"]["device"]["device"] == "cuda"
    assert results["meta"]["device"]["name"]


def test_device_cuda_without_a_gpu_is_refused_before_any_work(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    out = tmp_path / "run"
    recipe = RECIPES / "industrial_benchmark" / "explore_smoke.yaml"
    proc = _run("explore", recipe, f"output_dir={out}", "device=cuda")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith("error: ")
    assert "CUDA device" in proc.stderr and not out.exists()


@pytest.mark.parametrize("key", ["training.world_model.compile", "planning_compile"])
def test_compile_without_a_cpp_compiler_is_refused_before_any_work(key, tmp_path, monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler++")
    out = tmp_path / "run"
    recipe = RECIPES / "industrial_benchmark" / "control_smoke.yaml"
    proc = _run("control", recipe, f"output_dir={out}", "device=cpu", f"{key}=true")
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and "'no-such-compiler++' is not on PATH" in last
    assert not out.exists()
