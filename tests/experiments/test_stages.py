"""Stages: finished stages and parts are skipped on a re-run; wall time adds up across runs."""

from __future__ import annotations

import json

import pytest

from torchrl_recon.experiments.stages import Stages, StopRequested


def test_run_parts_skips_finished_parts_and_sums_their_wall_time(tmp_path):
    calls = []

    def part(i):
        calls.append(i)
        if i == 2 and len(calls) == 3:  # the first run dies in part 2
            raise KeyboardInterrupt
        return {"value": i * i}

    stages = Stages(tmp_path, seed=0)
    with pytest.raises(KeyboardInterrupt):
        stages.run(
            "squares",
            lambda: {"values": [r["value"] for r in stages.run_parts("squares", 4, part)]},
        )
    assert not stages.done("squares") and calls == [0, 1, 2]
    part_1 = tmp_path / "stages" / "squares" / "part_1.json"
    record = json.loads(part_1.read_text())
    record["wall_time_s"] = 100.0  # pretend part 1 took long the first time
    del record["_sha256"]  # a hand edit must drop the hash: the record then reads as legacy
    part_1.write_text(json.dumps(record))

    stages = Stages(tmp_path, seed=0)
    out = stages.run(
        "squares", lambda: {"values": [r["value"] for r in stages.run_parts("squares", 4, part)]}
    )
    assert out["values"] == [0, 1, 4, 9]
    assert calls == [0, 1, 2, 2, 3]  # only the missing parts ran again
    assert out["wall_time_s"] >= 100.0  # includes the earlier run's parts


def test_stop_after_raises_after_the_named_stage(tmp_path):
    stages = Stages(tmp_path, seed=0, stop_after="first")
    with pytest.raises(StopRequested):
        stages.run("first", lambda: {"x": 1})
    assert Stages(tmp_path, seed=0).run("first", lambda: {"x": 2})["x"] == 1
