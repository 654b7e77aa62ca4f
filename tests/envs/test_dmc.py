"""DeepMind Control tasks (the ``dmc`` extra) through make_env and the recipes/dmc recipes.

One test runs without the extra (a ``dmc:`` id is one error line naming it); the others need
dm_control and are skipped without it."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch

from torchrl_recon.cli import main
from torchrl_recon.envs import get_entry, make_env
from torchrl_recon.envs.dmc import INSTALL, MissingExtraError

ROOT = Path(__file__).resolve().parents[2]
DMC = ROOT / "recipes" / "dmc"
HAS_DMC = importlib.util.find_spec("dm_control") is not None
# dm_control looks for a display to render with (never used here)
pytestmark = pytest.mark.filterwarnings("ignore:.*DISPLAY environment variable")
needs_dmc = pytest.mark.skipif(not HAS_DMC, reason=f"no dm_control ({INSTALL})")
if HAS_DMC:  # absl (dm_control's logging) writes to the stderr of its import; Hydra's logging
    # setup closes every handler, and absl's closes its stream unless it is sys.stderr now: under
    # pytest's capture that is a capture stream of an earlier test. Give it one never closed.
    from absl import logging as absl_logging

    absl_logging.get_absl_handler().python_handler.setStream(sys.__stderr__)
# id, observation dims, action dims
TASKS = [("dmc:cartpole/swingup", 5, 1), ("dmc:reacher/easy", 6, 2), ("dmc:pendulum/swingup", 3, 1)]


def _errors(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error:")]


def test_without_the_extra_a_dmc_id_is_one_line_naming_the_extra(tmp_path, capsys, monkeypatch):
    if HAS_DMC:  # hide dm_control, as on a machine without the extra
        find_spec = importlib.util.find_spec
        monkeypatch.setattr(
            importlib.util,
            "find_spec",
            lambda n, *a: None if n == "dm_control" else find_spec(n, *a),
        )
    with pytest.raises(MissingExtraError, match="dm_control is not installed") as e:
        make_env("dmc:cartpole/swingup", seed=0)
    assert isinstance(e.value, ValueError) and str(e.value).endswith(INSTALL)
    out = tmp_path / "run"
    code = main(["online", str(DMC / "online_cartpole_swingup.yaml"), f"output_dir={out}"])
    err = capsys.readouterr().err
    assert code == 2 and len(_errors(err)) == 1 and INSTALL in err and "'env.id'" in err, err
    assert not out.exists()


@needs_dmc
@pytest.mark.parametrize("dmc_id, n_obs, n_act", TASKS)
def test_make_env_gives_one_float_observation_and_the_task_s_actions(dmc_id, n_obs, n_act):
    env = make_env(dmc_id, seed=0, frame_skip=2, max_episode_steps=500)
    assert env.observation_spec["observation"].shape == (n_obs,)
    assert env.observation_spec["observation"].dtype == torch.float32
    assert env.action_spec.shape == (n_act,) and env.action_spec.dtype == torch.float32
    assert env.action_spec.space.low.tolist() == [-1.0] * n_act
    assert len(get_entry(dmc_id).state_names) == n_obs
    td = env.rollout(4)
    assert td["next", "observation"].shape == (4, n_obs)
    assert td["next", "reward"].dtype == torch.float32
    assert td["next", "step_count"].flatten().tolist() == [1, 2, 3, 4]
    assert not td["next", "done"].any()
    env.close()


@needs_dmc
def test_a_seed_reproduces_its_episode_and_another_differs():
    def run(seed: int) -> torch.Tensor:
        env = make_env("dmc:pendulum/swingup", seed=seed, frame_skip=2)
        torch.manual_seed(0)  # the random actions
        obs = env.rollout(5)["next", "observation"]
        env.close()
        return obs

    assert torch.equal(run(3), run(3))
    assert not torch.equal(run(3), run(4))


@needs_dmc
def test_a_batch_of_seeded_envs_truncates_at_max_episode_steps():
    env = make_env("dmc:cartpole/swingup", seed=[1, 2], parallel=False, frame_skip=2)
    reset = env.reset()["observation"]
    assert reset.shape == (2, 5) and not torch.equal(reset[0], reset[1])
    env.close()
    env = make_env("dmc:reacher/easy", seed=0, num_envs=2, parallel=False, max_episode_steps=3)
    td = env.rollout(5, break_when_any_done=False)
    assert td.shape == (2, 5)
    assert td["next", "truncated"].squeeze(-1)[:, 2].all() and td["next", "done"].sum() == 2
    env.close()


@needs_dmc
def test_an_episode_is_the_suite_s_1000_steps_at_frame_skip_2():
    env = make_env("dmc:pendulum/swingup", seed=0, frame_skip=2)
    td = env.rollout(600)
    assert td.shape == (500,) and td["next", "truncated"][-1].item()
    env.close()


@needs_dmc
@pytest.mark.parametrize("stem", ["cartpole_swingup", "reacher_easy", "pendulum_swingup"])
def test_each_recipe_is_valid_at_100k_agent_steps_with_action_repeat_2(stem):
    from torchrl_recon.experiments.recipe import load_recipe

    cfg = load_recipe(DMC / f"online_{stem}.yaml", ["seed=0"])
    assert cfg.env.id == f"dmc:{stem.replace('_', '/')}" and cfg.env.name == stem
    assert cfg.env.cost == "learned" and cfg.env.termination is None
    assert cfg.env.kwargs.frame_skip == 2 and cfg.env.episode_steps == 500
    assert cfg.random_steps + cfg.iterations * cfg.steps_per_iteration == 100_000
    assert cfg.planner.kwargs.warm_start_uniform == 0 and cfg.planner.kwargs.return_mean_elites


@needs_dmc
@pytest.mark.parametrize(
    "overrides, words",
    [
        (["env.id=dmc:cartpole/swingupp"], ["'env.id'", "swingup_sparse"]),
        (["env.id=dmc:cartpol/swingup"], ["'env.id'", "domains"]),
        (["env.kwargs.frame_skip=0"], ["'env.kwargs.frame_skip'", "positive"]),
        (["+env.kwargs.time_limit=5"], ["'env.kwargs'", "frame_skip"]),
        (["env.cost=null"], ["'env.cost'", "learned"]),
    ],
)
def test_a_bad_dmc_env_section_is_one_error_line_before_any_work(
    tmp_path, capsys, overrides, words
):
    out = tmp_path / "run"
    code = main(
        ["online", str(DMC / "online_cartpole_swingup.yaml"), *overrides, f"output_dir={out}"]
    )
    err = capsys.readouterr().err
    assert code == 2 and len(_errors(err)) == 1, err
    assert all(w in _errors(err)[0] for w in words), err
    assert not out.exists()


@needs_dmc
@pytest.mark.slow  # 20 s
def test_a_tiny_online_run_of_a_recipe_writes_its_results(tmp_path, capsys):
    out = tmp_path / "run"
    sizes = ["iterations=1", "random_steps=75", "steps_per_iteration=25", "env.episode_steps=25"]
    sizes += ["training.slice_len=10", "training.num_slices=4", "refit_steps=4"]
    sizes += ["training.world_model.steps=10", "training.uncertainty.steps=10"]
    sizes += ["planner.kwargs={horizon: 5, num_candidates: 16, iterations: 2, num_elites: 4}"]
    sizes += ["logger.backend=none", "progress=false"]
    recipe = DMC / "online_reacher_easy.yaml"
    code = main(["online", str(recipe), *sizes, f"output_dir={out}"])
    assert code == 0, capsys.readouterr().err
    results = json.loads((out / "results.json").read_text())
    assert results["env"] == "reacher_easy" and len(results["iterations"]) == 1
