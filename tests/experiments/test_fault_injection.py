"""Fault injection: kill smoke runs and resume them; damage finished runs and expect a refusal.

Kills: a smoke run is stopped with SIGKILL at a stage boundary or mid-stage, then the same
command is run again in a fresh process. The resumed run directory must hold the same data as an
uninterrupted run (docs/experiments.md, "Stop and resume"): ``results.json`` equal number for
number (``meta`` and ``wall_time_s`` aside), every buffer, checkpoint, RNG state and figure equal
byte for byte, every stage record equal but for its wall time. Stages last tenths of a second,
so where a kill lands is racy: each test records it (the ``kill_landed`` user property, also
printed: ``-rP`` shows it) and asserts only what must hold wherever it lands.

Kill points, for every stage of the recipe:

- ``boundary``: as soon as the stage's record ``stages/<stage>.json`` appears;
- ``mid``: half way through the stage: after the previous stage's record (or ``meta.json`` for
  the first stage), once the process has spent half the CPU time the stage took in the
  reference run;
- ``writing``: as soon as the stage's first output appears (its buffer folder, checkpoint,
  first ``part_<i>.json`` or RNG state), before its record.

The whole file is ``slow`` (its reference runs and kill chains took 70 s of make test's time;
``test_cli_errors`` kills and resumes a run in make test): ``make test-faults``
(``pytest tests/experiments/test_fault_injection.py``) and ``make test-all`` run it.

Damage: each kind of file of a finished control run is truncated, garbled or deleted and the
same command run again. The run must refuse with one ``error:`` line naming the file (exit code
2, no traceback) and change nothing. Those tests wait for the integrity checks: see
:data:`INTEGRITY_CHECKS_MERGED`.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import pytest
import yaml

from torchrl_recon.experiments.batching import batches
from torchrl_recon.experiments.compose import compose_recipe
from torchrl_recon.experiments.registry import get_type

pytestmark = pytest.mark.slow
INTEGRITY_CHECKS_MERGED = True
"""Set to True once run directories check their files: the damaged-file tests then must pass."""

NEEDS_INTEGRITY = (
    []
    if INTEGRITY_CHECKS_MERGED
    else [pytest.mark.xfail(reason="needs integrity checks", strict=False)]
)

REPO = Path(__file__).resolve().parents[2]
RECIPES = {
    "explore": REPO / "recipes" / "industrial_benchmark" / "explore_smoke.yaml",
    "control": REPO / "recipes" / "industrial_benchmark" / "control_smoke.yaml",
}
RUN_TIMEOUT_S = 300
POLL_S = 0.002
# Files that are not run data: the run lock, Hydra's job log, the per-start provenance.
NOT_DATA = {".lock", "explore.log", "control.log", "meta.json"}


def expected_stages(kind: str) -> list[str]:
    """The stages of a smoke recipe in the order they run.

    Control: the registry's ``stage_list``. Explore: written out here from the recipe's rounds
    of guided data (a refit after each but the last) and retrainings, as the explore stages run
    them (the registry lists stage templates, not their order across rounds).
    """
    cfg = compose_recipe(RECIPES[kind])
    if kind == "control":
        return get_type("control").stage_list(cfg)
    per_round = cfg.env.episode_steps * cfg.guided.refit_every_episodes
    rounds = math.ceil(cfg.guided.steps / per_round)
    guided = []
    for r in range(rounds):
        guided += [f"guided_data_{r}"] + ([f"guided_refit_{r}"] if r < rounds - 1 else [])
    groups = batches(cfg.retrainings, cfg.retrainings_per_fit)
    retrain = [f"retrain_{g}" for g in range(len(groups))]
    return ["validation", "initial_random", "initial_models", *guided, "random_arm", *retrain]


STAGES = {kind: expected_stages(kind) for kind in RECIPES}
WHERE = ("boundary", "mid", "writing")
# The unmarked subset: two boundaries and one mid-stage kill per recipe, in one chain. The first
# boundary comes before the networks are built from the global RNG, so a resumed run that did
# not restore the RNG state of the skipped stage gives other numbers.
CHAINS = {
    "explore": [
        ("initial_random", "boundary"),
        ("guided_data_0", "writing"),
        ("retrain_0", "boundary"),
    ],
    "control": [
        ("random_data", "boundary"),
        ("setting_u_low", "writing"),
        ("setting_u_high", "boundary"),
    ],
}


# ----------------------------------------------------------------------------------------------
# Running the command line


def command(kind: str, run_dir: Path) -> list[str]:
    """The command a user types, with a fixed run directory and no logger or progress bars."""
    return [
        sys.executable,
        "-m",
        "torchrl_recon.cli",
        kind,
        str(RECIPES[kind]),
        f"output_dir={run_dir}",
        "logger.backend=none",
        "progress=false",
    ]


def environment() -> dict[str, str]:
    """This environment, with the checkout under test first on the path and one thread."""
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}


def start(kind: str, run_dir: Path, logs: Path, name: str) -> subprocess.Popen:
    """Start the command in a fresh process; its stdout and stderr go to ``logs/<name>.*``."""
    logs.mkdir(parents=True, exist_ok=True)
    with open(logs / f"{name}.out", "wb") as out, open(logs / f"{name}.err", "wb") as err:
        return subprocess.Popen(
            command(kind, run_dir), stdout=out, stderr=err, env=environment(), cwd=REPO
        )


def tail(logs: Path, name: str, chars: int = 3000) -> str:
    return (logs / f"{name}.err").read_text(errors="replace")[-chars:]


def finish(kind: str, run_dir: Path, logs: Path, name: str) -> None:
    """Run the command to its end; fail with its stderr unless it exits 0."""
    proc = start(kind, run_dir, logs, name)
    code = proc.wait(timeout=RUN_TIMEOUT_S)
    assert code == 0, f"{name} exited with {code}:\n{tail(logs, name)}"


def kill_when(proc: subprocess.Popen, fire: Callable[[], bool]) -> float:
    """SIGKILL ``proc`` as soon as ``fire()`` is true; returns the seconds it ran.

    Fails if the process ends first: the kill point was never reached.
    """
    begin = time.monotonic()
    while proc.poll() is None:
        if fire():
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
            return time.monotonic() - begin
        if time.monotonic() - begin > RUN_TIMEOUT_S:
            proc.kill()
            proc.wait()
            pytest.fail(f"the kill point was not reached in {RUN_TIMEOUT_S} s")
        time.sleep(POLL_S)
    pytest.fail(f"the run ended (exit code {proc.returncode}) before the kill point was reached")


# ----------------------------------------------------------------------------------------------
# Kill points


@dataclass(frozen=True)
class KillPoint:
    """Where to kill a run: at the ``stage``'s ``boundary``, ``mid``-stage or while ``writing``."""

    stage: str
    where: str

    def __str__(self) -> str:
        return f"{self.where} of {self.stage}"

    def trigger(
        self, run_dir: Path, order: list[str], pid: int, stage_cpu: float | None = None
    ) -> Callable[[], bool]:
        """A function that turns true when process ``pid`` reaches this point.

        ``mid`` needs ``stage_cpu``, the CPU seconds the stage took in the reference run: the kill
        comes when the process has spent half of them since the previous stage's record. CPU
        time, unlike wall time, does not stretch when other work shares the cores.
        """
        stages = run_dir / "stages"
        if self.where == "boundary":
            return (stages / f"{self.stage}.json").exists
        if self.where == "writing":
            outputs = [
                run_dir / "buffers" / self.stage,
                run_dir / "checkpoints" / f"{self.stage}.pt.tmp",
                run_dir / "checkpoints" / f"{self.stage}.pt",
                stages / self.stage / "part_0.json",
                stages / f"{self.stage}.rng.pt.tmp",
                stages / f"{self.stage}.rng.pt",
            ]
            return lambda: any(p.exists() for p in outputs)
        assert self.where == "mid" and stage_cpu is not None, (self.where, stage_cpu)
        i = order.index(self.stage)
        begun = stages / f"{order[i - 1]}.json" if i else run_dir / "meta.json"
        assert not begun.exists(), f"{begun} exists already: 'mid' needs a run that writes it"
        seen: list[float] = []

        def fire() -> bool:
            if not seen:
                if begun.exists():
                    seen.append(cpu_seconds(pid) or 0.0)
                return False
            return (cpu_seconds(pid) or 0.0) - seen[0] >= stage_cpu / 2

        return fire


def cpu_seconds(pid: int) -> float | None:
    """CPU time (user + system) of a running process, from ``/proc``; None where there is none."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def landed(run_dir: Path, order: list[str]) -> str:
    """Where a killed run stopped, read from its directory: the stage and what it had written."""
    if (run_dir / "results.json").exists():
        return "after results.json was written (figures or shutdown)"
    done = [s for s in order if (run_dir / "stages" / f"{s}.json").exists()]
    if done != order[: len(done)]:
        return f"out of order: records of {done}"
    if len(done) == len(order):
        return "after the last stage, before results.json"
    stage = order[len(done)]
    written = sorted(
        {
            str(p.relative_to(run_dir))
            for p in (
                *run_dir.glob(f"buffers/{stage}"),
                *run_dir.glob(f"checkpoints/{stage}.pt*"),
                *run_dir.glob(f"stages/{stage}/part_*.json"),
                *run_dir.glob(f"stages/{stage}.rng.pt*"),
                *run_dir.rglob("*.tmp"),
            )
        }
    )
    return f"in {stage} (stage {len(done) + 1}/{len(order)}; written: {', '.join(written) or 'nothing'})"


# ----------------------------------------------------------------------------------------------
# Comparing run directories


def _without(obj, keys: set[str]):
    if isinstance(obj, dict):
        return {k: _without(v, keys) for k, v in obj.items() if k not in keys}
    if isinstance(obj, list):
        return [_without(v, keys) for v in obj]
    return obj


def run_data(run_dir: Path) -> dict[str, str]:
    """What must not depend on kills: every file of ``run_dir`` but :data:`NOT_DATA`, as text.

    JSON files lose their ``wall_time_s`` and ``_sha256`` keys (``results.json`` its ``meta``
    too) and are
    written back sorted (``NaN`` stays ``NaN``, floats exact); ``config.yaml`` loses
    ``output_dir``; any other file is its SHA-256.
    """
    data = {}
    for path in sorted(p for p in run_dir.rglob("*") if p.is_file()):
        rel = path.relative_to(run_dir).as_posix()
        if rel in NOT_DATA:
            continue
        if path.suffix == ".json":
            try:
                obj = json.loads(path.read_text())
            except ValueError:
                data[rel] = f"not JSON: sha256 {hashlib.sha256(path.read_bytes()).hexdigest()}"
                continue
            obj = _without(obj, {"meta"}) if rel == "results.json" else obj
            # a record's own SHA-256 covers its wall time; the files it lists are compared here
            data[rel] = json.dumps(_without(obj, {"wall_time_s", "_sha256"}), sort_keys=True)
        elif rel == "config.yaml":
            config = yaml.safe_load(path.read_text())
            config.pop("output_dir", None)
            data[rel] = json.dumps(config, sort_keys=True)
        else:
            data[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    return data


def _first_difference(a, b, where: str = "") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if a.get(key, "(absent)") != b.get(key, "(absent)"):
                return _first_difference(
                    a.get(key, "(absent)"), b.get(key, "(absent)"), f"{where}.{key}"
                )
        return ""
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            if x != y:
                return _first_difference(x, y, f"{where}[{i}]")
        return ""
    return f"{where.lstrip('.')}: {a!r} != {b!r}"


def assert_same_run(resumed: Path, reference: Path, context: str) -> None:
    """Fail, naming the files (and the first differing result), unless both hold the same data."""
    got, want = run_data(resumed), run_data(reference)
    if got == want:
        return
    lines = [f"the resumed run differs from the uninterrupted one ({context}):"]
    lines += [f"  missing: {p}" for p in sorted(set(want) - set(got))]
    lines += [f"  extra: {p}" for p in sorted(set(got) - set(want))]
    changed = [p for p in sorted(set(got) & set(want)) if got[p] != want[p]]
    lines += [f"  differs: {p}" for p in changed]
    if "results.json" in changed:
        first = _first_difference(json.loads(got["results.json"]), json.loads(want["results.json"]))
        lines.append(f"  first differing result: {first}")
    raise AssertionError("\n".join(lines))


# ----------------------------------------------------------------------------------------------
# Reference runs (uninterrupted, once per module)


@dataclass
class Reference:
    """An uninterrupted run: its directory and the CPU seconds each stage took (empty without /proc)."""

    run_dir: Path
    stage_cpu: dict[str, float]


class References:
    """Uninterrupted smoke runs, all started on first use, each waited for when needed.

    They run beside the first kill test, which finds its kill points on the file system and
    needs them only to compare at its end. A thread per run notes the run's CPU time as each
    stage record appears, for the ``mid`` kill points.
    """

    def __init__(self, root: Path, kinds: set[str]):
        self.root, self.kinds = root, kinds
        self.procs: dict[str, subprocess.Popen] = {}
        self.watchers: dict[str, threading.Thread] = {}
        self.cpu_marks: dict[str, dict[str, float]] = {}
        self.done: dict[str, Reference] = {}

    def start(self, kind: str) -> None:
        """Start the reference runs (of every kind the selected tests use) if not yet started."""
        for k in sorted(self.kinds | {kind}):
            if k not in self.procs:
                self.procs[k] = start(k, self.root / k, self.root / "logs", k)
                self.cpu_marks[k] = {}
                self.watchers[k] = threading.Thread(target=self._watch, args=(k,), daemon=True)
                self.watchers[k].start()

    def _watch(self, kind: str) -> None:
        proc, marks = self.procs[kind], self.cpu_marks[kind]
        files = [("meta.json", self.root / kind / "meta.json")]
        files += [(s, self.root / kind / "stages" / f"{s}.json") for s in STAGES[kind]]
        while proc.poll() is None and files:
            if files[0][1].exists():
                cpu = cpu_seconds(proc.pid)
                if cpu is None:
                    return
                marks[files.pop(0)[0]] = cpu
            else:
                time.sleep(POLL_S)

    def __call__(self, kind: str) -> Reference:
        """The finished reference run of ``kind`` (waits for it)."""
        self.start(kind)
        if kind not in self.done:
            code = self.procs[kind].wait(timeout=RUN_TIMEOUT_S)
            self.watchers[kind].join()
            assert code == 0, f"reference {kind} run failed:\n{tail(self.root / 'logs', kind)}"
            marks, order = self.cpu_marks[kind], ["meta.json", *STAGES[kind]]
            stage_cpu = {
                b: marks[b] - marks[a] for a, b in pairwise(order) if a in marks and b in marks
            }
            self.done[kind] = Reference(self.root / kind, stage_cpu)
        return self.done[kind]

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.fixture(scope="module")
def reference(request, tmp_path_factory):
    """``reference(kind)``: the uninterrupted smoke run of ``kind``, made once per module."""
    kinds = {
        item.callspec.params["kind"]
        for item in request.session.items
        if getattr(item, "module", None) is request.module
        and "kind" in getattr(getattr(item, "callspec", None), "params", {})
    }
    refs = References(tmp_path_factory.mktemp("references"), kinds)
    yield refs
    refs.close()


# ----------------------------------------------------------------------------------------------
# Kill and resume


def kill_and_resume(
    kind: str, points: list[KillPoint], reference: References, tmp_path: Path, request
) -> None:
    """Kill a fresh run at each point in turn (each time in a new process), then finish it."""
    run_dir, logs = tmp_path / "run", tmp_path / "logs"
    reference.start(kind)
    where = []
    for i, point in enumerate(points):
        stage_cpu = None
        if point.where == "mid":
            stage_cpu = reference(kind).stage_cpu.get(point.stage)
            if stage_cpu is None:
                pytest.skip("mid-stage kills time the stage by its CPU time, read from /proc")
        proc = start(kind, run_dir, logs, f"killed_{i}")
        seconds = kill_when(proc, point.trigger(run_dir, STAGES[kind], proc.pid, stage_cpu))
        where.append(f"{point}: landed {landed(run_dir, STAGES[kind])} after {seconds:.1f} s")
        assert proc.returncode == -signal.SIGKILL, tail(logs, f"killed_{i}")
    request.node.user_properties.append(("kill_landed", " | ".join(where)))
    print("\n".join(where))
    finish(kind, run_dir, logs, "resumed")
    assert_same_run(run_dir, reference(kind).run_dir, "; ".join(where))


@pytest.mark.parametrize("kind", sorted(CHAINS))
def test_killed_three_times_resumes_to_the_same_run(kind, reference, tmp_path, request):
    """Two boundaries and one mid-stage kill, each resumed by the same command in a new process."""
    points = [KillPoint(stage, where) for stage, where in CHAINS[kind]]
    kill_and_resume(kind, points, reference, tmp_path, request)


@pytest.mark.parametrize("kind", sorted(RECIPES))
def test_reference_run_has_the_expected_stages(kind, reference):
    """The kill points name real stages: the reference's records, in order, match the recipe."""
    run_dir = reference(kind).run_dir
    records = sorted((run_dir / "stages").glob("*.json"), key=lambda p: p.stat().st_mtime_ns)
    assert [p.stem for p in records] == STAGES[kind]
    cfg = compose_recipe(RECIPES[kind])
    for stage in STAGES[kind]:
        assert get_type(kind).is_stage(cfg, stage), stage


@pytest.mark.slow
@pytest.mark.parametrize("where", WHERE)
@pytest.mark.parametrize(
    "kind, stage", [(kind, stage) for kind in sorted(STAGES) for stage in STAGES[kind]]
)
def test_killed_once_resumes_to_the_same_run(kind, stage, where, reference, tmp_path, request):
    """One kill at one point, then the same command in a new process finishes the run."""
    kill_and_resume(kind, [KillPoint(stage, where)], reference, tmp_path, request)


# ----------------------------------------------------------------------------------------------
# Damaged files

# One file of each kind in a finished control smoke run (control has them all).
DAMAGE_TARGETS = {
    "buffer storage": "buffers/random_data/storage/observation.memmap",
    "buffer metadata": "buffers/random_data/buffer_metadata.json",
    "checkpoint": "checkpoints/models.pt",
    "rng state": "stages/random_data.rng.pt",
    "stage record": "stages/random_data.json",
    "part record": "stages/setting_baseline/part_0.json",
    "config": "config.yaml",
    "meta": "meta.json",
}
# Deleting these two is not damage (see test_deleted_description_is_rewritten).
REWRITTEN = {"config.yaml", "meta.json"}
# Deleting a record is the documented remedy for a damaged stage: that stage is computed again
# (see test_deleted_record_recomputes). A deleted part record of a finished setting is never
# read again (the setting's own record holds its results), so it cannot be refused.
RECOMPUTED = {"stages/random_data.json"}
UNREAD = {"stages/setting_baseline/part_0.json"}
# Run by `make test` once the integrity checks are in (all are slow until then, as an expected
# failure tells CI nothing): data only a checksum can tell, and a torn checkpoint.
QUICK_DAMAGE = {("buffer storage", "garble"), ("checkpoint", "truncate")}


def damage(path: Path, how: str) -> None:
    """``truncate`` to half its size, ``garble`` 16 bytes in its middle, or ``delete`` it."""
    if how == "delete":
        path.unlink()
        return
    data = bytearray(path.read_bytes())
    if how == "truncate":
        path.write_bytes(data[: len(data) // 2])
        return
    assert how == "garble", how
    mid = len(data) // 2
    data[mid : mid + 16] = bytes(b ^ 0xFF for b in data[mid : mid + 16])
    path.write_bytes(data)


def file_hashes(run_dir: Path) -> dict[str, str]:
    return {
        p.relative_to(run_dir).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(run_dir.rglob("*"))
        if p.is_file()
    }


def _damage_cases():
    for kind, target in DAMAGE_TARGETS.items():
        for how in ("truncate", "garble", "delete"):
            if how == "delete" and target in REWRITTEN | RECOMPUTED | UNREAD:
                continue
            marks = [*NEEDS_INTEGRITY]
            if (kind, how) not in QUICK_DAMAGE or not INTEGRITY_CHECKS_MERGED:
                marks.append(pytest.mark.slow)
            yield pytest.param(target, how, marks=marks, id=f"{how}-{kind.replace(' ', '_')}")


def finished_copy(reference: References, tmp_path: Path) -> Path:
    """A copy of the finished control reference run, to damage."""
    run_dir = tmp_path / "run"
    shutil.copytree(reference("control").run_dir, run_dir)
    return run_dir


@pytest.mark.parametrize("target, how", list(_damage_cases()))
def test_damaged_file_is_refused_and_nothing_changes(target, how, reference, tmp_path):
    """A damaged file stops the re-run before it writes anything, with one line naming the file.

    Truncated, garbled or deleted data (buffer storage and metadata, a checkpoint, an RNG state),
    or a truncated or garbled stage or part record, cannot come from a kill: files are written
    whole, then renamed, and a stage's record comes last. A torn ``config.yaml`` or
    ``meta.json`` is refused as well, rather than silently replaced. The user reads one ``error:`` line naming
    the file (exit code 2, no traceback); the directory, the damaged file included, is left as
    it was for them to inspect.
    """
    run_dir = finished_copy(reference, tmp_path)
    damage(run_dir / target, how)
    before = file_hashes(run_dir)
    proc = subprocess.run(
        command("control", run_dir),
        capture_output=True,
        text=True,
        env=environment(),
        cwd=REPO,
        timeout=RUN_TIMEOUT_S,
    )
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert proc.returncode == 2, f"exit code {proc.returncode}:\n{proc.stderr[-3000:]}"
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert len(errors) == 1, proc.stderr[-3000:]
    assert target in errors[0], f"{errors[0]!r} does not name {target}"
    assert file_hashes(run_dir) == before, "the refused run changed the run directory"


@pytest.mark.slow
@pytest.mark.parametrize("target", sorted(REWRITTEN))
def test_deleted_description_is_rewritten(target, reference, tmp_path):
    """A deleted ``config.yaml`` or ``meta.json`` is written again; the run goes on.

    Neither holds stage data: every start writes ``config.yaml`` from its command and
    ``meta.json`` from the machine it runs on. What a user who deleted one and re-runs the same
    command expects is the run they had: it finishes with the same results and leaves every data
    file as it was. Deleting ``meta.json`` loses only the history of earlier starts. Deleting
    ``config.yaml`` loses the check that a resumed run has the same config, so the run trusts
    the command, as it did when the directory was first made.
    """
    run_dir = finished_copy(reference, tmp_path)
    before = run_data(run_dir)
    (run_dir / target).unlink()
    finish("control", run_dir, tmp_path / "logs", "rerun")
    assert (run_dir / target).is_file()
    assert_same_run(run_dir, reference("control").run_dir, f"after deleting {target}")
    assert run_data(run_dir) == before


@pytest.mark.slow
@pytest.mark.parametrize("target", sorted(RECOMPUTED))
def test_deleted_record_recomputes(target, reference, tmp_path):
    """Deleting a stage's (or a part's) record is what a refusal tells the user to do: the
    same command computes that stage again, from its own seed, and the run ends as before."""
    run_dir = finished_copy(reference, tmp_path)
    (run_dir / target).unlink()
    finish("control", run_dir, tmp_path / "logs", "rerun")
    assert_same_run(run_dir, reference("control").run_dir, f"after deleting {target}")
