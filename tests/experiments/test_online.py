"""The online experiment kind: smoke runs on a shipped env and on a gymnasium env through
``env.id``, resumed after a stop, and its recipe checks."""

from __future__ import annotations

import json
import math
import uuid
from pathlib import Path

import pytest
import torch

from tests.experiments.tiny import short_env
from torchrl_recon.cli import main
from torchrl_recon.experiments.recipe import load_recipe
from torchrl_recon.experiments.run_dir import RunDirConflict, prepare_run_dir, release_run_dir

RECIPES = Path(__file__).resolve().parents[2] / "recipes"

COSTS = """
import torch


def pendulum(obs, action, next_obs):
    theta = torch.atan2(next_obs[..., 1], next_obs[..., 0])
    return theta.pow(2) + 0.1 * next_obs[..., 2].pow(2) + 0.001 * action[..., 0].pow(2)


def spinning(obs, action, next_obs):
    return next_obs[..., 2].abs() > 7.5
"""


@pytest.fixture
def costs(tmp_path, monkeypatch) -> str:
    name = f"online_costs_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{name}.py").write_text(COSTS)
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


def _results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


@pytest.mark.slow  # 5 s; the Pendulum online smoke (termination, resume) stays
def test_industrial_benchmark_online_smoke(tmp_path, capsys):
    out = tmp_path / "ib"
    code = main(["online", "industrial_benchmark/online_smoke", f"output_dir={out}"])
    assert code == 0, capsys.readouterr().err
    r = _results(out)
    assert [it["iteration"] for it in r["iterations"]] == [1, 2]
    assert [it["env_steps"] for it in r["iterations"]] == [120, 150]
    assert len(r["random"]["returns"]) == 3  # 90 random steps in 30-step episodes
    for it in r["iterations"]:
        assert len(it["returns"]) == 1 and math.isfinite(it["returns"][0])
        assert math.isfinite(it["model_error"]) and math.isfinite(it["mean_u"])
        assert 0 < it["replans"] <= 30 and it["fit_s"] > 0 and it["plan_s"] > 0
    assert (out / "learning_curve.png").stat().st_size > 0
    assert "online industrial_benchmark seed 0" in capsys.readouterr().out


@pytest.mark.slow  # 7 s; tests/fitting/test_online covers the exploration phase
def test_an_exploration_round_plays_before_control(tmp_path, capsys):
    out = tmp_path / "ib"
    args = ["online", "industrial_benchmark/online_smoke", f"output_dir={out}"]
    assert main([*args, "exploration.iterations=1", "exploration.cap=2.0"]) == 0
    explored = _results(out)["iterations"]
    assert [it["policy"] for it in explored] == ["explore", "mpc"]
    # an exploring round runs each plan open loop (re-planning every horizon), control re-plans
    # at every step
    assert explored[0]["replans"] < explored[1]["replans"]
    assert main([*args[:2], f"output_dir={tmp_path / 'control'}"]) == 0
    controlled = _results(tmp_path / "control")["iterations"]
    assert [it["policy"] for it in controlled] == ["mpc", "mpc"]
    assert controlled[0]["returns"] != explored[0]["returns"]
    capsys.readouterr()


def test_pendulum_online_smoke_with_a_termination_resumes_to_the_same_numbers(
    costs, tmp_path, capsys
):
    args = ["online", "gym/online_smoke", "env.id=Pendulum-v1", f"env.cost={costs}:pendulum"]
    args += [f"env.termination={costs}:spinning"]
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    assert main([*args, f"output_dir={whole}"]) == 0, capsys.readouterr().err
    # warmup auto (the default) is random here: 25-step episodes hold a training slice, so the
    # run stopped and resumed with warmup=random gives the same numbers
    args_random = [*args, "warmup=random"]
    assert main([*args_random, f"output_dir={parts}", "stop_after=play_1"]) == 0
    assert not (parts / "results.json").exists()
    assert main([*args_random, f"output_dir={parts}"]) == 0, capsys.readouterr().err
    a, b = _results(whole), _results(parts)
    for r in (a, b):
        for it in r["iterations"]:
            for key in ("fit_s", "plan_s", "env_s", "wall_time_s"):
                it.pop(key)
        r.pop("first_fit"), r.pop("meta")  # wall times; when and how each ran
    assert a == b and "warmup" not in a  # results name a warm-up other than random only
    assert a["env"] == "Pendulum-v1" and len(a["iterations"]) == 2


def test_a_run_dir_made_with_warmup_random_resumes_with_it_not_with_the_new_default(tmp_path):
    """Online run dirs written before ``warmup: auto`` say ``warmup: random``: resuming one
    under the default is one clear conflict naming the key; ``warmup=random`` resumes it."""
    base = [f"output_dir={tmp_path / 'run'}", "env.id=Pendulum-v1"]
    base += ["env.cost=torchrl_recon.envs.gym_costs:pendulum"]
    old = load_recipe(RECIPES / "gym" / "online_smoke.yaml", [*base, "warmup=random"])
    release_run_dir(prepare_run_dir(old))
    with pytest.raises(RunDirConflict, match=r"warmup: 'random' -> 'auto'"):
        prepare_run_dir(load_recipe(RECIPES / "gym" / "online_smoke.yaml", base))
    resumed = prepare_run_dir(old)
    release_run_dir(resumed)
    assert json.loads((resumed / "meta.json").read_text())["resumed"] is True


def test_online_recipe_errors_before_any_work(costs, tmp_path, capsys):
    out = tmp_path / "bad"
    base = ["online", "gym/online_smoke", "env.id=Pendulum-v1", f"env.cost={costs}:pendulum"]
    for override, expected in (
        ("planner.kind=mpc", "'planner.kind'"),
        ("random_steps=20", "'random_steps'"),
        ("warmup=sometimes", "'warmup'"),
        ("refit_old_steps=0", "'refit_old_steps'"),
        ("exploration.iterations=3", "'exploration.iterations' must be at most iterations = 2"),
        ("exploration.beta=1", "'exploration.beta'"),
        ("exploration.cap=1.1", "'exploration.cap' must be null or above exploration.ratio = 1.2"),
    ):
        assert main([*base, f"output_dir={out}", override]) == 2
        err = capsys.readouterr().err
        assert expected in err, err
        assert not out.exists()


def test_refits_on_the_new_steps_and_a_sample_of_the_old_run_from_the_recipe(
    costs, tmp_path, capsys
):
    args = ["online", "gym/online_smoke", "env.id=Pendulum-v1", f"env.cost={costs}:pendulum"]
    out = tmp_path / "mixed"
    assert main([*args, f"output_dir={out}", "refit_old_steps=25"]) == 0, capsys.readouterr().err
    r = _results(out)
    assert len(r["iterations"]) == 2 and all(math.isfinite(it["fit_s"]) for it in r["iterations"])
    capsys.readouterr()


@pytest.mark.slow  # 10 s; a saving of fit time, its setting checked in test_online_options
def test_the_estimator_is_refitted_only_when_the_plans_read_u(costs, tmp_path, capsys):
    """beta = 0, re-planning every step and no exploring round: refits leave the estimator as
    the first fit made it, and the plans (which never read u) are the same as with
    ``refit_uncertainty=always``; only the u of the new steps differs."""
    args = ["online", "gym/online_smoke", "env.id=Pendulum-v1", f"env.cost={costs}:pendulum"]
    runs = {}
    for mode in ("auto", "always"):
        out = tmp_path / mode
        assert main([*args, f"output_dir={out}", f"refit_uncertainty={mode}"]) == 0
        runs[mode] = _results(out)["iterations"]
    auto, always = runs["auto"], runs["always"]
    assert [sorted(it["val_loss"]) for it in auto] == [["world_model"]] * 2
    assert [sorted(it["val_loss"]) for it in always] == [["uncertainty", "world_model"]] * 2
    for key in ("returns", "model_error", "replans"):
        assert [it[key] for it in auto] == [it[key] for it in always]
    assert auto[0]["mean_u"] == always[0]["mean_u"]  # before any refit
    assert auto[1]["mean_u"] != always[1]["mean_u"]  # after one
    # a round that explores reads u: the refit before it fits the estimator
    out = tmp_path / "explore"
    assert main([*args, f"output_dir={out}", "exploration.iterations=2"]) == 0
    assert [sorted(it["val_loss"]) for it in _results(out)["iterations"]] == [
        ["uncertainty", "world_model"],
        ["world_model"],
    ]
    capsys.readouterr()


def test_a_run_dir_made_before_refit_uncertainty_resumes_with_always(tmp_path):
    """Online run dirs written before ``refit_uncertainty`` refitted the estimator every time:
    such a config reads as ``always``, so resuming under ``auto`` is one clear conflict;
    ``refit_uncertainty=always`` resumes it."""
    base = [f"output_dir={tmp_path / 'run'}", "env.id=Pendulum-v1"]
    base += ["env.cost=torchrl_recon.envs.gym_costs:pendulum"]
    old = load_recipe(RECIPES / "gym" / "online_smoke.yaml", base)
    run_dir = prepare_run_dir(old)
    release_run_dir(run_dir)
    saved = (run_dir / "config.yaml").read_text()
    (run_dir / "config.yaml").write_text(saved.replace("refit_uncertainty: auto\n", ""))
    with pytest.raises(RunDirConflict, match="refit_uncertainty: 'always' -> 'auto'") as err:
        prepare_run_dir(old)
    assert "resume it as it was made with refit_uncertainty=always" in str(err.value)
    resumed = load_recipe(
        RECIPES / "gym" / "online_smoke.yaml", [*base, "refit_uncertainty=always"]
    )
    release_run_dir(prepare_run_dir(resumed))


def _short_env_args(tmp_path, monkeypatch) -> list[str]:
    return ["online", "gym/online_smoke", *short_env(tmp_path, monkeypatch)]


def test_episodes_shorter_than_a_training_window_train_on_padded_slices(
    tmp_path, monkeypatch, capsys
):
    out = tmp_path / "short"
    assert main([*_short_env_args(tmp_path, monkeypatch), f"output_dir={out}"]) == 0
    assert "warm-up plan" in capsys.readouterr().out  # the table's title names it
    results = json.loads((out / "results.json").read_text())
    # auto: most random episodes are shorter than a training slice
    assert results["warmup"] == "plan"
    # 3-step episodes: the smoke recipe's 75 random steps hold 25, each with its return
    assert len(results["random"]["returns"]) == 25
    assert all(math.isfinite(loss) for loss in results["first_fit"].values())


def test_padded_slices_with_an_estimator_that_takes_no_mask_are_one_clear_error(
    tmp_path, monkeypatch, capsys
):
    args = [*_short_env_args(tmp_path, monkeypatch), "models.uncertainty.kind=ensemble"]
    assert main([*args, f"output_dir={tmp_path / 'short'}"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and "models.uncertainty.kind = ensemble cannot train" in err[0], err


def test_random_steps_below_an_episode_and_a_slice_run_where_episodes_end_early(
    tmp_path, monkeypatch, capsys
):
    """With ``env.termination``, ``random_steps`` need not reach ``env.episode_steps`` (25) +
    ``training.slice_len`` (10): 12 steps of 3-step episodes are four episodes to split."""
    args = ["online", "gym/online_smoke", *short_env(tmp_path, monkeypatch, termination=True)]
    out = tmp_path / "short"
    assert main([*args, "random_steps=12", "stop_after=models", f"output_dir={out}"]) == 0
    assert (out / "checkpoints" / "models.pt").exists(), capsys.readouterr().err


def test_random_data_with_fewer_than_two_episodes_are_one_error_before_any_fit(
    costs, tmp_path, capsys
):
    """Where episodes may end (``env.termination``) but do not, the random data are checked once
    collected: 26 steps of 25-step episodes leave one episode and a 1-step piece."""
    args = ["online", "gym/online_smoke", "env.id=Pendulum-v1", f"env.cost={costs}:pendulum"]
    out = tmp_path / "pendulum"
    args += [f"env.termination={costs}:spinning", "random_steps=26", f"output_dir={out}"]
    assert main(args) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and "'random_steps' = 26 gave 1 episode that ended or held" in err[0]
    assert "env.episode_steps + training.slice_len = 35" in err[0], err
    assert (out / "stages" / "random_data.json").exists()  # collected and kept
    assert not (out / "checkpoints").exists()  # refused before the first fit


def test_fit_cuda_graph_needs_members_a_cuda_device_and_no_compile(tmp_path, capsys):
    """``fit_cuda_graph: true``: refused before the run directory without members, on the CPU
    or beside the world model's ``compile``; with them, the fits' schedule takes it."""
    from torchrl_recon.experiments.online import recipe_schedule

    out = tmp_path / "run"
    base = [
        "online",
        "industrial_benchmark/online_smoke",
        f"output_dir={out}",
        "fit_cuda_graph=true",
    ]
    cases = [
        ([], "'world_model_members' must be at least 2 with fit_cuda_graph"),
        (["world_model_members=2", "device=cpu"], "'device' must be a CUDA device"),
        (
            ["world_model_members=2", "device=cuda", "training.world_model.compile=true"],
            "'training.world_model.compile' must be false with fit_cuda_graph",
        ),
    ]
    if not torch.cuda.is_available():
        cases.append((["world_model_members=2"], "'fit_cuda_graph' needs a CUDA device"))
    for extra, words in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, err
    assert not out.exists()
    recipe = RECIPES / "industrial_benchmark" / "online_smoke.yaml"
    graph = ["fit_cuda_graph=true", "world_model_members=2", "device=cuda"]
    assert recipe_schedule(load_recipe(recipe, graph)).cuda_graph is True
    assert recipe_schedule(load_recipe(recipe, [])).cuda_graph is False
