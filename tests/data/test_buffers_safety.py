"""Saved replay buffers are read as data: no pickle runs, damaged files are refused, nothing is written."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import pytest
import torch
from tensordict import NonTensorData, TensorDict

from torchrl_recon.data import load_buffer, load_buffer_data, make_sequence_buffer, save_buffer
from torchrl_recon.errors import DamagedFileError


class Payload:
    """Unpickling this creates ``marker``: the proof that a loader ran code from a file."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _transitions(n: int = 40) -> TensorDict:
    return TensorDict(
        {
            "observation": torch.randn(n, 5),
            "action": torch.rand(n, 2),
            ("next", "observation"): torch.randn(n, 5),
            ("collector", "traj_ids"): torch.arange(n) // 10,
        },
        [n],
    )


@pytest.fixture
def saved(tmp_path) -> tuple[Path, TensorDict]:
    data = _transitions()
    rb = make_sequence_buffer(len(data), slice_len=5, num_slices=2)
    rb.extend(data)
    path = tmp_path / "rb"
    save_buffer(rb, path)
    return path, rb[:]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _fresh(n: int = 40):
    return make_sequence_buffer(n, slice_len=5, num_slices=2)


def test_round_trip_restores_transitions_and_writer_and_writes_nothing(saved):
    path, expected = saved
    before = {p: p.stat().st_mtime_ns for p in path.rglob("*") if p.is_file()}
    snapshot = _snapshot(path)
    restored = load_buffer(_fresh(), path)
    assert len(restored) == len(expected)
    assert (restored[:] == expected).all()
    assert restored.writer._cursor == 0 and restored.writer._write_count == 40
    assert (load_buffer_data(path) == expected).all()
    restored.sample()  # the buffer works
    assert _snapshot(path) == snapshot
    assert {p: p.stat().st_mtime_ns for p in path.rglob("*") if p.is_file()} == before


def _plant_sidecar(path: Path, marker: Path) -> list[Path]:
    """A ``NonTensorData`` entry in the storage: tensordict keeps it as a pickle sidecar."""
    evil = TensorDict({"evil": NonTensorData(Payload(marker), batch_size=[40])}, [40])
    evil.memmap(path.parent / "evil_td")
    storage = path / "storage"
    (path.parent / "evil_td" / "evil").rename(storage / "evil")
    meta = json.loads((storage / "meta.json").read_text())
    meta["evil"] = {"type": "NonTensorData"}
    (storage / "meta.json").write_text(json.dumps(meta))
    assert (storage / "evil" / "other.pickle").is_file()
    return [storage / "evil" / "other.pickle", storage / "meta.json"]


def _plant_prefetch(path: Path, marker: Path) -> list[Path]:
    (path / "prefetch.pkl").write_bytes(pickle.dumps(Payload(marker)))
    return [path / "prefetch.pkl"]


def _plant_transform(path: Path, marker: Path) -> list[Path]:
    torch.save({"payload": Payload(marker)}, path / "transform.t")
    return [path / "transform.t"]


def _plant_rng_state(path: Path, marker: Path) -> list[Path]:
    TensorDict({"rng_state": NonTensorData(Payload(marker))}).memmap(path / "rng_state")
    return [path / "rng_state"]


def _plant_json(relative: str):
    def plant(path: Path, marker: Path) -> list[Path]:
        (path / relative).write_bytes(pickle.dumps(Payload(marker)))
        return [path / relative]

    return plant


PLANTS = {
    "storage sidecar": _plant_sidecar,
    "prefetch.pkl": _plant_prefetch,
    "transform.t": _plant_transform,
    "rng_state": _plant_rng_state,
    "storage meta.json": _plant_json("storage/meta.json"),
    "storage_metadata.json": _plant_json("storage/storage_metadata.json"),
    "buffer_metadata.json": _plant_json("buffer_metadata.json"),
    "writer metadata.json": _plant_json("writer/metadata.json"),
    "leaf memmap": _plant_json("storage/observation.memmap"),
}


@pytest.mark.parametrize("kind", sorted(PLANTS))
def test_a_planted_pickle_is_refused_and_never_runs(saved, tmp_path, kind):
    path, _ = saved
    marker = tmp_path / "marker"
    touched = PLANTS[kind](path, marker)
    snapshot = _snapshot(path)
    for load in (lambda: load_buffer(_fresh(), path), lambda: load_buffer_data(path)):
        with pytest.raises(DamagedFileError) as err:
            load()
        message = str(err.value)
        assert "\n" not in message and any(str(f) in message for f in touched), message
    assert not marker.exists()
    assert _snapshot(path) == snapshot


def test_torchrl_own_loads_would_run_the_sidecar(saved, tmp_path):
    """The plant above is live: TorchRL's ``loads`` (tensordict's default) unpickles it."""
    path, _ = saved
    marker = tmp_path / "marker"
    _plant_sidecar(path, marker)
    with pytest.warns(FutureWarning, match="pickle"):
        try:
            _fresh().loads(path)
        except Exception:  # it may fail after the code has run
            pass
    assert marker.exists()


@pytest.mark.parametrize("size", [0, 16, 3000])
def test_a_truncated_or_grown_memmap_is_refused_and_left_as_it_is(saved, size):
    path, _ = saved
    leaf = path / "storage" / "observation.memmap"
    assert leaf.stat().st_size == 40 * 5 * 4
    leaf.write_bytes(leaf.read_bytes()[:size] + b"\0" * max(0, size - 800))
    snapshot = _snapshot(path)
    with pytest.raises(DamagedFileError, match=rf"observation.memmap: {size} bytes, expected 800"):
        load_buffer(_fresh(), path)
    assert leaf.stat().st_size == size  # never grown back
    assert _snapshot(path) == snapshot


def test_missing_or_unexpected_files_are_refused(saved):
    path, _ = saved
    (path / "storage" / "notes.txt").write_text("hello")
    with pytest.raises(DamagedFileError, match="notes.txt: not part of the saved TensorDict"):
        load_buffer_data(path)
    (path / "storage" / "notes.txt").unlink()
    (path / "writer" / "metadata.json").unlink()
    with pytest.raises(DamagedFileError, match=r"writer/metadata.json is missing"):
        load_buffer_data(path)


def test_a_buffer_too_small_for_the_saved_data_is_a_clear_error(saved):
    path, _ = saved
    with pytest.raises(ValueError, match="holds 40 transitions .* room for 10"):
        load_buffer(_fresh(10), path)
    with pytest.raises(FileNotFoundError, match="No saved replay buffer"):
        load_buffer_data(path.parent / "nothing")


def test_a_buffer_that_holds_transitions_is_not_restored_over(saved):
    """Restoring over held transitions mixed the two (5 held + 40 saved read as 45)."""
    path, expected = saved
    held = _fresh()
    held.extend(_transitions(5))
    before = held[:].clone()
    with pytest.raises(ValueError, match="restores .* into an empty buffer; the one given holds 5"):
        load_buffer(held, path)
    assert len(held) == 5 and (held[:] == before).all()
    held.empty()
    assert len(load_buffer(held, path)) == 40
    torch.testing.assert_close(held[:]["observation"], expected["observation"])
