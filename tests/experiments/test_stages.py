"""Stages: finished stages and parts are skipped on a re-run; wall time adds up across runs."""

from __future__ import annotations

import json
import zlib

import pytest
import torch
from torchrl.record.loggers import CSVLogger

from torchrl_recon.experiments.stages import Stages, StopRequested, stage_seed


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
    for i, seconds in ((0, 100.0), (1, 50.0)):  # pretend parts 0 and 1 took long the first time
        marker = tmp_path / "stages" / "squares" / f"part_{i}.json"
        record = json.loads(marker.read_text())
        record["wall_time_s"] = seconds
        del record["_sha256"]  # a hand edit must drop the hash: the record then reads as legacy
        marker.write_text(json.dumps(record))

    stages = Stages(tmp_path, seed=0)
    out = stages.run(
        "squares", lambda: {"values": [r["value"] for r in stages.run_parts("squares", 4, part)]}
    )
    assert out["values"] == [0, 1, 4, 9]
    assert calls == [0, 1, 2, 2, 3]  # only the missing parts ran again
    assert 150.0 <= out["wall_time_s"] < 150.9  # the earlier run's parts + this run's (short)


def test_stop_after_raises_after_the_named_stage(tmp_path):
    stages = Stages(tmp_path, seed=0, stop_after="first")
    with pytest.raises(StopRequested, match="first"):
        stages.run("first", lambda: {"x": 1})
    assert Stages(tmp_path, seed=0).run("first", lambda: {"x": 2})["x"] == 1


def test_each_stage_is_seeded_from_the_run_seed_and_its_name_alone(tmp_path):
    def draw():
        return {"x": torch.rand(3).tolist()}

    stages = Stages(tmp_path / "a", seed=7)
    torch.manual_seed(999)  # whatever ran before
    first = stages.run("fit", draw)["x"]
    torch.manual_seed(stage_seed(7, "fit"))
    assert first == torch.rand(3).tolist()
    stages.run("other", draw)
    torch.manual_seed(123)
    assert Stages(tmp_path / "b", seed=7).run("fit", draw)["x"] == first  # order plays no part
    assert Stages(tmp_path / "c", seed=8).run("fit", draw)["x"] != first
    assert Stages(tmp_path / "d", seed=7).run("fot", draw)["x"] != first


def test_stage_seed_is_stable_and_in_range():
    assert stage_seed(0, "random_data") == zlib.crc32(b"random_data") % (2**31 - 1)
    assert stage_seed(3, "fit") == (3 * 1_000_003 + zlib.crc32(b"fit")) % (2**31 - 1)
    seeds = {stage_seed(s, n) for s in range(5) for n in ("a", "b", "fit", "control")}
    assert len(seeds) == 20 and all(0 <= s < 2**31 - 1 for s in seeds)


def test_a_done_stage_is_skipped_and_leaves_the_same_random_state(tmp_path):
    calls = []

    def stage():
        calls.append(1)
        return {"x": torch.rand(2).tolist()}

    stages = Stages(tmp_path, seed=1)
    assert not stages.done("collect")
    record = stages.run("collect", stage)
    after_run = torch.rand(4)
    assert stages.done("collect") and calls == [1]
    assert stages.wall_time_s["collect"] == record["wall_time_s"] >= 0

    torch.manual_seed(5)  # a fresh process would start elsewhere
    again = Stages(tmp_path, seed=1).run("collect", stage)
    assert calls == [1]  # not run again
    assert (again["x"], again["wall_time_s"]) == (record["x"], record["wall_time_s"])  # stored
    torch.testing.assert_close(torch.rand(4), after_run)  # code after the stage draws the same


def test_run_parts_runs_each_part_once_in_order(tmp_path):
    stages = Stages(tmp_path, seed=0)
    seen = []
    records = stages.run_parts("episodes", 3, lambda i: seen.append(i) or {"i": i, "sq": i * i})
    assert seen == [0, 1, 2]
    assert [(r["i"], r["sq"]) for r in records] == [(0, 0), (1, 1), (2, 4)]
    assert all(r["wall_time_s"] >= 0 for r in records)
    again = Stages(tmp_path, seed=0).run_parts("episodes", 4, lambda i: {"i": i, "sq": -1})
    assert [r["sq"] for r in again] == [0, 1, 4, -1]  # only the new part 3 ran
    assert Stages(tmp_path, seed=0).run_parts("empty", 0, lambda i: {"i": i}) == []


def test_wall_times_are_measured_and_logged(tmp_path):
    logger = CSVLogger("log", log_dir=str(tmp_path / "logs"))
    stages = Stages(tmp_path / "new" / "run", seed=0, logger=logger)  # parents are created
    record = stages.run("quick", lambda: {"x": 1})
    assert 0.0 <= record["wall_time_s"] < 0.9  # a trivial stage, nothing added to it
    parts = stages.run_parts("parts", 2, lambda i: {"i": i})
    assert all(0.0 <= r["wall_time_s"] < 0.9 for r in parts)
    logged = (tmp_path / "logs" / "log" / "scalars" / "wall_time" / "quick.csv").read_text()
    step, value = logged.split()[0].split(",")
    assert int(step) == 0 and float(value) == pytest.approx(record["wall_time_s"])
