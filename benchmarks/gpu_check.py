"""One command for a GPU machine: the CUDA tests, every benchmark and a smoke run of each
experiment kind on the GPU, and one report with the GPU's name and every step's figures.

Run (``make gpu-check`` does the first)::

    python benchmarks/gpu_check.py --out outputs/gpu_check
    python benchmarks/gpu_check.py --out /tmp/check --dry-run           # wiring only, no GPU needed
    python benchmarks/gpu_check.py --out /tmp/check --device cpu --tiny # every step, tiny, on the CPU
    python benchmarks/gpu_check.py --out /tmp/check --steps 1 10 11     # only these steps
    python benchmarks/gpu_check.py --out /tmp/check --quick             # planners and fits only

Steps, in this order (each a subprocess with its own time limit; all of them together within
``--budget-s``, 450 s by default, so the whole check stays under 8 minutes: a step whose turn
comes when less than ``MIN_STEP_S`` is left is reported as not run):

1. the CUDA tests of ``tests/test_device.py`` and ``tests/planners/test_compiled_plans.py``
   (``pytest -k cuda``: the tests that skip without a GPU);
2. the benchmarks with ``--device cuda``: planners against TorchRL's CEMPlanner on the same
   GPU (with ``--compile``: our CEM rows under ``torch.compile`` against eager, in the same
   run; with ``--reduce-overhead``: CEM, MPPI and iCEM each plan one CUDA graph, with
   ``TORCHINDUCTOR_CUDAGRAPH_OR_ERROR=1``, compiled while the step's time allows: the step
   passes its time left as ``--time-limit-s``, and a row whose compile would not fit is left
   out with a line saying so), the same at K = 10,000 candidates (1,000 elites), population fits (with
   ``--compile``: the fits with ``compile=True`` against eager; with ``--cuda-graph``: the
   shared fit with each step one replayed CUDA graph, and its sampling alone),
   episode batching, window scoring, uncertainty overhead, gradient planning and control
   batching;
3. a smoke run of each experiment kind with ``device=cuda``: ``explore``, ``control``,
   ``calibrate`` and ``online`` on the Industrial Benchmark smoke recipes;
4. the CUDA smoke-recipe tests of the other environments (``tests/experiments/test_recipes.py
   -k "cuda and not industrial_benchmark"``; IB's are step 3).

The report, ``<out>/gpu_check.md``, gives the GPU's name (``torch.cuda.get_device_name``),
the torch / CUDA / cuDNN / torchrl versions, and for each step its command, exit status, wall
time and printed figures; each step's whole output is in ``<out>/logs/``, the experiments'
run directories in ``<out>/runs/``. Without a CUDA device the report says "no CUDA device":
the test steps still run (their CUDA tests skip) and the GPU steps are reported as skipped.
``--quick`` runs the planners' and fits' CUDA tests, the planner rows at K = 1,000 and 10,000
(eager and reduce-overhead) and the fit rows (eager and CUDA graph), to iterate on a GPU, in
7.5 minutes by the estimate it prints first (each step's expected time on an H200, measured where
a run measured it, else its time limit; the whole check prints its own). ``--dry-run`` runs nothing heavy: it checks that every step is wired (the tests are
collected, each benchmark script accepts the flags passed to it, each recipe resolves with
its overrides) and writes the report with every section. Exit status: 0 when no step failed,
timed out or was found unwired, else 1.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchrl_recon.runs.provenance import git_info

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
BUDGET_S = 450
"""The whole check's time, in seconds (under the 8 minutes it is meant to take on one GPU)."""
MIN_STEP_S = 20
"""A step is not started with less than this left of the budget."""
NOISE = re.compile(r"\[torchrl\]\[INFO\]|^\s*$")


@dataclass
class Step:
    """One step of the check: a command, the time it may take and what its report shows."""

    name: str
    kind: str  # "tests", "benchmark" or "experiment"
    argv: list[str]
    timeout_s: int
    needs_cuda: bool = True
    tail: int = 40  # last lines of stdout shown as its figures
    recipe: str | None = None  # experiments: the recipe name
    overrides: list[str] = field(default_factory=list)  # experiments: key=value overrides
    run_dir: Path | None = None  # experiments: the run directory
    env: dict[str, str] = field(default_factory=dict)  # set in the step's environment
    estimate_s: float | None = None  # its expected wall time on an H200 (None: its timeout)
    status: str = "not run"
    exit_code: int | None = None
    wall_s: float | None = None
    figures: list[str] = field(default_factory=list)


def benchmark(
    name: str,
    script: str,
    timeout_s: int,
    full: list[str],
    tiny: list[str],
    *,
    estimate_s: float | None = None,
    quick: tuple[int, list[str]] | None = None,
    env: dict[str, str] | None = None,
):
    """A benchmark step's ``(name, script, timeout, full-size args, tiny args, options)``;
    options: its expected wall time on an H200 (``estimate_s``; None: its timeout), its
    ``--quick`` timeout and args (None: as the full check's), environment variables."""
    options = {"estimate_s": estimate_s, "quick": quick, "env": env or {}}
    return name, script, timeout_s, full, tiny, options


GRAPHS_OR_ERROR = {"TORCHINDUCTOR_CUDAGRAPH_OR_ERROR": "1"}
"""The compiled planner rows' environment: a graph that cannot be a CUDA graph fails its row
instead of running eagerly."""
TIME_LIMIT = "--time-limit-s"
"""A benchmark's own time limit: :func:`run_step` sets it to the time its step has (less
``START_S``), so that the benchmark leaves out a compiled row it has no time for."""
START_S = 10
"""Seconds of a step's time kept for its interpreter's start and exit."""
QUICK_S = 450
"""``--quick``'s estimate must stay within this (7.5 minutes: its CUDA tests alone ran past 120 s
on an H200 with cold compile caches, fourth run)."""


BENCHMARK_STEPS = [
    benchmark(
        "planners vs TorchRL's CEMPlanner (eager, torch.compile, reduce-overhead)",
        "planner_speed.py",
        150,
        # H=200: episode batching. The reduce-overhead rows (CEM, MPPI, iCEM with u, each
        # plan one CUDA graph) compile while the step's time allows (planner_speed.py's
        # --time-limit-s, set by run_step): 47.9 s on an H200 without them
        ["--horizons", "30", "--repeats", "5", "--compile", "--reduce-overhead"]
        + [TIME_LIMIT, "150"],
        ["--candidates", "20", "--elites", "4", "--horizons", "5", "--repeats", "1", "--compile"]
        + ["--reduce-overhead"],
        estimate_s=150,  # its limit: the compiles' time on a GPU is not measured yet
        # quick: 120 s, so that the first reduce-overhead compile (assumed 90 s) fits after the
        # eager rows (at 60 s the fourth run left all three out)
        quick=(120, ["--horizons", "30", "--repeats", "3", "--reduce-overhead", TIME_LIMIT, "120"]),
        env=GRAPHS_OR_ERROR,
    ),
    benchmark(
        "planners at K = 10,000 (1,000 elites) vs TorchRL's CEMPlanner (eager, reduce-overhead)",
        "planner_speed.py",
        120,
        ["--candidates", "10000", "--elites", "1000", "--horizons", "30", "--repeats", "3"]
        + ["--reduce-overhead", TIME_LIMIT, "120"],
        ["--candidates", "40", "--elites", "4", "--horizons", "5", "--repeats", "1"]
        + ["--reduce-overhead"],
        estimate_s=120,  # its limit, as above
        quick=(
            45,
            ["--candidates", "10000", "--elites", "1000", "--horizons", "30", "--repeats", "2"]
            + ["--reduce-overhead", TIME_LIMIT, "45"],
        ),
        env=GRAPHS_OR_ERROR,
    ),
    benchmark(
        "population fits (eager, torch.compile and CUDA graph)",
        "training_speed.py",
        150,
        # R = 1 and the sequential compile left out for time: 136 s with both on an H200
        ["--members", "20", "--steps", "5", "--compile", "shared", "--cuda-graph"],
        ["--hidden", "4", "--dense", "4", "--window", "2", "--slice-len", "4", "--windows", "2"]
        + ["--steps", "1", "--repeats", "1", "--members", "3", "--compile"],
        # 136.4 s before the cut, which left out the sequential compile (39.4 s) and its rows
        # (~14 s) and halved the eager rows' steps
        estimate_s=60,
        # quick: the eager and CUDA-graph rows (the compiled fit is the full check's)
        quick=(30, ["--members", "20", "--steps", "5", "--repeats", "2", "--cuda-graph"]),
    ),
    benchmark(
        "episode batching",
        "episode_batching.py",
        90,
        ["--steps", "5", "--repeats", "2"],  # 65 s at 10 steps on an H200
        ["--envs", "2", "--horizon", "5", "--restarts", "2", "--steps", "1"]
        + ["--candidates", "8", "--elites", "2", "--iterations", "1", "--repeats", "1"],
        estimate_s=41,  # 40.7 s on an H200 (third run)
    ),
    benchmark(
        "window scoring",
        "window_scoring.py",
        45,
        [],
        ["--candidates", "6", "--horizon", "3", "--obs-dim", "3", "--action-dim", "2"]
        + ["--repeats", "1"],
        estimate_s=10,  # 9.9 s
    ),
    benchmark(
        "uncertainty overhead",
        "uncertainty_overhead.py",
        45,
        [],
        ["--candidates", "20", "--horizons", "12", "--repeats", "2"],
        estimate_s=10,  # 10.1 s
    ),
    benchmark(
        "gradient planning",
        "gradient_planning.py",
        60,
        ["--repeats", "5"],
        ["--rows", "2", "--horizon", "5", "--repeats", "2"],
        estimate_s=17,  # 17.3 s
    ),
    benchmark(
        "planner quality at equal budget (shooting, CEM, MPPI, iCEM)",
        "planner_quality.py",
        60,
        ["--envs", "industrial_benchmark", "drone", "--fit-steps", "200", "--seeds", "2"],
        ["--envs", "drone", "--frames", "600", "--fit-steps", "2", "--contexts", "3"]
        + ["--candidates", "16", "--iterations", "2", "--horizon", "4", "--seeds", "1"],
        estimate_s=28,  # 28.2 s
    ),
    benchmark(
        "control batching",
        "control_batching.py",
        90,
        # one plan per episode (10 random warm-up steps first; 10 made the recipe refuse
        # itself): 75 s at 20 steps on an H200
        ["--steps", "11"],
        ["--episodes", "2", "--steps", "11", "--settings", "baseline"],
        estimate_s=50,  # 74.8 s at 20 steps, its gradient row 51.3 s of it; now one plan each
    ),
]
EXPERIMENT_KINDS = ("explore", "control", "calibrate", "online")
EXTRA_OVERRIDES = {"calibrate": ["outcomes.control_recipe=null", "outcomes.explore_recipe=null"]}


def has_pybullet() -> bool:
    """Whether pybullet imports (Minitaur's physics; a GPU image may lack it, and its CUDA smoke
    tests are then left out of the last step, as the report's header says)."""
    try:
        import pybullet  # noqa: F401
    except ImportError:
        return False
    return True


QUICK_SCRIPTS = ("planner_speed.py", "training_speed.py")
"""The benchmarks of ``--quick``: the planner rows (K = 1,000 and 10,000) and the fit rows."""
CUDA_TEST_FILES = ("tests/test_device.py", "tests/planners/test_compiled_plans.py")
"""The files of the first step's CUDA tests (the tests that skip without a GPU): the device
tests and the compiled planners' plans in a row as CUDA graphs."""
QUICK_TESTS = "cuda and (plan or fit)"
"""The CUDA tests of ``--quick``: the planners' and the fits'."""


def build_steps(device: str, tiny: bool, out: Path, quick: bool = False) -> list[Step]:
    """Every step of the check, in order, for ``device`` (``cuda``, ``cuda:N`` or ``cpu``);
    ``quick``: the planners' and fits' CUDA tests and the benchmarks of :data:`QUICK_SCRIPTS`."""
    python = sys.executable
    pytest = [python, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider"]
    selection = QUICK_TESTS if quick else "cuda"
    steps = [
        Step(
            f'CUDA tests ({" ".join(CUDA_TEST_FILES)} -k "{selection}")',
            "tests",
            pytest + [*CUDA_TEST_FILES, "-k", selection],
            240 if quick else 300,
            needs_cuda=False,
            tail=15,
            # fourth run (H200): quick's timed out at 120 s compiling the reduce-overhead test
            # (49 of 55 passed; cold caches), the whole's at 180 s on 80 of 82 (warm caches);
            # the third run's 72.6 s predates tests/planners/test_compiled_plans.py
            estimate_s=240 if quick else 300,
        )
    ]
    for name, script, timeout_s, full, small, options in BENCHMARK_STEPS:
        if quick and script not in QUICK_SCRIPTS:
            continue
        estimate_s = options["estimate_s"]
        if quick and options["quick"] is not None:
            timeout_s, full = options["quick"]
            estimate_s = timeout_s
        args = small if tiny else full
        argv = [python, str(BENCHMARKS / script), *args, "--device", device]
        step = Step(f"benchmark: {name} ({script})", "benchmark", argv, timeout_s)
        step.env, step.estimate_s = options["env"], estimate_s
        steps.append(step)
    if quick:
        return steps
    for kind in EXPERIMENT_KINDS:
        recipe = f"industrial_benchmark/{kind}_smoke"
        run_dir = out / "runs" / kind
        overrides = [f"device={device}", f"output_dir={run_dir}", "progress=false"]
        overrides += EXTRA_OVERRIDES.get(kind, [])
        argv = [python, "-m", "torchrl_recon.cli", kind, recipe, *overrides]
        steps.append(
            Step(
                f"experiment: {kind} smoke run ({recipe})",
                "experiment",
                argv,
                150 if kind == "calibrate" else 90,
                tail=15,
                recipe=recipe,
                overrides=overrides,
                run_dir=run_dir,
                estimate_s=20,  # 16-19 s each on an H200 (third run)
            )
        )
    selection = "cuda and not industrial_benchmark" + " and not minitaur" * (not has_pybullet())
    steps.append(
        Step(
            f'CUDA smoke-recipe tests, other envs (tests/experiments/test_recipes.py -k "{selection}")',
            "tests",
            pytest + ["tests/experiments/test_recipes.py", "-k", selection],
            300,
            needs_cuda=False,
            tail=15,
            estimate_s=30,  # 29.1 s (third run, without the Minitaur's)
        )
    )
    return steps


def estimate_line(steps: list[Step], budget_s: float, quick: bool = False) -> str:
    """The line the check prints first: its estimated time (each step's ``estimate_s``, else its
    timeout) against the budget, and for ``--quick`` against :data:`QUICK_S`."""
    total = sum(s.timeout_s if s.estimate_s is None else s.estimate_s for s in steps)
    cap = min(budget_s, QUICK_S) if quick else budget_s
    verdict = "within" if total <= cap else "over"
    line = f"estimated {total:.0f} s for {len(steps)} steps on an H200, {verdict} the {cap:.0f} s"
    line += " of --quick" if quick and cap == QUICK_S else " budget"
    if verdict == "over":
        line += ": the steps whose turn comes when the budget is spent are reported as not run"
    return line


# ----------------------------------------------------------------------------------------------
# Running a step


def run_command(
    argv: list[str], timeout_s: float, log: Path, env: dict[str, str] | None = None
) -> tuple[int | None, str]:
    """Run ``argv`` in the repository root, with ``env`` added to the environment; ``(exit
    code or None on timeout, stdout)``.

    The whole process group is killed at the timeout; stdout and stderr go to ``log``.
    """
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    proc = subprocess.Popen(
        argv,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=timeout_s)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        code = None
    log.write_text(f"$ {' '.join(argv)}\n\n--- stdout\n{out}\n--- stderr\n{err}")
    return code, out + ("" if code == 0 else err)


def figures_of(step: Step, output: str) -> list[str]:
    """The lines a step's report shows: its last ``tail`` lines of output, log noise left out."""
    lines = [line for line in output.splitlines() if not NOISE.search(line)]
    shown = lines[-step.tail :]
    if step.kind == "experiment" and step.exit_code == 0:
        results = step.run_dir / "results.json"
        if results.is_file():
            data = json.loads(results.read_text())
            device = data.get("meta", {}).get("device", {})
            line = f"results.json: device {device.get('device')} ({device.get('name')})"
            total = recorded_wall_time(data)
            shown.append(line + ("" if total is None else f", stages' wall time {total:.1f} s"))
    return shown


def recorded_wall_time(results: dict) -> float | None:
    """The seconds a run's ``results.json`` records for its stages, or None where it has none.

    explore, control and calibrate keep ``wall_time_s`` at the top (a number or one per stage);
    online keeps one in ``first_fit`` and one in each of its ``iterations``.

    >>> recorded_wall_time({"first_fit": {"wall_time_s": 1.0}, "iterations": [{"wall_time_s": 2.5}]})
    3.5
    """
    stages = results.get("wall_time_s")
    if isinstance(stages, dict):
        return float(sum(stages.values()))
    if isinstance(stages, int | float):
        return float(stages)
    parts = [results.get("first_fit", {}), *results.get("iterations", [])]
    seconds = [p["wall_time_s"] for p in parts if isinstance(p, dict) and "wall_time_s" in p]
    return float(sum(seconds)) if seconds else None


def accepted_flags(script: Path, argv: list[str]) -> list[str]:
    """The ``--flags`` of ``argv`` that ``script``'s source does not define (empty: all wired)."""
    source = script.read_text()
    device = "parse_device_args" in source or "add_device_argument" in source
    missing = []
    for arg in argv:
        if arg.startswith("--") and f'"{arg}"' not in source:
            if not (arg == "--device" and device):
                missing.append(arg)
    return missing


def dry_run(step: Step, log: Path) -> None:
    """Check that ``step`` is wired without running it; set its status."""
    start = time.perf_counter()
    if step.kind == "tests":
        argv = [*step.argv, "--collect-only"]
        code, out = run_command(argv, step.timeout_s, log)
        found = re.search(r"(\d+)(?:/\d+)? tests? collected", out)
        count = int(found[1]) if found else 0
        wired = code == 0 and count > 0
        step.status = f"dry run: {'wired' if wired else 'NOT wired'} ({count} tests collected)"
        step.figures = [line for line in out.splitlines() if "collected" in line][-1:]
    elif step.kind == "benchmark":
        script = Path(step.argv[1])
        missing = accepted_flags(script, step.argv[2:]) if script.is_file() else ["script"]
        if not missing:
            compile(script.read_text(), str(script), "exec")  # a syntax error fails the check
        step.status = "dry run: wired (script and flags found)"
        if missing:
            step.status = f"dry run: NOT wired ({script.name} lacks {', '.join(missing)})"
    else:
        from torchrl_recon.experiments.recipe import load_recipe, resolve_recipe_path

        try:
            cfg = load_recipe(resolve_recipe_path(step.recipe), step.overrides)
            step.status = f"dry run: wired (recipe resolves, device={cfg.device})"
        except Exception as error:  # noqa: BLE001 - reported in the step's line
            step.status = f"dry run: NOT wired ({type(error).__name__}: {error})"
    step.wall_s = time.perf_counter() - start


def run_step(step: Step, log: Path, left_s: float) -> None:
    """Run ``step`` within ``min(its timeout, left_s)`` seconds; set its status and figures."""
    limit = min(step.timeout_s, left_s)
    argv = list(step.argv)
    if TIME_LIMIT in argv:  # the benchmark's own limit: the time this step has
        argv[argv.index(TIME_LIMIT) + 1] = f"{max(limit - START_S, 1):.0f}"
    start = time.perf_counter()
    code, out = run_command(argv, limit, log, step.env)
    step.wall_s = time.perf_counter() - start
    step.exit_code = code
    if code is None:
        step.status = f"timed out after {limit:.0f} s"
    else:
        step.status = "passed" if code == 0 else f"failed (exit {code})"
    step.figures = figures_of(step, out)


# ----------------------------------------------------------------------------------------------
# The report


def machine_lines(device: str) -> list[str]:
    """The report's header: GPU name (or "no CUDA device"), versions, host, commit."""
    import torchrl

    cuda = torch.cuda.is_available()
    if cuda:
        index = (torch.device(device).index or 0) if device.startswith("cuda") else 0
        props = torch.cuda.get_device_properties(index)
        gpu = (
            f"{torch.cuda.get_device_name(index)} ({props.total_memory / 2**30:.0f} GiB, "
            f"compute capability {props.major}.{props.minor}, {torch.cuda.device_count()} visible)"
        )
    else:
        gpu = "no CUDA device (torch.cuda.is_available() is False)"
    lines = [
        f"- GPU: {gpu}",
        f"- torch {torch.__version__}, CUDA {torch.version.cuda or 'none'}, cuDNN "
        f"{torch.backends.cudnn.version() if cuda else 'n/a'}, torchrl {torchrl.__version__}, "
        f"Python {platform.python_version()}",
        f"- host: {platform.node()}, {os.cpu_count()} CPUs, {platform.processor() or platform.machine()}",
    ]
    if not has_pybullet():
        lines.append("- pybullet is not installed: Minitaur's CUDA smoke tests were left out")
    smi = shutil.which("nvidia-smi")
    if smi:
        query = [smi, "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"]
        done = subprocess.run(query, capture_output=True, text=True, timeout=30)
        if done.returncode == 0:
            lines.append(f"- nvidia-smi: {done.stdout.strip()}")
    git = git_info(ROOT)
    if git["commit"] != "unknown":
        lines.append(
            f"- commit: {git['commit'][:7]}" + (" (uncommitted changes)" * bool(git["dirty"]))
        )
    return lines


def shown_command(argv: list[str]) -> str:
    """``argv`` as the report shows it: ``python`` for this interpreter, paths from the root."""
    parts = ["python" if arg == sys.executable else arg.replace(f"{ROOT}/", "") for arg in argv]
    return shlex.join(parts)


def write_report(path: Path, header: list[str], steps: list[Step], mode: str, wall_s: float):
    """Write the markdown report: machine, a summary table, then one section per step."""
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = ["# gpu-check report", "", f"{stamp}, mode: {mode}, total {wall_s:.0f} s", ""]
    lines += [*header, "", "| # | step | status | wall s |", "|---:|---|---|---:|"]
    for i, step in enumerate(steps, 1):
        wall = "" if step.wall_s is None else f"{step.wall_s:.1f}"
        lines.append(f"| {i} | {step.name} | {step.status} | {wall} |")
    for i, step in enumerate(steps, 1):
        lines += ["", f"## {i}. {step.name}", "", "```", shown_command(step.argv), "```", ""]
        exit_code = "none" if step.exit_code is None else str(step.exit_code)
        lines += [f"status: {step.status}; exit status: {exit_code}", ""]
        if step.figures:
            lines += ["```", *step.figures, "```"]
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the report and logs")
    parser.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu (default cuda)")
    parser.add_argument("--tiny", action="store_true", help="the benchmarks at tiny sizes")
    parser.add_argument("--dry-run", action="store_true", help="check the wiring, run nothing")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="only the planners' and fits' CUDA tests and benchmarks (within 7.5 minutes)",
    )
    parser.add_argument("--budget-s", type=float, default=BUDGET_S, help="the whole check's time")
    parser.add_argument(
        "--steps", type=int, nargs="+", help="run only these steps (numbers as in the report)"
    )
    args = parser.parse_args(argv)
    if not re.fullmatch(r"cpu|cuda(:\d+)?", args.device):
        parser.error(f"--device must be cpu, cuda or cuda:N, got {args.device!r}")
    out = args.out.resolve()
    (out / "logs").mkdir(parents=True, exist_ok=True)
    cuda = torch.cuda.is_available()
    gpu_missing = args.device.startswith("cuda") and not cuda
    if gpu_missing:
        print(
            "no CUDA device: the test steps run (their CUDA tests skip), the GPU steps are skipped"
        )
    steps = build_steps(args.device, args.tiny, out, quick=args.quick)
    print(estimate_line(steps, args.budget_s, args.quick), flush=True)
    mode = "dry run" if args.dry_run else ("tiny" if args.tiny else "full")
    mode += ", quick" if args.quick else ""
    report, header = out / "gpu_check.md", machine_lines(args.device)
    start = time.perf_counter()
    for i, step in enumerate(steps, 1):
        log = out / "logs" / f"{i:02d}_{re.sub(r'[^a-z0-9]+', '_', step.name.lower())[:40]}.log"
        left = args.budget_s - (time.perf_counter() - start)
        if args.steps and i not in args.steps:
            step.status = "not selected (--steps)"
        elif args.dry_run:
            dry_run(step, log)
        elif step.needs_cuda and gpu_missing:
            step.status = "skipped: no CUDA device"
        elif left < MIN_STEP_S:
            step.status = f"not run: the {args.budget_s:.0f} s budget was spent"
        else:
            run_step(step, log, left)
        print(f"[{i}/{len(steps)}] {step.name}: {step.status}", flush=True)
        # written after every step: a check stopped from outside keeps what it measured
        write_report(report, header, steps, mode, time.perf_counter() - start)
    print(f"report: {report}")
    bad = ("failed", "timed out", "dry run: NOT wired")
    return 1 if any(step.status.startswith(bad) for step in steps) else 0


if __name__ == "__main__":
    sys.exit(main())
