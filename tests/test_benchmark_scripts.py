"""The benchmark scripts run and print their ratios (tiny sizes: this checks they work, not speed)."""

from __future__ import annotations

import functools
import io
import re
import runpy
import sys
from contextlib import redirect_stdout
from pathlib import Path
from unittest import mock

import pytest
import torch

from torchrl_recon.runs.timing import interleaved_median_ms

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"


@functools.cache
def _run(script: str, *args: str) -> str:
    """A script's stdout at one thread, run as ``__main__`` in this process (a subprocess would
    import torch again for each; each script and argument list runs once per session)."""
    argv, out = [str(BENCHMARKS / script), *args, "--threads", "1"], io.StringIO()
    path = [str(BENCHMARKS), *sys.path]  # the scripts import their _common module
    with mock.patch.object(sys, "argv", argv), mock.patch.object(sys, "path", path):
        with redirect_stdout(out):
            runpy.run_path(argv[0], run_name="__main__")
    return out.getvalue()


SPEED_UP = r"speed-up vs [^:]+: ([0-9.]+)x"
LIMIT = r"([0-9.]+)x its arithmetic limit$"
"""The end of each of our rows in the scripts that print how far a call is from its FLOPs."""
TINY_PLANNER = ["--candidates", "20", "--elites", "4", "--horizons", "5", "--repeats", "1"]
TINY_FIT = ["--hidden", "4", "--dense", "4", "--window", "2", "--slice-len", "4", "--windows", "2"]
TINY_FIT += ["--steps", "1", "--repeats", "1", "--members", "1", "3"]
TINY_EPISODES = ["--envs", "2", "--horizon", "5", "--restarts", "2", "--steps", "1"]
TINY_EPISODES += ["--candidates", "8", "--elites", "2", "--iterations", "1", "--repeats", "1"]
TINY_WINDOWS = ["--candidates", "6", "--horizon", "3", "--obs-dim", "3", "--action-dim", "2"]
TINY_WINDOWS += ["--repeats", "1"]
GEMM = r"^GEMM rate \(float32 [^)]+\): ([0-9.]+) GFLOP/s$"


@pytest.mark.parametrize(
    ("script", "args", "pattern", "count"),
    [
        ("gradient_planning.py", ["--rows", "2", "--horizon", "5", "--repeats", "2"], SPEED_UP, 2),
        pytest.param(
            "cpu_blocks.py",
            ["--candidates", "20", "--horizon", "4", "--repeats", "1"],
            r"speed-up +([0-9.]+)x",
            12,  # each way's, each CEM call's, the processes' ceiling
            marks=pytest.mark.slow,  # three compiles: a minute on a cold cache
        ),
        (
            "planner_speed.py",
            TINY_PLANNER,
            SPEED_UP,
            3,
        ),
        (
            "training_speed.py",
            ["--hidden", "4", "--dense", "4", "--window", "2", "--slice-len", "4", "--windows", "2"]
            + ["--steps", "1", "--repeats", "1", "--device", "cpu"],
            r"\Aspeed-up of 20 vectorised retrainings vs sequential: ([0-9.]+)x\Z",
            1,
        ),
        (
            "episode_batching.py",
            TINY_EPISODES,
            r"^speed-up of 2 episodes in one call \((?:gradient|CEM, K=8)\): ([0-9.]+)x$",
            2,
        ),
        pytest.param(  # 8 s: make test-all
            "control_batching.py",
            ["--episodes", "2", "--steps", "11", "--settings", "baseline"],
            r"^speed-up of 2 episodes as one batch \(baseline\): ([0-9.]+)x$",
            1,
            marks=pytest.mark.slow,
        ),
        (
            "window_scoring.py",
            TINY_WINDOWS,
            r"^speed-up vs window copies: ([0-9.]+)x$",
            1,
        ),
        (
            "uncertainty_overhead.py",
            ["--candidates", "20", "--horizons", "12", "--repeats", "2"],
            r"ratio: ([0-9.]+)$",
            1,
        ),
        (
            "torchrl_world_models.py",
            ["--candidates", "8", "--horizon", "3", "--iterations", "1", "--elites", "2"]
            + ["--repeats", "1"],
            r"^speed-up \([^)]+\): ([0-9.]+)x$",
            2,
        ),
    ],
)
def test_benchmark_prints_measured_ratios(script, args, pattern, count):
    out = _run(script, *args)
    if pattern.startswith(r"\A"):  # a pattern of the exact last line
        out = out.strip().splitlines()[-1]
    ratios = re.findall(pattern, out, flags=re.MULTILINE)
    assert len(ratios) >= count and all(float(r) > 0 for r in ratios), out


@pytest.mark.parametrize(
    ("script", "args", "rows"),
    [
        (
            # our seven planners at the one horizon; TorchRL's three rows have no limit
            "planner_speed.py",
            TINY_PLANNER,
            [
                "ours CEM (no u)",
                "ours CEM (with u, beta=0.1)",
                "ours MPPI (no u)",
                "ours MPPI (with u, beta=0.1)",
                "ours iCEM (with u, beta=0.1)",
                "ours random shooting (with u)",
                "ours gradient (with u, 16 restarts x 20 steps)",
            ],
        ),
        (
            "training_speed.py",
            TINY_FIT,
            [
                f"R={r:3d}  {way}"
                for r in (1, 3)
                for way in ("sequential", "population", "population, shared_sampling")
            ],
        ),
        (
            "episode_batching.py",
            TINY_EPISODES,
            ["gradient:", "CEM, K=8:"],
        ),
    ],
)
def test_benchmark_prints_each_rows_arithmetic_limit(script, args, rows):
    """The GEMM rate of this run above the table, and every one of our rows ending in its
    multiple of the arithmetic limit (``N.Nx its arithmetic limit``)."""
    out = _run(script, *args)
    lines = out.splitlines()
    gemm = [i for i, line in enumerate(lines) if re.match(GEMM, line)]
    assert len(gemm) == 1 and float(re.match(GEMM, lines[gemm[0]])[1]) > 0, out
    for row in rows:
        found = [line for line in lines if re.match(rf"\s*{re.escape(row)}(?![,\w])", line)]
        assert len(found) == 1, (row, out)
        multiple = re.search(LIMIT, found[0])
        assert multiple and float(multiple[1]) > 0, (row, out)
        assert lines.index(found[0]) > gemm[0], (row, out)  # the rate is printed above the table
    assert sum(bool(re.search(LIMIT, line)) for line in lines) == len(rows), out


def test_window_scoring_prints_its_arithmetic_limit():
    out = _run("window_scoring.py", *TINY_WINDOWS)
    assert re.search(GEMM, out, flags=re.MULTILINE), out
    line = re.search(r"^arithmetic limit of score_sequence: .*$", out, flags=re.MULTILINE)
    assert line and float(re.search(LIMIT, line[0])[1]) > 0, out


def test_interleaved_timer_refuses_zero_repeats():
    with pytest.raises(ValueError, match="repeats must be at least 1, got 0"):
        interleaved_median_ms({"a": lambda: None}, 0)


def test_planner_quality_prints_each_planners_cost_and_the_difference_from_cem():
    out = _run(
        "planner_quality.py",
        *["--envs", "drone", "--frames", "600", "--fit-steps", "2", "--contexts", "3"],
        *["--candidates", "16", "--iterations", "2", "--horizon", "4", "--seeds", "2"],
    )
    for label in ("random shooting", "CEM", "MPPI", "iCEM"):
        assert re.search(rf"^\s+{label}\s+mean predicted cost\s+-?[0-9.]+", out, re.M), out
    assert len(re.findall(r"vs CEM\s+[+-][0-9.]+ ± [0-9.]+$", out, re.M)) == 2, out


TINY_FLOOR = ["--candidates", "20", "--elites", "4", "--horizon", "5", "--repeats", "1"]
TINY_FLOOR += ["--members", "3", "--hidden", "4", "--dense", "4", "--window", "2"]
TINY_FLOOR += ["--slice-len", "4", "--windows", "2"]
FLOOR_ROW = r"^\s+{}\s+[0-9.]+ ms   GEMM floor\s+([0-9.]+) ms \((\d+) products\)   limit\s+[0-9.]+ ms   floor ([0-9.]+)x its arithmetic limit$"


def test_gemm_floor_prints_each_rows_floor_and_what_the_target_leaves():
    out = _run("gemm_floor.py", *TINY_FLOOR)
    lines = out.splitlines()
    assert re.match(GEMM, lines[2]), out
    products = {}
    for row in ("CEM (no u)", "CEM (with u, beta=0.1)", "population fit step"):
        found = [
            i for i, line in enumerate(lines) if re.match(FLOOR_ROW.format(re.escape(row)), line)
        ]
        assert len(found) == 1, (row, out)
        floor, count, multiple = re.match(
            FLOOR_ROW.format(re.escape(row)), lines[found[0]]
        ).groups()
        assert float(floor) > 0 and float(multiple) > 0, (row, out)
        products[row] = int(count)
        room = r"^\s+target [0-9.]+x = [0-9.]+ ms leaves -?[0-9.]+ ms for the rest \(now -?[0-9.]+ ms\)$"
        assert re.match(room, lines[found[0] + 1]), (row, out)
    # 5 iterations x 5 steps of at least the gate, dense and head products; u adds its own
    assert products["CEM (no u)"] >= 75, out
    assert products["CEM (with u, beta=0.1)"] > products["CEM (no u)"], out
    assert products["population fit step"] > 0, out


def test_gemm_floor_counts_backward_and_out_products():
    """The recorder sees the products autograd's backward makes and ``out=`` forms."""
    with mock.patch.object(sys, "path", [str(BENCHMARKS), *sys.path]):
        import gemm_floor
    a, b = torch.randn(4, 3, requires_grad=True), torch.randn(3, 5, requires_grad=True)
    with gemm_floor.MatmulRecorder() as recorder:
        (a @ b).sum().backward()  # one product forward, two backward
        torch.mm(a.detach(), b.detach(), out=torch.empty(4, 5))
        torch.add(a, 1)  # not a product
    assert sum(recorder.calls.values()) == 4
    ms, count = gemm_floor.gemm_floor_ms(recorder.calls, torch.device("cpu"), repeats=1, inner=2)
    assert count == 4 and ms > 0


@pytest.mark.parametrize("threads", ["2", "16"])
def test_cpu_blocks_accepts_make_cpu_cores_arguments(threads, monkeypatch):
    """``make cpu-cores``' arguments reach the end of cpu_blocks' setup (its full run compiles
    three graphs: in the slow set, above)."""
    monkeypatch.setenv("TORCHRL_RECON_SETUP_ONLY", "1")
    with pytest.raises(SystemExit) as stop:
        _run("cpu_blocks.py", "--block-threads", threads, "--repeats", "10")
    assert stop.value.code == 0


def test_code_shape_prints_each_measure_with_its_target_and_measures_a_body():
    """Issue 59's measures come from the source: nine lines ``name: value (target <= n)``, and a
    function body's length leaves its docstring out."""
    import ast

    with mock.patch.object(sys, "argv", [str(BENCHMARKS / "code_shape.py")]):
        out = io.StringIO()
        with redirect_stdout(out):
            shape = runpy.run_path(str(BENCHMARKS / "code_shape.py"), run_name="__main__")
    lines = out.getvalue().splitlines()
    assert len(lines) == 9 and all(re.fullmatch(r".+: \d+ \(target <= \d+\)", s) for s in lines)
    source = 'def f():\n    """Doc\n    string."""\n    a = 1\n    return a\n'
    assert shape["body_lines"](ast.parse(source).body[0]) == 2
    # "in code" leaves out docstrings, comments and strings, not the code beside them
    code = shape["code_only"]('"""torch.compile"""\nx = torch.compile(f)  # torch.compile\n')
    assert code.count("torch.compile") == 1 and len(code.splitlines()) == 2
