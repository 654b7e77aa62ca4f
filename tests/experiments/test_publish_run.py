"""docs/results/publish_run.py: what a published run keeps as files, what goes into its
experiment folder's records archive, and no absolute machine path."""

from __future__ import annotations

import json

import pytest

from tests.experiments.results_fixtures import known_explore
from torchrl_recon.reports import summarize
from torchrl_recon.runs.archive import ARCHIVE, MANIFEST, read_members

FILES = [
    "config.yaml",
    "meta.json",
    "results.json",
    "table1.png",
    "other.png",
    "control.log",
    "stages/models.json",
    "stages/setting_done.json",
    "stages/setting_done/part_0.json",
    "stages/setting_running/part_0.json",
    "buffers/random_data/storage/x.memmap",
    "checkpoints/models.pt",
    "wandb/run/file.json",
]


def _run(tmp_path, seed=0, root=None):
    run = tmp_path / "outputs" / f"seed{seed}"
    for name in FILES:
        (run / name).parent.mkdir(parents=True, exist_ok=True)
        (run / name).write_text("x")
    (run / "results.json").write_text(json.dumps(known_explore()[seed]))
    root = root or tmp_path / "checkout"
    meta = {"run_dir": str(run), "argv": ["torchrl-recon", "explore", f"output_dir={run}"]}
    (run / "meta.json").write_text(json.dumps(meta, indent=1))
    (run / "config.yaml").write_text(f"seed: {seed}\noutput_dir: {run}\n")
    return run


@pytest.fixture
def docs(tmp_path):
    """A docs/ folder whose page shows the figure of seed 0."""
    docs = tmp_path / "checkout" / "docs"
    (docs / "results").mkdir(parents=True)
    (docs / "page.md").write_text("![](results/explore/drone/seed0/table1.png)\n")
    return docs


def test_publish_keeps_what_is_read_and_packs_the_records(tmp_path, docs, results_script):
    publish_run = results_script("publish_run")
    dest = docs / "results" / "explore" / "drone" / "seed0"
    copied = publish_run.publish(
        _run(tmp_path), dest, root=tmp_path / "checkout", results_root=docs / "results"
    )
    assert {p.relative_to(dest).as_posix() for p in copied} == {
        "config.yaml",
        "meta.json",
        "results.json",
        "table1.png",  # shown in the docs
    }
    folder = docs / "results" / "explore"
    assert sorted(read_members(folder)) == [
        "drone/seed0/other.png",
        "drone/seed0/stages/models.json",
        "drone/seed0/stages/setting_done.json",
        "drone/seed0/stages/setting_running/part_0.json",  # a finished setting's are in its record
    ]
    manifest = json.loads((folder / MANIFEST).read_text())
    assert list(manifest["results"]) == ["drone/seed0/results.json"]
    # paths of the machine written relative to the checkout the run started from
    meta = json.loads((dest / "meta.json").read_text())
    assert meta["run_dir"] == "../outputs/seed0"
    assert meta["argv"][-1] == "output_dir=../outputs/seed0"
    assert (dest / "config.yaml").read_text() == "seed: 0\noutput_dir: ../outputs/seed0\n"
    for path in folder.rglob("*"):
        if path.is_file() and path.suffix != ".xz":
            assert str(tmp_path) not in path.read_text(), path
    assert summarize([folder])["archives"][0]["results"] == 1


def test_publishing_again_replaces_the_runs_members_and_adds_others(tmp_path, docs, results_script):
    publish_run = results_script("publish_run")
    folder, root = docs / "results" / "explore", tmp_path / "checkout"
    for seed in (0, 1):
        publish_run.publish(
            _run(tmp_path, seed), folder / "drone" / f"seed{seed}", root=root,
            results_root=docs / "results",
        )  # fmt: skip
    run = _run(tmp_path, 0)
    (run / "stages" / "models.json").unlink()
    publish_run.publish(run, folder / "drone" / "seed0", root=root, results_root=docs / "results")
    members = read_members(folder)
    assert "drone/seed0/stages/models.json" not in members
    assert "drone/seed1/stages/models.json" in members
    assert sorted(json.loads((folder / MANIFEST).read_text())["results"]) == [
        "drone/seed0/results.json",
        "drone/seed1/results.json",
    ]
    assert summarize([folder])["archives"][0] == {
        "archive": (folder / ARCHIVE).as_posix(),
        "members": len(members),
        "results": 2,
    }


def test_publish_refuses_an_absolute_path_outside_the_root(tmp_path, docs, results_script):
    run = _run(tmp_path)
    (run / "meta.json").write_text(json.dumps({"run_dir": "/Users/me/runs/seed0"}))
    with pytest.raises(ValueError, match=r"meta.json:1 still holds an absolute path \(/Users/me/"):
        results_script("publish_run").publish(
            run, docs / "results" / "explore" / "drone" / "seed0",
            root=tmp_path / "checkout", results_root=docs / "results",
        )  # fmt: skip


def test_publish_refuses_a_directory_that_is_not_a_run(tmp_path, results_script):
    with pytest.raises(FileNotFoundError, match="not a run directory"):
        results_script("publish_run").publish(tmp_path, tmp_path / "dest")


def test_pack_moves_an_older_folders_loose_records_into_its_archive(tmp_path, docs, results_script):
    publish_run = results_script("publish_run")
    folder = docs / "results" / "control"
    for seed in (0, 1):
        run = folder / "drone" / f"seed{seed}"
        for name in ("results.json", "stages/models.json", "control_errors.png"):
            (run / name).parent.mkdir(parents=True, exist_ok=True)
            (run / name).write_text(json.dumps(known_explore()[seed]))
    (folder / "drone" / "summary").mkdir()
    (folder / "drone" / "summary" / "summary_explore.json").write_text("{}")
    (folder / "run_seeds.sh").write_text("echo scripts stay files\n")
    packed = publish_run.repack(folder, results_root=docs / "results")
    assert len(packed) == 4
    assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()) == [
        "drone/seed0/results.json",
        "drone/seed1/results.json",
        "drone/summary/summary_explore.json",
        ARCHIVE,
        MANIFEST,
        "run_seeds.sh",
    ]
    assert sorted(read_members(folder)) == [
        f"drone/seed{s}/{n}" for s in (0, 1) for n in ("control_errors.png", "stages/models.json")
    ]
    assert not (folder / "drone" / "seed0" / "stages").exists()
    assert summarize([folder / "drone" / "seed1"])["archives"][0]["results"] == 1


def test_relative_paths_rewrites_only_paths_of_the_machine(results_script):
    rewrite = results_script("publish_run").relative_paths
    from pathlib import Path

    root = Path("/srv/main")
    text = '"run_dir": "/srv/runs/a/seed0", "x": "active / random", "y": "/dev/null"'
    assert (
        rewrite(text, root)
        == '"run_dir": "../runs/a/seed0", "x": "active / random", "y": "/dev/null"'
    )
    summary_dir = root / "docs/results/control/drone/summary"
    files = '"/srv/main/docs/results/control/drone/seed0/results.json"'
    assert rewrite(files, root, summary_dir) == '"../seed0/results.json"'
