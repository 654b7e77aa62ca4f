"""benchmarks/planner_ceiling.py plans with MuJoCo itself as the model: at a tiny size it prints
each episode's return and the mean, appends the record to ``--out``, and its simulator model
predicts what the env then does."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.scripts import load_script

pytest.importorskip("mujoco")

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "planner_ceiling.py"


def test_a_tiny_run_prints_each_episode_and_appends_its_record(tmp_path, capsys, monkeypatch):
    ceiling = load_script(SCRIPT)
    out = tmp_path / "ceiling.jsonl"
    args = ["--task", "InvertedPendulum-v5", "--planner", "cem", "--candidates", "20"]
    args += ["--iterations", "2", "--horizon", "5", "--episodes", "2", "--steps", "30"]
    args += ["--shape", '{"0": 0.5}']
    monkeypatch.setattr(sys, "argv", ["planner_ceiling.py", *args, "--out", str(out)])
    ceiling.main()
    printed = capsys.readouterr().out
    assert printed.count("  episode ") == 2 and "mean return" in printed
    assert "step 25: return" in printed  # the progress of a long episode
    (record,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(record["episodes"]) == 2 and record["steps"] == 30
    assert all(0 < e["length"] <= 30 and e["return"] > 0 for e in record["episodes"])
    assert all(len(e["last_obs"]) == 4 for e in record["episodes"]) and record["shape"] == {
        "0": 0.5
    }


def test_shape_adds_the_named_squared_entries_and_refuses_an_entry_the_task_lacks(
    monkeypatch, capsys
):
    ceiling = load_script(SCRIPT)
    cost = ceiling.shaped(lambda s, a, s2: s2.sum(-1), {0: 3.0, 2: 1.0, "a": 0.5})
    got = cost(None, torch.tensor([[1.0, 2.0]]), torch.tensor([[2.0, 1.0, -1.0]]))
    torch.testing.assert_close(got, torch.tensor([2.0 + 12.0 + 1.0 + 0.5 * 5.0]))
    args = ["planner_ceiling.py", "--task", "InvertedPendulum-v5", "--shape", '{"4": 1}']
    monkeypatch.setattr(sys, "argv", args)
    with pytest.raises(SystemExit):
        ceiling.main()
    assert "--shape names observation entries [4]; InvertedPendulum-v5 has 4" in (
        capsys.readouterr().err
    )


def test_the_simulator_model_predicts_what_the_env_does():
    """Rolled out from the env's state, a candidate's first imagined observation is the one the
    env reaches with that action (the model is the simulator, frame_skip included)."""
    import gymnasium as gym

    ceiling = load_script(SCRIPT)
    env = gym.make("InvertedPendulum-v5")
    obs, _ = env.reset(seed=0)
    sim = ceiling.SimulatorModel(env, ceiling.TASKS["InvertedPendulum-v5"][0])
    actions = torch.tensor([[[0.5], [-0.2]]])  # one candidate, two steps
    imagined = sim.imagine(None, None, None, actions)
    first, *_ = env.step(actions[0, 0].numpy())
    second, *_ = env.step(actions[0, 1].numpy())
    torch.testing.assert_close(
        imagined[0], torch.from_numpy(np.stack([first, second])).float(), atol=1e-5, rtol=0
    )
