"""The benchmark scripts run and print their ratios (tiny sizes: this checks they work, not speed)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_recon.timing import interleaved_median_ms

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"


SPEED_UP = r"speed-up vs [^:]+: ([0-9.]+)x"


@pytest.mark.parametrize(
    ("script", "args", "pattern", "count"),
    [
        ("gradient_planning.py", ["--rows", "2", "--horizon", "5", "--repeats", "2"], SPEED_UP, 2),
        (
            "planner_speed.py",
            ["--candidates", "20", "--elites", "4", "--horizons", "5", "--repeats", "1"],
            SPEED_UP,
            2,
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
            ["--envs", "2", "--horizon", "5", "--restarts", "2", "--steps", "1"]
            + ["--candidates", "8", "--elites", "2", "--iterations", "1", "--repeats", "1"],
            r"^speed-up of 2 episodes in one call \((?:gradient|CEM, K=8)\): ([0-9.]+)x$",
            2,
        ),
        (
            "control_batching.py",
            ["--episodes", "2", "--steps", "11", "--settings", "baseline"],
            r"^speed-up of 2 episodes as one batch \(baseline\): ([0-9.]+)x$",
            1,
        ),
        (
            "window_scoring.py",
            ["--candidates", "6", "--horizon", "3", "--obs-dim", "3", "--action-dim", "2"]
            + ["--repeats", "1"],
            r"^speed-up vs window copies: ([0-9.]+)x$",
            1,
        ),
        (
            "uncertainty_overhead.py",
            ["--candidates", "20", "--horizons", "12", "--repeats", "2"],
            r"ratio: ([0-9.]+)$",
            1,
        ),
    ],
)
def test_benchmark_prints_measured_ratios(script, args, pattern, count):
    out = subprocess.run(
        [sys.executable, script, *args, "--threads", "1"],
        cwd=BENCHMARKS,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    ).stdout
    if pattern.startswith(r"\A"):  # a pattern of the exact last line
        out = out.strip().splitlines()[-1]
    ratios = re.findall(pattern, out, flags=re.MULTILINE)
    assert len(ratios) >= count and all(float(r) > 0 for r in ratios), out


def test_interleaved_timer_refuses_zero_repeats():
    with pytest.raises(ValueError, match="repeats must be at least 1, got 0"):
        interleaved_median_ms({"a": lambda: None}, 0)
