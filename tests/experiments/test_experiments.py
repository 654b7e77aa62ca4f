"""The two experiments at toy scale: outputs exist and are finite; a stopped run resumes to the same numbers."""

from __future__ import annotations

import json
import math

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_recon.experiments import control, explore
from torchrl_recon.experiments.config import ControlConfig, ExploreConfig
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.stages import StopRequested
from torchrl_recon.planners.beta import cost_to_u_ratio
from torchrl_recon.runs.files import with_hash


def run_explore(cfg, run_dir, logger):
    """One explore run in ``run_dir`` without the runner (no results.json, no figures)."""
    return explore.run(RunContext(cfg, run_dir, logger))


def run_control(cfg, run_dir, logger):
    """One control run in ``run_dir`` without the runner."""
    return control.run(RunContext(cfg, run_dir, logger))


TRAINING = {
    "slice_len": 15,
    "num_slices": 8,
    "world_model": {"steps": 40, "eval_every": 20},
    "uncertainty": {"steps": 40, "eval_every": 20},
}


def _explore_cfg(**extra):
    return OmegaConf.merge(
        OmegaConf.structured(ExploreConfig),
        {
            "env": {"name": "industrial_benchmark", "episode_steps": 50},
            "progress": False,
            "models": {"window": 5},
            "training": TRAINING,
            "initial_random_steps": 300,
            "validation": {"trajectories": 4, "steps": 20},
            "guided": {
                "steps": 200,
                "refit_every_episodes": 2,
                "planner": {"kwargs": {"horizon": 10, "num_candidates": 64}},
            },
            "random_steps": 200,
            "retrainings": 2,
            "logger": {"backend": "none"},
        },
        extra,
    )


def _control_cfg(**extra):
    planner = {"kwargs": {"horizon": 10, "num_candidates": 64}}
    return OmegaConf.merge(
        OmegaConf.structured(ControlConfig),
        {
            "env": {"name": "drone", "episode_steps": 30},
            "progress": False,
            "models": {"window": 5},
            "training": TRAINING,
            "random_episodes": 3,
            "random_episode_steps": 100,
            "episodes": 2,
            "warmup_random_steps": 5,
            "logger": {"backend": "none"},
            "settings": [
                {"name": "baseline", "planner": planner},
                {"name": "u_low", "planner": planner, "band": {"low": 0.0, "high": 0.33}},
                {
                    "name": "gradient",
                    "planner": {
                        "kind": "gradient",
                        "kwargs": {"horizon": 10, "restarts": 2, "steps": 3},
                    },
                    "beta": 0.1,
                    "beta_relative": True,
                },
            ],
        },
        extra,
    )


@pytest.mark.slow  # 10 s; test_cli_errors' SIGINT test resumes the explore smoke and checks its output
def test_explore_outputs_and_resume(tmp_path):
    full = run_explore(_explore_cfg(), tmp_path / "full", None)
    assert set(full["arms"]) == {"random", "active"}
    for arm in full["arms"].values():
        assert len(arm["mse"]) == 2 and all(math.isfinite(v) and v > 0 for v in arm["mse"])
    assert math.isfinite(full["ratio"])
    assert full["data"] == {
        **full["data"],
        "initial_steps": 300,
        "random_arm_steps": 200,
        "active_arm_steps": 200,
    }
    assert (tmp_path / "full" / "buffers" / "initial_random" / "storage").is_dir()
    assert (tmp_path / "full" / "checkpoints" / "initial_models.pt").is_file()

    with pytest.raises(StopRequested):
        run_explore(_explore_cfg(stop_after="guided_data_1"), tmp_path / "resumed", None)
    resumed = run_explore(_explore_cfg(), tmp_path / "resumed", None)
    assert resumed["arms"] == full["arms"]


def test_control_outputs_and_resume(tmp_path):
    full = run_control(_control_cfg(), tmp_path / "full", None)
    assert set(full["settings"]) == {"baseline", "u_low", "gradient"}
    for setting in full["settings"].values():
        assert len(setting["episodes"]) == 2
        for key in ("prediction_mse", "cost_error", "real_cost", "predicted_cost"):
            assert math.isfinite(setting["mean"][key])
        assert setting["mean"]["replans"] >= 1
    example = full["trajectory_example"]
    assert len(example["real"]) == len(example["predicted"]) == len(example["uncertainty"]) > 0
    # the relative β is 0.1 in units of the random data's mean |cost| / mean u
    assert full["beta_unit"] > 0
    assert full["settings"]["gradient"]["beta_effective"] == pytest.approx(0.1 * full["beta_unit"])
    assert "beta_effective" not in full["settings"]["baseline"]

    with pytest.raises(StopRequested):
        run_control(_control_cfg(stop_after="setting_baseline"), tmp_path / "resumed", None)
    resumed = run_control(_control_cfg(), tmp_path / "resumed", None)
    assert resumed["settings"] == full["settings"]


def test_control_error_threshold_replans_where_the_state_leaves_the_plan(tmp_path):
    cfg = _control_cfg(replan={"mode": "every_n", "every": 100, "error_threshold": 1e-9})
    cfg.settings = cfg.settings[:1]
    episodes = run_control(cfg, tmp_path, None)["settings"]["baseline"]["episodes"]
    # no prediction is exact to 1e-9: a re-plan at every step after the random warm-up, where
    # every 100 alone gives one per episode
    planned_steps = [e["steps"] - cfg.warmup_random_steps for e in episodes]
    assert [e["replans"] for e in episodes] == planned_steps
    assert all(n > 1 for n in planned_steps)


def test_control_setting_stopped_between_episodes_resumes_at_the_next_episode(tmp_path):
    """A setting killed after its first episode keeps that episode and reruns only the rest."""
    full = run_control(_control_cfg(), tmp_path / "full", None)
    stages = tmp_path / "full" / "stages"
    # what a kill during episode 1 of the last setting leaves behind: part_0 only, no marker
    (stages / "setting_gradient.json").unlink()
    (stages / "setting_gradient" / "part_1.json").unlink()
    kept = stages / "setting_gradient" / "part_0.json"
    record = json.loads(kept.read_text())
    record.pop("_sha256")  # an edited part is written with its new hash, as Stages writes one
    kept.write_text(json.dumps(with_hash({**record, "kept_from_before": True})))

    resumed = run_control(_control_cfg(), tmp_path / "full", None)
    assert resumed["settings"] == full["settings"]
    assert '"kept_from_before": true' in kept.read_text()  # episode 0 was not run again
    assert (stages / "setting_gradient" / "part_1.json").is_file()


def test_relative_beta_refuses_data_without_cost_or_u():
    data = TensorDict({"next": {"reward": torch.zeros(4, 1)}}, [4])
    with pytest.raises(ValueError, match="mean |cost| = 0.0"):
        cost_to_u_ratio(data, torch.ones(3))
    data = TensorDict({"next": {"reward": torch.ones(4, 1)}}, [4])
    with pytest.raises(ValueError, match="mean u = nan"):
        cost_to_u_ratio(data, torch.tensor([float("nan")]))


@pytest.mark.parametrize(
    ("run", "make_cfg", "data_stage", "models_stage"),
    [
        (run_control, _control_cfg, "random_data", "models"),
        (run_explore, _explore_cfg, "initial_random", "initial_models"),
    ],
    ids=["control", "explore"],
)
def test_run_stopped_before_its_models_fits_the_same_models(
    tmp_path, run, make_cfg, data_stage, models_stage
):
    """The networks are built between two stages from the global RNG: a resumed run restores
    the state the finished stage left, so it fits the models a run without a stop fits (the
    same validation losses to the last bit)."""
    with pytest.raises(StopRequested):
        run(make_cfg(stop_after=models_stage), tmp_path / "straight", None)
    for stop in (data_stage, models_stage):
        with pytest.raises(StopRequested):
            run(make_cfg(stop_after=stop), tmp_path / "stopped", None)
    for name in ("straight", "stopped"):
        assert (tmp_path / name / "stages" / f"{data_stage}.rng.pt").is_file()
    records = [
        json.loads((tmp_path / name / "stages" / f"{models_stage}.json").read_text())
        for name in ("straight", "stopped")
    ]
    for record in records:
        record.pop("wall_time_s"), record.pop("_sha256")  # the record's hash covers its wall time
    assert records[0] == records[1]  # the checkpoints' hashes included
