"""The benchmark scripts run and print their ratios (tiny sizes: this checks they work, not speed)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"


@pytest.mark.parametrize(
    ("script", "args"),
    [
        ("gradient_planning.py", ["--rows", "2", "--horizon", "5", "--repeats", "2"]),
        (
            "planner_speed.py",
            ["--candidates", "20", "--elites", "4", "--horizons", "5", "--repeats", "1"],
        ),
    ],
)
def test_benchmark_prints_measured_speed_ups(script, args):
    out = subprocess.run(
        [sys.executable, script, *args, "--threads", "1"],
        cwd=BENCHMARKS,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    ).stdout
    ratios = re.findall(r"speed-up vs [^:]+: ([0-9.]+)x", out)
    assert len(ratios) >= 2 and all(float(r) > 0 for r in ratios), out
