"""``make gpu-check`` (benchmarks/gpu_check.py): its CPU-side path runs here, the GPU steps skip."""

from __future__ import annotations

import functools
import io
import json
import re
import subprocess
from contextlib import redirect_stdout
from pathlib import Path

import pytest
import torch

from tests.scripts import load_script

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"
SCRIPT = BENCHMARKS / "gpu_check.py"
NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")


@functools.cache
def _load():
    """The script as a module."""
    return load_script(SCRIPT)


def _check(out: Path, *args: str) -> subprocess.CompletedProcess:
    """The check's ``main`` in this process (its steps are subprocesses of their own), its exit
    code and printed lines as a finished process's."""
    argv, printed = ["--out", str(out), *args], io.StringIO()
    with redirect_stdout(printed):
        code = _load().main(argv)
    return subprocess.CompletedProcess(argv, code, printed.getvalue(), "")


def _sections(report: str) -> dict[str, str]:
    """Each step's section of the report: its title → its status line."""
    titles = re.findall(r"^## \d+\. (.+)$", report, flags=re.MULTILINE)
    statuses = re.findall(r"^status: (.+); exit status: .+$", report, flags=re.MULTILINE)
    assert len(titles) == len(statuses), report
    return dict(zip(titles, statuses, strict=True))


def test_every_device_benchmark_is_a_step_of_the_check():
    """A benchmark script that takes ``--device`` runs in the check (so 'every benchmark' holds)."""
    check = _load()
    in_check = {script for _, script, *_ in check.BENCHMARK_STEPS}
    with_device = {
        path.name
        for path in BENCHMARKS.glob("*.py")
        if path.name not in ("_common.py", "gpu_check.py")
        and re.search(r"parse_device_args|add_device_argument|\"--device\"", path.read_text())
    }
    assert with_device == in_check
    steps = check.build_steps("cuda", tiny=False, out=Path("out"))
    assert [s.kind for s in steps].count("experiment") == 4
    assert all("--device" in s.argv for s in steps if s.kind == "benchmark")
    assert all("device=cuda" in s.argv for s in steps if s.kind == "experiment")
    assert sum(s.timeout_s for s in steps if s.kind != "tests") > check.BUDGET_S  # budget caps
    assert check.BUDGET_S + 30 <= 8 * 60  # room for the start and the report


@pytest.mark.slow  # 20 s; a GPU session's tool, its unit checks stay
def test_dry_run_finds_every_step_wired(tmp_path):
    proc = _check(tmp_path, "--dry-run")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = (tmp_path / "gpu_check.md").read_text()
    assert "- GPU: " in report and "torch " in report and "CUDA " in report
    if not torch.cuda.is_available():
        assert "- GPU: no CUDA device" in report
    sections = _sections(report)
    assert len(sections) == len(_load().build_steps("cuda", tiny=False, out=tmp_path))
    assert all(status.startswith("dry run: wired") for status in sections.values()), sections
    kinds = [title.split(":")[0] for title in sections]
    assert (
        kinds.count("benchmark") == len(_load().BENCHMARK_STEPS) == 9
        and kinds.count("experiment") == 4
    ), sections


def test_the_recorded_wall_time_of_each_results_layout():
    """Every experiment kind's ``results.json`` layout gives its seconds; none gives None (an
    online run's used to read as 0.0 s)."""
    wall_time = _load().recorded_wall_time
    assert wall_time({"wall_time_s": {"fit": 1.5, "play": 2.0}}) == 3.5
    assert wall_time({"wall_time_s": 4}) == 4.0
    online = {"first_fit": {"wall_time_s": 1.0}, "iterations": [{"wall_time_s": 2.5}] * 2}
    assert wall_time(online) == 6.0
    assert wall_time({"iterations": []}) is None


def test_a_flag_a_benchmark_lacks_is_reported_unwired():
    check = _load()
    script = BENCHMARKS / "planner_speed.py"
    assert check.accepted_flags(script, ["--horizons", "5", "--device", "cuda"]) == []
    assert check.accepted_flags(script, ["--no-such-flag", "1"]) == ["--no-such-flag"]


@NO_CUDA
@pytest.mark.slow  # 17 s; the dry run and the full-size argv test check the wiring in make test
def test_without_cuda_the_tests_run_and_the_gpu_steps_skip(tmp_path):
    proc = _check(tmp_path, "--device", "cuda")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("no CUDA device"), proc.stdout
    sections = _sections((tmp_path / "gpu_check.md").read_text())
    for title, status in sections.items():
        expected = "passed" if title.startswith("CUDA") else "skipped: no CUDA device"
        assert status == expected, (title, status)
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_every_step_runs_on_the_cpu_at_tiny_sizes(tmp_path):
    """The whole check end to end on the CPU (tiny benchmarks, the smoke recipes)."""
    proc = _check(tmp_path, "--device", "cpu", "--tiny", "--budget-s", "1500")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = (tmp_path / "gpu_check.md").read_text()
    assert set(_sections(report).values()) == {"passed"}, report
    assert "its arithmetic limit" in report and "speed-up" in report
    assert report.count("results.json: device cpu (") == 4, report
    assert report.count("stages' wall time") == 4, report  # online's included
    assert "torch.compile (default) vs eager" in report, report
    assert "torch.compile vs eager, R=3: sequential" in report, report


SETUP_RUNNER = """
import json, os, runpy, sys
sys.path.insert(0, sys.argv[1])
os.environ["TORCHRL_RECON_SETUP_ONLY"] = "1"
for argv in json.loads(sys.argv[2]):
    sys.argv = argv
    try:
        runpy.run_path(argv[0], run_name="__main__")
        print("NO EXIT", argv, flush=True)
    except SystemExit as stop:
        print("EXIT", stop.code, argv, flush=True)
"""


@pytest.mark.slow  # 7 s; as above
def test_every_full_size_benchmark_argv_passes_its_setup_on_the_cpu(tmp_path):
    """Each benchmark step's full-size argv (the GPU check's own), on the CPU, runs to the end of
    its setup (arguments accepted, recipes resolved: ``TORCHRL_RECON_SETUP_ONLY`` stops it
    there), all in one process. Step 9's ``--steps 10`` made the Drone control recipe refuse
    itself here."""
    steps = [s for s in _load().build_steps("cpu", False, tmp_path) if s.kind == "benchmark"]
    argvs = [step.argv[1:] for step in steps]  # [script, *args]
    python = steps[0].argv[0]
    proc = subprocess.run(
        [python, "-c", SETUP_RUNNER, str(BENCHMARKS), json.dumps(argvs)],
        cwd=SCRIPT.parents[1],
        capture_output=True,
        text=True,
        timeout=300,
    )
    ends = [line for line in proc.stdout.splitlines() if line.startswith(("EXIT", "NO EXIT"))]
    assert len(ends) == len(argvs), proc.stdout[-3000:] + proc.stderr[-3000:]
    for line, argv in zip(ends, argvs, strict=True):
        assert line.startswith("EXIT 0 "), f"{argv}: {line}\n{proc.stderr[-3000:]}"
    assert proc.stdout.count("setup done") == len(argvs)


def test_quick_selects_the_planner_and_fit_steps(tmp_path):
    steps = _load().build_steps("cuda", False, tmp_path, quick=True)
    assert [s.kind for s in steps] == ["tests", "benchmark", "benchmark", "benchmark"]
    assert steps[0].argv[-1] == "cuda and (plan or fit)"
    assert all(Path(s.argv[1]).name == "planner_speed.py" for s in steps[1:3])
    assert "--candidates" not in steps[1].argv  # K = 1,000, the script's default
    assert steps[2].argv[steps[2].argv.index("--candidates") + 1] == "10000"
    assert Path(steps[3].argv[1]).name == "training_speed.py"
    assert len(_load().build_steps("cuda", False, tmp_path)) > len(steps)


def test_the_compiled_planner_rows_run_within_their_steps_and_quick_within_its_cap(
    tmp_path, monkeypatch
):
    """The planner steps (whole and quick) time CEM, MPPI and iCEM as one CUDA graph a plan
    with a silent eager fall-back refused, and pass their benchmark the time they have, which
    run_step sets from what is left; ``--quick``'s printed estimate is within its cap (7.5 minutes)."""
    check = _load()
    for quick in (False, True):
        steps = check.build_steps("cuda", False, tmp_path, quick=quick)
        planners = [s for s in steps if Path(s.argv[1]).name == "planner_speed.py"]
        assert len(planners) == 2
        for step in planners:
            assert "--reduce-overhead" in step.argv
            assert step.env == {"TORCHINDUCTOR_CUDAGRAPH_OR_ERROR": "1"}
            limit = step.argv[step.argv.index("--time-limit-s") + 1]
            assert float(limit) == step.timeout_s
        line = check.estimate_line(steps, check.BUDGET_S, quick)
        assert line.startswith("estimated ")
        if quick:
            assert "within the 450 s of --quick" in line, line
    seen = {}

    def run_command(argv, limit, log, env=None):
        seen.update(argv=argv, env=env)
        return 0, ""

    monkeypatch.setattr(check, "run_command", run_command)
    check.run_step(planners[0], tmp_path / "log", left_s=33.0)
    assert seen["argv"][seen["argv"].index("--time-limit-s") + 1] == "23"  # 33 s less START_S
    assert seen["env"] == {"TORCHINDUCTOR_CUDAGRAPH_OR_ERROR": "1"}
