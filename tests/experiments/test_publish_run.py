"""docs/results/publish_run.py: what a published run directory keeps."""

from __future__ import annotations

import pytest


def test_publish_keeps_records_and_plots_but_not_buffers(tmp_path, results_script):
    run, dest = tmp_path / "run", tmp_path / "dest"
    files = [
        "config.yaml",
        "meta.json",
        "results.json",
        "table1.png",
        "control.log",
        "stages/models.json",
        "stages/setting_done.json",
        "stages/setting_done/part_0.json",
        "stages/setting_running/part_0.json",
        "buffers/random_data/storage/x.memmap",
        "checkpoints/models.pt",
        "wandb/run/file.json",
    ]
    for name in files:
        (run / name).parent.mkdir(parents=True, exist_ok=True)
        (run / name).write_text("x")

    copied = {
        p.relative_to(dest).as_posix() for p in results_script("publish_run").publish(run, dest)
    }
    assert copied == {
        "config.yaml",
        "meta.json",
        "results.json",
        "table1.png",
        "stages/models.json",
        "stages/setting_done.json",
        "stages/setting_running/part_0.json",  # a finished setting's parts are in its record
    }


def test_publish_refuses_a_directory_that_is_not_a_run(tmp_path, results_script):
    with pytest.raises(FileNotFoundError, match="not a run directory"):
        results_script("publish_run").publish(tmp_path, tmp_path / "dest")
