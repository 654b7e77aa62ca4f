"""A run directory is data, never code: every loader refuses planted pickles and damaged files.

One smoke run (``stop_after=initial_models``: validation, data, models) is made once per test
run (by the first pytest-xdist worker to ask); each test works on a copy. A payload whose
unpickling would create a marker file is planted in each kind of file a run directory holds and
reads back, and every public loader is called on it: the marker never appears, the refusal is
one ``DamagedFileError`` line naming the file, and the run directory is left byte-identical.
"""

from __future__ import annotations

import copy
import functools
import io
import json
import os
import pickle
import shutil
import subprocess
from collections.abc import Callable
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest
import torch
import yaml
from filelock import FileLock
from omegaconf import DictConfig
from tensordict import NonTensorData, TensorDict

from torchrl_recon.cli import main
from torchrl_recon.data import load_buffer, load_buffer_data, make_sequence_buffer
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.experiments.recipe import load_recipe
from torchrl_recon.experiments.recipe_models import build_models
from torchrl_recon.experiments.run_dir import (
    check_run_dir,
    prepare_run_dir,
    read_config,
    read_meta,
    release_run_dir,
    write_results,
)
from torchrl_recon.experiments.stages import Stages
from torchrl_recon.fitting import load_checkpoint, load_modules
from torchrl_recon.reports import read_results, summarize

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "industrial_benchmark" / "explore_smoke.yaml"
BUFFER = "buffers/initial_random"
CHECKPOINT = "checkpoints/initial_models.pt"
RNG = "stages/initial_models.rng.pt"


class Payload:
    """Unpickling this creates ``marker``: the proof that a loader ran code from a file."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _cli(run_dir: Path, *extra: str) -> subprocess.CompletedProcess:
    """``torchrl-recon explore RECIPE ...`` run by the command line's ``main`` in this process
    (a subprocess would import torch again, ~2/3 of its time; ``test_cli_errors`` runs the
    installed entry point itself), its exit code and printed output as a finished process's."""
    argv = ["explore", str(RECIPE), f"output_dir={run_dir}", "logger.backend=none", *extra]
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(argv)
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


def _explore_results(seed: int) -> dict:
    arm = {"mse": [1.0, 2.0], "mean": 1.5, "std": 0.7}
    return {
        "experiment": "explore",
        "env": "industrial_benchmark",
        "seed": seed,
        "arms": {"random": arm, "active": arm},
    }


def _make_base_run(run_dir: Path) -> None:
    """A real run directory: data, models, validation; plus control-style parts and results."""
    proc = _cli(run_dir, "stop_after=initial_models")
    assert proc.returncode == 0, proc.stderr[-2000:]
    Stages(run_dir, seed=0).run_parts("episodes", 2, lambda i: {"i": i})
    write_results(run_dir, _explore_results(0))
    release_run_dir(run_dir)


@pytest.fixture(scope="module")
def base_run(tmp_path_factory) -> Path:
    """:func:`_make_base_run`'s directory, made once per test run: under pytest-xdist by the
    first worker to ask, in this run's folder common to its workers (each test copies it)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        run_dir = tmp_path_factory.mktemp("safety") / "run"
        _make_base_run(run_dir)
        return run_dir
    shared = tmp_path_factory.getbasetemp().parent / "run_dir_safety"
    shared.mkdir(exist_ok=True)
    run_dir, done = shared / "run", shared / "done"
    with FileLock(str(shared / "lock")):
        if not done.exists():
            shutil.rmtree(run_dir, ignore_errors=True)  # a worker that failed to finish it
            _make_base_run(run_dir)
            done.touch()
    return run_dir


@pytest.fixture
def run(base_run, tmp_path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(base_run, copy, ignore=shutil.ignore_patterns(".lock"))
    return copy


def _snapshot(run_dir: Path) -> dict[str, bytes]:
    """Every file's bytes (but the empty lock file that ``prepare_run_dir`` takes)."""
    files = sorted(p for p in run_dir.rglob("*") if p.is_file() and p.name != ".lock")
    return {str(p): p.read_bytes() for p in files}


@functools.cache
def _recipe() -> DictConfig:
    """The recipe as ``load_recipe`` makes it, loaded once: only its ``output_dir`` (which no
    other key interpolates) differs between the copies of the run."""
    return load_recipe(RECIPE, ["output_dir=unset", "logger.backend=none"])


def _cfg(run_dir: Path) -> DictConfig:
    """``load_recipe(RECIPE, [f"output_dir={run_dir}", "logger.backend=none"])``."""
    cfg = copy.deepcopy(_recipe())
    cfg.output_dir = str(run_dir)
    return cfg


def _modules_of(run_dir: Path) -> dict:
    """A world model and an estimator built from the run's recipe (for ``load_checkpoint``)."""
    world, estimator = build_models(_cfg(run_dir), 6, 3)  # the Industrial Benchmark's dims
    return {"world_model": world, "uncertainty": estimator}


def _must_not_run():
    raise AssertionError("a done stage was computed again")


# ---------------------------------------------------------------------------------------------
# Every public loader of a run directory, by name.


LOADERS: dict[str, Callable[[Path], object]] = {
    "load_buffer": lambda r: load_buffer(
        make_sequence_buffer(300, slice_len=1, num_slices=1), r / BUFFER
    ),
    "load_buffer_data": lambda r: load_buffer_data(r / BUFFER),
    "Stages.load_data": lambda r: Stages(r, seed=0).load_data("initial_random"),
    "Stages.run initial_random": lambda r: Stages(r, seed=0).run("initial_random", _must_not_run),
    "Stages.run initial_models": lambda r: Stages(r, seed=0).run("initial_models", _must_not_run),
    "Stages.verify validation": lambda r: Stages(r, seed=0).verify("validation"),
    "Stages.run_parts": lambda r: Stages(r, seed=0).run_parts(
        "episodes", 2, lambda i: _must_not_run()
    ),
    "load_checkpoint": lambda r: load_checkpoint(r / CHECKPOINT, _modules_of(r)),
    "load_modules": lambda r: load_modules(r / CHECKPOINT),
    "read_config": read_config,
    "check_run_dir": lambda r: check_run_dir(_cfg(r)),
    "read_meta": read_meta,
    "read_results": read_results,
    "summarize": lambda r: summarize([r]),
}


# ---------------------------------------------------------------------------------------------
# Plants: each writes a live payload into one kind of file; returns the files it touched and the
# loaders that must refuse it (all other loaders must still work).


def _raw_pickle(relative: str):
    def plant(r: Path, marker: Path) -> list[Path]:
        (r / relative).write_bytes(pickle.dumps(Payload(marker)))
        return [r / relative]

    return plant


def _sidecar(r: Path, marker: Path) -> list[Path]:
    storage = r / BUFFER / "storage"
    size = json.loads((storage / "meta.json").read_text())["shape"]
    evil = TensorDict({"evil": NonTensorData(Payload(marker), batch_size=size)}, size)
    evil.memmap(r.parent / "evil_td")
    (r.parent / "evil_td" / "evil").rename(storage / "evil")
    meta = json.loads((storage / "meta.json").read_text())
    meta["evil"] = {"type": "NonTensorData"}
    (storage / "meta.json").write_text(json.dumps(meta))
    return [storage / "evil" / "other.pickle", storage / "meta.json"]


def _transform(r: Path, marker: Path) -> list[Path]:
    torch.save({"payload": Payload(marker)}, r / BUFFER / "transform.t")
    return [r / BUFFER / "transform.t"]


def _buffer_rng(r: Path, marker: Path) -> list[Path]:
    TensorDict({"rng_state": NonTensorData(Payload(marker))}).memmap(r / BUFFER / "rng_state")
    return [r / BUFFER / "rng_state"]


def _torch_file(relative: str, wrap: Callable[[Payload], object]):
    def plant(r: Path, marker: Path) -> list[Path]:
        torch.save(wrap(Payload(marker)), r / relative)
        return [r / relative]

    return plant


def _yaml(r: Path, marker: Path) -> list[Path]:
    (r / "config.yaml").write_text(
        f"experiment: !!python/object/apply:builtins.open ['{marker}', 'w']\n"
    )
    return [r / "config.yaml"]


BUFFER_LOADERS = ("load_buffer", "load_buffer_data", "Stages.load_data")
PLANTS = {
    # kind: (plant, loaders that must refuse, a reader that would run the payload)
    "buffer storage sidecar (other.pickle)": (
        _sidecar,
        (*BUFFER_LOADERS, "Stages.run initial_random"),
        lambda r: TensorDict.load_memmap(r / BUFFER / "storage", allow_pickle=True),
    ),
    "buffer storage tensor (.memmap)": (
        _raw_pickle(f"{BUFFER}/storage/observation.memmap"),
        (*BUFFER_LOADERS, "Stages.run initial_random"),
        lambda r: pickle.loads((r / BUFFER / "storage" / "observation.memmap").read_bytes()),
    ),
    "buffer storage meta.json": (
        _raw_pickle(f"{BUFFER}/storage/meta.json"),
        (*BUFFER_LOADERS, "Stages.run initial_random"),
        lambda r: pickle.loads((r / BUFFER / "storage" / "meta.json").read_bytes()),
    ),
    "buffer storage_metadata.json": (
        _raw_pickle(f"{BUFFER}/storage/storage_metadata.json"),
        (*BUFFER_LOADERS, "Stages.run initial_random"),
        lambda r: pickle.loads((r / BUFFER / "storage" / "storage_metadata.json").read_bytes()),
    ),
    "buffer_metadata.json": (
        _raw_pickle(f"{BUFFER}/buffer_metadata.json"),
        (*BUFFER_LOADERS, "Stages.run initial_random"),
        lambda r: pickle.loads((r / BUFFER / "buffer_metadata.json").read_bytes()),
    ),
    "buffer writer metadata.json": (
        _raw_pickle(f"{BUFFER}/writer/metadata.json"),
        (*BUFFER_LOADERS, "Stages.run initial_random"),
        lambda r: pickle.loads((r / BUFFER / "writer" / "metadata.json").read_bytes()),
    ),
    "buffer prefetch.pkl": (
        _raw_pickle(f"{BUFFER}/prefetch.pkl"),
        BUFFER_LOADERS,
        lambda r: pickle.loads((r / BUFFER / "prefetch.pkl").read_bytes()),
    ),
    "buffer transform.t": (
        _transform,
        BUFFER_LOADERS,
        lambda r: torch.load(r / BUFFER / "transform.t", weights_only=False),
    ),
    "buffer rng_state": (
        _buffer_rng,
        BUFFER_LOADERS,
        lambda r: TensorDict.load_memmap(r / BUFFER / "rng_state", allow_pickle=True),
    ),
    "checkpoint .pt": (
        _torch_file(CHECKPOINT, lambda p: {"format": 1, "modules": {}, "extra": {"x": p}}),
        ("load_checkpoint", "load_modules", "Stages.run initial_models"),
        lambda r: torch.load(r / CHECKPOINT, weights_only=False),
    ),
    "stage RNG state .rng.pt": (
        _torch_file(RNG, lambda p: p),
        ("Stages.run initial_models",),
        lambda r: torch.load(r / RNG, weights_only=False),
    ),
    "stage record .json": (
        _raw_pickle("stages/initial_random.json"),
        ("Stages.run initial_random", "Stages.load_data"),
        lambda r: pickle.loads((r / "stages" / "initial_random.json").read_bytes()),
    ),
    "stage part_*.json": (
        _raw_pickle("stages/episodes/part_0.json"),
        ("Stages.run_parts",),
        lambda r: pickle.loads((r / "stages" / "episodes" / "part_0.json").read_bytes()),
    ),
    "config.yaml": (
        _yaml,
        ("read_config", "check_run_dir"),
        lambda r: yaml.unsafe_load((r / "config.yaml").read_text()),
    ),
    "meta.json": (
        _raw_pickle("meta.json"),
        ("read_meta",),
        lambda r: pickle.loads((r / "meta.json").read_bytes()),
    ),
    "results.json": (
        _raw_pickle("results.json"),
        ("read_results", "summarize"),
        lambda r: pickle.loads((r / "results.json").read_bytes()),
    ),
}


def test_sixteen_kinds_of_files_are_planted():
    assert len(PLANTS) == 16


@pytest.mark.parametrize("kind", sorted(PLANTS))
def test_each_plant_is_live(run, tmp_path, kind):
    """Control: an unsafe reader of the planted file does run the payload."""
    plant, _, unsafe = PLANTS[kind]
    marker = tmp_path / "marker"
    plant(run, marker)
    try:
        unsafe(run)
    except Exception:  # the payload may break the reader after it ran
        pass
    assert marker.exists()


def test_every_loader_reads_the_clean_run(run):
    """Control: every loader works on the clean copy the plants start from, and writes nothing."""
    snapshot = _snapshot(run)
    for load in LOADERS.values():
        load(run)
    assert _snapshot(run) == snapshot


@pytest.mark.parametrize("kind", sorted(PLANTS))
def test_a_planted_payload_is_refused_by_every_loader_and_never_runs(run, tmp_path, kind):
    """On a clean copy (which every loader reads, see above) one planted file: each loader
    that reads it refuses it, naming the file, the others still work, and nothing runs."""
    plant, refusing, _ = PLANTS[kind]
    marker = tmp_path / "marker"
    touched = plant(run, marker)
    snapshot = _snapshot(run)
    for name, load in LOADERS.items():
        if name in refusing:
            with pytest.raises(DamagedFileError) as err:
                load(run)
            message = str(err.value)
            assert "\n" not in message, (name, message)
            assert any(str(f) in message for f in touched), (name, message)
        else:
            load(run)  # files that were not touched still load
        assert not marker.exists(), name
    assert _snapshot(run) == snapshot  # reading (and refusing) writes nothing


@pytest.mark.parametrize("kind", ["config.yaml", "meta.json"])
def test_prepare_run_dir_refuses_before_writing(run, tmp_path, kind):
    plant, _, _ = PLANTS[kind]
    marker = tmp_path / "marker"
    touched = plant(run, marker)
    snapshot = _snapshot(run)
    with pytest.raises(DamagedFileError, match=str(touched[0])):
        prepare_run_dir(_cfg(run))
    assert not marker.exists()
    assert _snapshot(run) == snapshot
    release_run_dir(run)


# ---------------------------------------------------------------------------------------------
# Integrity: damage found on resume, named with its stage and the remedy.


def _refused(run: Path, stage: str, load: Callable[[], object], file: str) -> str:
    snapshot = _snapshot(run)
    with pytest.raises(DamagedFileError) as err:
        load()
    message = str(err.value)
    assert "\n" not in message and str(run / file) in message, message
    assert f"delete {run / 'stages' / stage}.json" in message, message
    assert _snapshot(run) == snapshot
    return message


def test_truncated_buffer_file_is_refused_and_not_grown_back(run):
    leaf = run / "buffers" / "validation" / "storage" / "observation.memmap"
    leaf.write_bytes(leaf.read_bytes()[:16])
    message = _refused(
        run,
        "validation",
        lambda: Stages(run, seed=0).run("validation", _must_not_run),
        str(leaf.relative_to(run)),
    )
    assert "has 16 bytes, but stage 'validation'" in message
    _refused(
        run,
        "validation",
        lambda: Stages(run, seed=0).load_data("validation"),
        str(leaf.relative_to(run)),
    )
    assert leaf.stat().st_size == 16


def test_same_size_change_is_found_by_the_hash(run):
    leaf = run / BUFFER / "storage" / "action.memmap"
    data = bytearray(leaf.read_bytes())
    data[0] ^= 1
    leaf.write_bytes(bytes(data))
    message = _refused(
        run,
        "initial_random",
        lambda: Stages(run, seed=0).load_data("initial_random"),
        f"{BUFFER}/storage/action.memmap",
    )
    assert "SHA-256" in message


def test_hand_edited_record_is_refused(run):
    record = run / "stages" / "initial_models.json"
    data = json.loads(record.read_text())
    data["world_model_val_loss"] = 999
    record.write_text(json.dumps(data, indent=1))
    message = _refused(
        run,
        "initial_models",
        lambda: Stages(run, seed=0).run("initial_models", _must_not_run),
        "stages/initial_models.json",
    )
    assert "does not match the SHA-256" in message


@pytest.mark.parametrize(
    "damage, expected",
    [
        (lambda b: b[: len(b) // 2], "not valid JSON"),
        (lambda b: b"\x80\x04garbage", "not valid JSON"),
        (lambda b: b"[1, 2]", "not a record"),
        (lambda b: json.dumps({"world_model_val_loss": 1.0}).encode(), "has no 'wall_time_s'"),
    ],
    ids=["truncated", "garbage", "not an object", "missing key"],
)
def test_damaged_stage_record_is_refused(run, damage, expected):
    record = run / "stages" / "initial_models.json"
    record.write_bytes(damage(record.read_bytes()))
    message = _refused(
        run,
        "initial_models",
        lambda: Stages(run, seed=0).run("initial_models", _must_not_run),
        "stages/initial_models.json",
    )
    assert expected in message


def _legacy(run: Path) -> None:
    """Make every stage record look like one written before files were listed and hashed."""
    for record in (run / "stages").glob("*.json"):
        data = json.loads(record.read_text())
        data.pop("_files", None), data.pop("_sha256", None)
        record.write_text(json.dumps(data, indent=1))


@pytest.mark.parametrize(
    "damage",
    [lambda b: b[: len(b) // 2], lambda b: b"\x00" * 64, lambda b: b""],
    ids=["truncated", "garbage", "empty"],
)
@pytest.mark.parametrize("file", [CHECKPOINT, RNG])
def test_damaged_checkpoint_and_rng_files_are_refused_even_in_legacy_runs(run, file, damage):
    _legacy(run)
    path = run / file
    path.write_bytes(damage(path.read_bytes()))
    snapshot = _snapshot(run)
    if file == CHECKPOINT:  # a legacy record lists no files: the checkpoint's loaders refuse it
        loaders = [lambda: load_modules(path), lambda: load_checkpoint(path, _modules_of(run))]
    else:
        loaders = [lambda: Stages(run, seed=0).run("initial_models", _must_not_run)]
    for load in loaders:
        with pytest.raises(DamagedFileError) as err:
            load()
        message = str(err.value)
        assert "\n" not in message and str(path) in message, message
        assert "weights_only=False" not in message
    assert _snapshot(run) == snapshot


def test_legacy_records_still_resume_with_the_same_records(run):
    fresh = {
        s: Stages(run, seed=0).run(s, _must_not_run)
        for s in ("initial_random", "initial_models", "validation")
    }
    _legacy(run)
    stages = Stages(run, seed=0)
    assert {s: stages.run(s, _must_not_run) for s in fresh} == fresh
    torch.testing.assert_close(
        stages.load_data("validation")["observation"],
        Stages(run, seed=0).load_data("validation")["observation"],
    )


def test_records_list_the_files_their_stage_wrote(run):
    record = json.loads((run / "stages" / "initial_models.json").read_text())
    assert sorted(record["_files"]) == [CHECKPOINT, RNG]
    record = json.loads((run / "stages" / "initial_random.json").read_text())
    assert f"{BUFFER}/storage/observation.memmap" in record["_files"]
    assert "stages/initial_random.rng.pt" in record["_files"]
    assert "_files" not in Stages(run, seed=0).run("initial_random", _must_not_run)


def test_checkpoint_map_location_and_device_free_save(run, tmp_path):
    modules = load_modules(run / CHECKPOINT, map_location="cpu")
    assert all(p.device.type == "cpu" for m in modules.values() for p in m.parameters())
    payload = torch.load(run / CHECKPOINT, map_location="meta", weights_only=True)
    assert payload["modules"]["world_model"][
        "state_dict"
    ]  # loads without the device it was saved on


# ---------------------------------------------------------------------------------------------
# Through the command line: a resumed run refuses, runs nothing from the files, changes no data.


def test_cli_resume_refuses_a_planted_pickle(run, tmp_path):
    marker = tmp_path / "marker"
    touched = _sidecar(run, marker)
    data = {
        k: v
        for k, v in _snapshot(run).items()
        if "/buffers/" in k or "/checkpoints/" in k or "/stages/" in k
    }
    proc = _cli(run, "stop_after=initial_models")
    output = proc.stdout + proc.stderr
    assert proc.returncode != 0, output[-2000:]
    assert "DamagedFileError" in output or "error:" in output
    assert any(str(f) in output for f in touched), output[-2000:]
    assert not marker.exists()
    after = _snapshot(run)
    assert {k: after.get(k) for k in data} == data
