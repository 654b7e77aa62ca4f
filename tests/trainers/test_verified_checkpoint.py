"""A damaged checkpoint is refused before any state is loaded, on every route a user resumes
through: TorchRL's unified ``Checkpoint`` (as :class:`VerifiedCheckpoint`, alone, in TorchRL's own
``Trainer`` and upgraded by ``OnlineTrainer``), TorchRL's legacy ``save_trainer_file`` (with and
without the sidecar manifest) and the ``online`` recipe's run directory.

Each damage: a file truncated to half, one byte flipped, a file swapped with the same-named file
of another checkpoint, an extra file planted. Each refusal is one ``ValueError`` line naming the
file, and the weights of the Trainer asked to load are left as they were. That an intact
checkpoint resumes to the numbers of an uninterrupted run is test_checkpoint.py's.
"""

from __future__ import annotations

import json
import re
import shutil
import warnings
import zipfile
from pathlib import Path

import pytest
import torch
from torchrl.checkpoint import Checkpoint
from torchrl.trainers import Trainer

from tests.trainers.test_checkpoint import _trainer
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.experiments.recipe import load_recipe
from torchrl_recon.experiments.runner import run as run_recipe
from torchrl_recon.trainers import VerifiedCheckpoint, VerifiedTrainer, verify_checkpoint
from torchrl_recon.trainers.checkpoint import FILES, sidecar

DAMAGES = ("truncate", "flip", "swap", "plant")
RECIPE = (
    Path(__file__).resolve().parents[2] / "recipes" / "industrial_benchmark" / "online_smoke.yaml"
)


def damage(path: Path, how: str, other: Path | None = None) -> Path:
    """Damage the file ``path`` (``swap``: with ``other``; ``plant``: a file beside it); return
    the file the refusal must name."""
    if how == "truncate":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how == "flip":
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    elif how == "swap":
        assert other is not None and other.read_bytes() != path.read_bytes()
        shutil.copyfile(other, path)
    else:
        assert how == "plant", how
        path = path.with_name(f"planted{path.suffix}")
        path.write_bytes(b"\0" * 16)
    return path


def flip_member(archive: Path) -> None:
    """Flip the middle byte of the largest member's data (not padding) in a zip archive."""
    with zipfile.ZipFile(archive) as zf:
        info = max(zf.infolist(), key=lambda i: i.compress_size)
    data = bytearray(archive.read_bytes())
    at = info.header_offset
    name_len, extra_len = (int.from_bytes(data[at + k : at + k + 2], "little") for k in (26, 28))
    data[at + 30 + name_len + extra_len + info.compress_size // 2] ^= 0xFF
    archive.write_bytes(bytes(data))


def plant_member(archive: Path) -> None:
    with zipfile.ZipFile(archive, "a") as zf:
        zf.writestr(f"{zf.namelist()[0].split('/')[0]}/planted", b"\0" * 16)


def refused(load, named: Path) -> str:
    """``load()`` raises one :class:`DamagedFileError` (a ValueError) line naming ``named``;
    returns the message."""
    with pytest.raises(ValueError) as caught:
        load()
    message = str(caught.value)
    assert isinstance(caught.value, DamagedFileError), repr(caught.value)
    assert "\n" not in message, message
    assert str(named) in message, f"{message!r} does not name {named}"
    return message


def weights(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in trainer.loss_module.state_dict().items()}


def same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def loss_tensor(checkpoint: Path) -> Path:
    """The largest tensor file of the loss module (the world model's weights) in a unified
    checkpoint directory."""
    files = checkpoint.glob("components/*-loss_module/state/*.memmap")
    return max(files, key=lambda p: p.stat().st_size)


# ---- TorchRL's unified Checkpoint, as VerifiedCheckpoint ---------------------------------------


def _saved(path: Path, seed: int, fmt: str = "directory") -> Path:
    torch.manual_seed(seed)
    return VerifiedCheckpoint(format=fmt, policy=torch.nn.Linear(8, 8), step={"n": seed}).save(path)


@pytest.mark.parametrize("how", DAMAGES)
def test_verified_checkpoint_directory_refuses_a_damaged_file(tmp_path, how):
    path, other = _saved(tmp_path / "a", 0), _saved(tmp_path / "b", 1)
    tensor = max(path.glob("components/*policy/state/*.memmap"), key=lambda p: p.stat().st_size)
    named = damage(tensor, how, other / tensor.relative_to(path))
    target = torch.nn.Linear(8, 8)
    before = {k: v.clone() for k, v in target.state_dict().items()}
    refused(lambda: VerifiedCheckpoint(policy=target, step={}).load(path), named)
    assert same(before, target.state_dict())  # refused before anything was loaded


@pytest.mark.parametrize("how", DAMAGES)
def test_verified_checkpoint_archive_refuses_a_damaged_member(tmp_path, how):
    path, other = _saved(tmp_path / "a.zip", 0, "archive"), _saved(tmp_path / "b.zip", 1, "archive")
    if how == "swap":  # the archive rebuilt with the other checkpoint's weights member
        with zipfile.ZipFile(path) as a, zipfile.ZipFile(other) as b:
            members = {n: a.read(n) for n in a.namelist()}
            name = max((n for n in members if n.endswith(".memmap")), key=lambda n: len(members[n]))
            members[name] = b.read(name)
        with zipfile.ZipFile(path, "w") as a:
            for n, data in members.items():
                a.writestr(n, data)
    elif how == "plant":
        plant_member(path)
    else:
        damage(path, how)
    target = torch.nn.Linear(8, 8)
    before = {k: v.clone() for k, v in target.state_dict().items()}
    refused(lambda: VerifiedCheckpoint(policy=target, step={}).load(path), path)
    assert same(before, target.state_dict())


def test_a_deleted_or_damaged_manifest_is_refused(tmp_path):
    path = _saved(tmp_path / "a", 0)
    manifest = json.loads((path / FILES).read_text())
    manifest["files"]["manifest.json"]["size"] += 1  # edited, its own SHA-256 left as it was
    (path / FILES).write_text(json.dumps(manifest))
    refused(lambda: verify_checkpoint(path), path / FILES)
    (path / FILES).unlink()  # TorchRL's manifest says it was saved verified
    refused(lambda: verify_checkpoint(path), path / FILES)


def test_a_plain_torchrl_checkpoint_loads_with_a_warning(tmp_path):
    source, target = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    path = Checkpoint(policy=source).save(tmp_path / "plain")
    with pytest.warns(UserWarning, match="no files.json manifest"):
        VerifiedCheckpoint(policy=target).load(path)
    assert same(source.state_dict(), target.state_dict())


# ---- a Trainer: TorchRL's own with a VerifiedCheckpoint, the library's OnlineTrainer ----------


def test_torchrls_own_trainer_refuses_the_truncated_loss_tensor_it_used_to_load(tmp_path):
    """The reported case: TorchRL's Trainer with a unified checkpoint, the loss module's tensor
    file truncated to half. A plain ``Checkpoint`` loads it; a ``VerifiedCheckpoint`` refuses."""

    def trainer(seed: int, checkpoint: Checkpoint) -> Trainer:
        online = _trainer(seed=seed)
        return Trainer(
            collector=online.collector,
            total_frames=online.total_frames,
            frame_skip=1,
            optim_steps_per_batch=1,
            loss_module=online.loss_module,
            progress_bar=False,
            save_trainer_file=tmp_path / f"seed{seed}",
            checkpoint=checkpoint,
        )

    for checkpoint, refuses in ((Checkpoint(), False), (VerifiedCheckpoint(), True)):
        shutil.rmtree(tmp_path / "seed0", ignore_errors=True)
        trainer(0, checkpoint).save_trainer(force_save=True)
        tensor = loss_tensor(tmp_path / "seed0")
        damage(tensor, "truncate")
        fresh = trainer(1, type(checkpoint)())
        before = weights(fresh)
        if refuses:
            refused(lambda fresh=fresh: fresh.load_from_file(tmp_path / "seed0"), tensor)
            assert same(before, weights(fresh))
        else:  # TorchRL alone: no error, other weights
            fresh.load_from_file(tmp_path / "seed0")
            assert not same(before, weights(fresh))


@pytest.fixture
def saved_pair(tmp_path):
    """``saved_pair(fmt)``: two OnlineTrainer checkpoints (seeds 0 and 1) in ``fmt``, saved
    before any batch (the weights differ by seed)."""

    def save(fmt: str) -> tuple[Path, Path]:
        paths = []
        for seed in (0, 1):
            path = tmp_path / f"seed{seed}" / ("trainer.pt" if fmt == "legacy" else "trainer")
            path.parent.mkdir()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the legacy format's FutureWarning
                _trainer(path, fmt, seed=seed).save_trainer(force_save=True)
            paths.append(path)
        return paths[0], paths[1]

    return save


@pytest.mark.parametrize("how", DAMAGES)
def test_online_trainer_unified_checkpoint_refuses_a_damaged_file(saved_pair, how):
    path, other = saved_pair("directory")
    assert (path / FILES).is_file()  # a plain Checkpoint() given was upgraded
    tensor = loss_tensor(path)
    named = damage(tensor, how, other / tensor.relative_to(path))
    fresh = _trainer(path, "directory", seed=2)
    before = weights(fresh)
    refused(lambda: fresh.load_from_file(path), named)
    assert same(before, weights(fresh))


def test_online_trainer_refuses_a_damaged_torchrl_manifest(saved_pair):
    """TorchRL's own ``manifest.json`` damaged: TorchRL would take the directory for a legacy
    file; the check names the manifest first."""
    path, _ = saved_pair("directory")
    damage(path / "manifest.json", "truncate")
    refused(
        lambda: _trainer(path, "directory", seed=2).load_from_file(path), path / "manifest.json"
    )


@pytest.mark.parametrize("how", DAMAGES)
def test_online_trainer_legacy_file_refuses_damage(saved_pair, how):
    path, other = saved_pair("legacy")
    assert sidecar(path).is_file()
    if how == "plant":
        plant_member(path)  # one file: the extra is a member of its zip archive
    else:
        damage(path, how, other)
    fresh = _trainer(path, "legacy", seed=2)
    before = weights(fresh)
    message = refused(lambda: fresh.load_from_file(path), path)
    assert "SHA-256" in message or "bytes" in message, message
    assert same(before, weights(fresh))


@pytest.mark.parametrize("how", ["intact", "truncate", "flip", "plant"])
def test_a_legacy_file_of_plain_torchrl_loads_or_is_one_line(saved_pair, how):
    """No sidecar (saved by TorchRL alone): an intact file loads, with a warning; a truncated
    or flipped one is one line (its zip CRC-32); a planted member is not visible without it."""
    path, _ = saved_pair("legacy")
    sidecar(path).unlink()
    saved = torch.load(path, weights_only=True)["loss_module"]
    if how == "plant":
        plant_member(path)
    elif how == "flip":
        flip_member(path)
    elif how == "truncate":
        damage(path, how)
    fresh = _trainer(path, "legacy", seed=2)
    before = weights(fresh)
    if how in ("intact", "plant"):
        with pytest.warns(UserWarning, match="loaded without checking"):
            fresh.load_from_file(path)
        assert same(saved, weights(fresh))
    else:
        refused(lambda: fresh.load_from_file(path), path)
        assert same(before, weights(fresh))


def test_a_legacy_file_torch_cannot_read_is_one_line(tmp_path):
    """A file that is a valid zip but not a torch checkpoint: torch's long message, one line."""
    path = tmp_path / "not_torch.pt"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("x/y", b"nothing")
    fresh = _trainer(path, "legacy", seed=2)
    with pytest.warns(UserWarning):
        message = refused(lambda: fresh.load_from_file(path), path)
    assert message.startswith(f"{path} cannot be read by torch.load (")


def test_unpickling_is_refused(saved_pair):
    path, _ = saved_pair("legacy")
    fresh = _trainer(path, "legacy", seed=2)
    with pytest.raises(ValueError, match=re.escape("expected weights_only=True")):
        fresh.load_from_file(path, weights_only=False)


def test_a_checkpoint_subclass_other_than_verified_is_one_type_error():
    class Mine(Checkpoint):
        pass

    with pytest.raises(TypeError, match="subclass VerifiedCheckpoint"):
        VerifiedTrainer(checkpoint=Mine())


# ---- the online recipe: its run directory's stages ---------------------------------------------


@pytest.fixture(scope="module")
def online_runs(tmp_path_factory):
    """A finished ``online`` smoke run of the Industrial Benchmark (seed 0), and one of seed 1
    stopped after its first fit (stage ``models``)."""
    root = tmp_path_factory.mktemp("online")
    assert run_recipe(load_recipe(RECIPE, [f"output_dir={root / 'seed0'}", "seed=0"]))
    stopped = [f"output_dir={root / 'seed1'}", "seed=1", "stop_after=models"]
    assert run_recipe(load_recipe(RECIPE, stopped)) is None
    return root / "seed0", root / "seed1"


@pytest.mark.parametrize(
    "how, target",
    [
        ("truncate", "buffers/play_1/storage/observation.memmap"),
        ("flip", "checkpoints/refit_1.pt"),
        ("swap", "checkpoints/models.pt"),
        ("plant", "buffers/play_1/storage/observation.memmap"),
    ],
)
def test_the_online_recipe_refuses_a_damaged_run_directory(online_runs, tmp_path, how, target):
    run_dir = tmp_path / "run"
    shutil.copytree(online_runs[0], run_dir)
    named = damage(run_dir / target, how, online_runs[1] / target)
    cfg = load_recipe(RECIPE, [f"output_dir={run_dir}", "seed=0"])
    refused(lambda: run_recipe(cfg), named)
