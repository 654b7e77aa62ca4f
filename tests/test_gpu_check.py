"""``make gpu-check`` (benchmarks/gpu_check.py): its CPU-side path runs here, the GPU steps skip."""

from __future__ import annotations

import functools
import io
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
    assert kinds.count("benchmark") == 8 and kinds.count("experiment") == 4, sections


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
