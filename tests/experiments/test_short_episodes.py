"""Envs whose episodes end before a training window (issue 33): the control kind plans them from
the first step, the explore kind refuses Table 1's protocol at once unless its validation
trajectories fit, and the online kind's per-iteration model error and mean u are computed on
the windows that exist."""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict

from tests.experiments.tiny import TINY, short_env
from torchrl_recon.cli import main
from torchrl_recon.data import TRAJ_KEY
from torchrl_recon.fitting.online import mean_uncertainty, model_error
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners.beta import window_uncertainty

FAST_CONTROL = [*TINY, "episodes=2", "random_episodes=4", "random_episode_steps=12"]


def _error_lines(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]


def test_control_on_episodes_of_3_steps_plans_them_from_the_first_step(
    tmp_path, monkeypatch, capsys
):
    out = tmp_path / "control"
    args = ["control", "gym/control_smoke", *short_env(tmp_path, monkeypatch), *FAST_CONTROL]
    assert main([*args, "replan.mode=uncertainty", f"output_dir={out}"]) == 0
    assert "warm-up plan)" in capsys.readouterr().out  # the table's title names it
    results = json.loads((out / "results.json").read_text())
    # the threshold and β's unit come from the padded episodes' windows
    assert math.isfinite(results["replan_threshold"]) and results["replan_threshold"] > 0
    assert math.isfinite(results["beta_unit"]) and results["beta_unit"] > 0
    # auto: most random episodes are shorter than a training slice
    assert results["warmup"] == "plan"
    for setting in results["settings"].values():
        assert setting["ended_in_warmup"] == 0
        assert all(e["steps"] == 3 and e["replans"] >= 1 for e in setting["episodes"])
        assert math.isfinite(setting["mean"]["prediction_mse"])


def test_explore_on_episodes_of_3_steps_is_one_clear_error_before_any_fit(
    tmp_path, monkeypatch, capsys
):
    out = tmp_path / "explore"
    args = ["explore", "gym/explore_smoke", *short_env(tmp_path, monkeypatch), *TINY]
    assert main([*args, "validation.trajectories=2", f"output_dir={out}"]) == 2
    err = _error_lines(capsys)
    assert len(err) == 1, err
    for part in ("models.window = 3", "validation.steps = 20", "longest 3", "control or online"):
        assert part in err[0], err[0]
    assert not (out / "checkpoints").exists()  # refused before the first fit
    assert not (out / "stages" / "initial_random.json").exists()


@pytest.mark.slow  # 5 s; explore's 3-step error stays
def test_calibrate_on_episodes_of_3_steps_is_one_clear_error_before_any_fit(
    tmp_path, monkeypatch, capsys
):
    args = ["calibrate", "industrial_benchmark/calibrate_smoke", *short_env(tmp_path, monkeypatch)]
    args += ["env.name=short", "random_steps=120", "outcomes.explore_recipe=null"]
    args += ["outcomes.control_recipe=null"]
    # the evaluation's held-out trajectories (models.window + evaluation.horizon = 15 steps)
    out = tmp_path / "long"
    assert main([*args, f"output_dir={out}"]) == 2
    err = _error_lines(capsys)
    assert len(err) == 1 and "no random episode lasted 15 steps" in err[0], err
    assert "models.window + evaluation.horizon" in err[0]
    assert sorted(p.name for p in (out / "stages").glob("*.json")) == ["random_data.json"]
    # trajectories that fit the episodes: an estimator that cannot train on padded slices
    out = tmp_path / "padded"
    fit = ["models.window=1", "evaluation.horizon=2"]
    assert main([*args, *fit, f"output_dir={out}"]) == 2
    err = _error_lines(capsys)
    assert len(err) == 1 and "estimators[1].kind = ensemble cannot train on padded" in err[0]
    assert sorted(p.name for p in (out / "stages").glob("*.json")) == ["random_data.json"]


def test_explore_runs_when_the_validation_trajectories_fit_the_episodes(tmp_path, monkeypatch):
    out = tmp_path / "explore"
    args = ["explore", "gym/explore_smoke", *short_env(tmp_path, monkeypatch), *TINY]
    fit = ["models.window=2", "validation.steps=1", "validation.trajectories=2", "retrainings=2"]
    assert main([*args, *fit, f"output_dir={out}"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert all(math.isfinite(v) for arm in results["arms"].values() for v in arm["mse"])


def _episodes(count: int, steps: int) -> TensorDict:
    n = count * steps
    return TensorDict(
        {
            "observation": torch.randn(n, 2),
            "action": torch.rand(n, 1) * 2 - 1,
            ("next", "observation"): torch.randn(n, 2),
            TRAJ_KEY: torch.arange(n) // steps,
        },
        [n],
    )


def test_model_error_on_episodes_shorter_than_a_slice_counts_each_real_step_once():
    torch.manual_seed(0)
    world, data = LSTMWorldModel(2, 1, window=2), _episodes(5, 3)
    world.fit_normalization(data["observation"], data["action"], data["next", "observation"])
    errors = []
    with torch.no_grad():
        for episode in data.reshape(5, 3):  # each whole episode, no padding
            delta = episode["next", "observation"] - episode["observation"]
            pred = world.predict_delta(episode["observation"][None], episode["action"][None])[0]
            errors.append((pred - world.delta_norm.normalize(delta)).pow(2))
    expected = float(torch.cat(errors).mean())
    assert math.isclose(model_error(world, data, 10), expected, rel_tol=1e-5)
    # long episodes: the windows of 10 steps, as before
    assert math.isfinite(model_error(world, _episodes(2, 12), 10))


def test_mean_u_on_episodes_shorter_than_the_window_scores_them_started_at_rest():
    torch.manual_seed(0)
    est, data = ReconstructionUncertainty(2, 1, window=4), _episodes(5, 3)
    episodes = data.reshape(5, 3)
    obs, action = episodes["observation"], episodes["action"]
    at_rest = torch.cat([obs[:, :1], obs], 1), torch.cat([torch.zeros(5, 1, 1), action], 1)
    with torch.no_grad():
        expected = est.score(*at_rest).flatten()  # one window each, ending at the last step
    torch.testing.assert_close(window_uncertainty(data, est), expected)
    assert math.isclose(mean_uncertainty(est, data), float(expected.mean()), rel_tol=1e-6)


def test_online_on_episodes_of_3_steps_records_model_error_and_mean_u(tmp_path, monkeypatch):
    out = tmp_path / "online"
    args = ["online", "gym/online_smoke", *short_env(tmp_path, monkeypatch), *TINY]
    assert main([*args, f"output_dir={out}"]) == 0
    iterations = json.loads((out / "results.json").read_text())["iterations"]
    assert len(iterations) == 2
    for it in iterations:
        assert math.isfinite(it["model_error"]) and math.isfinite(it["mean_u"]), it


def test_auto_warmup_plans_where_most_random_episodes_are_short():
    """One random episode that lasted a training slice (InvertedPendulum's reach 20-26 steps now
    and then) does not make the warm-up random; most episodes that long do."""
    from omegaconf import OmegaConf

    from torchrl_recon.experiments.random_data import warmup_mode

    cfg = OmegaConf.create({"warmup": "auto", "training": {"slice_len": 5}})

    def data(lengths: list[int]) -> TensorDict:
        ids = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
        return TensorDict({TRAJ_KEY: ids}, [len(ids)])

    assert warmup_mode(cfg, data([3, 2, 6, 4])) == "plan"  # one of four holds a slice
    assert warmup_mode(cfg, data([3, 6, 6, 7])) == "random"  # three of four do
    assert warmup_mode(cfg, data([20, 3])) == "random"  # a full episode and a budget's rest
