"""docs/results/control_tables.py: tables and partial results from a run's stage records."""

from __future__ import annotations

import json

import yaml

from torchrl_recon.evaluation.mpc import METRICS


def _episode(value: float) -> dict:
    return {key: value for key in METRICS}


def test_unfinished_setting_is_reported_with_its_finished_episodes(tmp_path, results_script):
    tables = results_script("control_tables")
    settings = [{"name": "baseline"}, {"name": "gradient"}, {"name": "not_started"}]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({"settings": settings, "episodes": 10}))
    stages = tmp_path / "stages"
    (stages / "setting_gradient").mkdir(parents=True)
    baseline = [_episode(v) for v in (1.0, 2.0, 3.0)]
    (stages / "setting_baseline.json").write_text(
        json.dumps({"episodes": baseline, "mean": _episode(2.0), "std": _episode(1.0)})
    )
    for i, value in enumerate((4.0, 6.0, 5.0)):
        record = {"metrics": _episode(value), "trajectory_example": None, "wall_time_s": 1.0}
        (stages / "setting_gradient" / f"part_{i}.json").write_text(json.dumps(record))

    found = tables.settings_so_far(tmp_path)
    assert list(found) == ["baseline", "gradient"]
    assert found["gradient"]["unfinished"] == "3 of 10 episodes"
    assert found["gradient"]["mean"]["prediction_mse"] == 5.0
    assert "| gradient (3 of 10 episodes) | 5 ± 1 |" in tables.table(found)


def test_a_published_runs_records_are_read_from_its_folders_archive(tmp_path, results_script):
    from torchrl_recon.runs.archive import pack

    tables = results_script("control_tables")
    run = tmp_path / "control" / "drone" / "seed0"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump({"settings": [{"name": "baseline"}]}))
    record = {"episodes": [_episode(1.0)], "mean": _episode(1.0), "std": _episode(0.0)}
    members = {"drone/seed0/stages/setting_baseline.json": json.dumps(record).encode()}
    pack(tmp_path / "control", members, {})
    assert not (run / "stages").exists()
    assert tables.settings_so_far(run) == {"baseline": record}
