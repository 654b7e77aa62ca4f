"""Any gymnasium env through the recipes and the CLI: recipes/gym with Pendulum-v1 and a user's
``module:EnvId`` env, each with a ``module:function`` torch cost; bad env sections refused
before any work with one ``error:`` line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from torchrl_recon.cli import main
from torchrl_recon.envs import registry
from torchrl_recon.experiments.recipe import RecipeError, load_recipe
from torchrl_recon.experiments.recipe_env import cost_fn, env_entry
from torchrl_recon.experiments.recipe_planning import planning_model
from torchrl_recon.modules import LSTMWorldModel

ROOT = Path(__file__).resolve().parents[2]
GYM = ROOT / "recipes" / "gym"

COSTS = """
import torch


def pendulum(obs, action, next_obs):
    theta = torch.atan2(obs[..., 1], obs[..., 0])
    return theta.pow(2) + 0.1 * obs[..., 2].pow(2) + 0.001 * action[..., 0].pow(2)


def per_dim(obs, action, next_obs):
    return obs  # one value per dim: not a cost per step


def two_args(obs, action):
    return obs.sum(-1)
"""

USER_ENV = '''
import gymnasium as gym
import numpy as np
import torch


class Drift(gym.Env):
    """s' = 0.9 s + a in 2-D, actions in [-0.5, 0.5]; reward -|s'|^2."""

    def __init__(self, start: float = 1.0):
        self.start = start
        self.observation_space = gym.spaces.Box(-10.0, 10.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-0.5, 0.5, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.s = self.np_random.uniform(-self.start, self.start, 2).astype(np.float32)
        return self.s.copy(), {}

    def step(self, action):
        self.s = (0.9 * self.s + np.asarray(action, np.float32)).clip(-10, 10)
        return self.s.copy(), -float((self.s**2).sum()), False, False, {}


def drift_cost(obs, action, next_obs):
    return next_obs.pow(2).sum(-1)


gym.register(id="{env_id}", entry_point="{module}:Drift", max_episode_steps=50)
'''


@pytest.fixture
def costs(tmp_path, monkeypatch) -> str:
    """A user's cost module on sys.path; returns its (unique) name."""
    name = f"gym_recipe_costs_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{name}.py").write_text(COSTS)
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


def _errors(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error:")]


@pytest.mark.slow  # 10 s; test_online's Pendulum smoke runs the gym path and resumes
def test_pendulum_control_smoke_through_the_cli_and_resumed(costs, tmp_path, capsys):
    out = tmp_path / "control"
    args = ["control", str(GYM / "control_smoke.yaml"), "env.id=Pendulum-v1"]
    args += [f"env.cost={costs}:pendulum", f"output_dir={out}", "env.state_names=[c,s,w]"]
    assert main([*args, "stop_after=models"]) == 0
    first = (out / "stages" / "random_data.json").stat().st_mtime_ns
    assert not (out / "results.json").exists()
    # resumed: the config (naming the cost) is the same; finished stages are not redone
    assert main(args) == 0, capsys.readouterr().err
    assert (out / "stages" / "random_data.json").stat().st_mtime_ns == first
    results = json.loads((out / "results.json").read_text())
    assert results["env"] == "Pendulum-v1"
    assert set(results["settings"]) == {"baseline", "beta_rel_0.1"}
    assert results["trajectory_example"]["state_names"] == ["c", "s", "w"]
    assert results["beta_unit"] > 0


@pytest.mark.slow  # 6 s; the Pendulum control smoke covers the gym path
def test_pendulum_explore_smoke_through_the_cli(costs, tmp_path, capsys):
    out = tmp_path / "explore"
    code = main(
        ["explore", str(GYM / "explore_smoke.yaml"), "env.id=Pendulum-v1"]
        + [f"env.cost={costs}:pendulum", f"output_dir={out}"]
    )
    assert code == 0, capsys.readouterr().err
    results = json.loads((out / "results.json").read_text())
    assert results["env"] == "Pendulum-v1" and results["data"]["active_arm_steps"] == 50


@pytest.mark.slow  # 12.5 s; test_custom_env_tutorial runs a user env
def test_a_user_env_and_cost_from_their_own_module(tmp_path):
    """The user's module (env registered with gymnasium + torch cost) on PYTHONPATH only."""
    module, env_id = f"user_envs_{uuid.uuid4().hex[:8]}", "Drift-v0"
    text = textwrap.dedent(USER_ENV).replace("{env_id}", env_id).replace("{module}", module)
    (tmp_path / f"{module}.py").write_text(text)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "torchrl_recon.cli", "control", str(GYM / "control_smoke.yaml")]
    cmd += [f"env.id={module}:{env_id}", f"env.cost={module}:drift_cost", f"output_dir={out}"]
    path = os.pathsep.join([str(tmp_path), str(ROOT), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["env"] == "Drift-v0"  # the run's name: the id without its module
    real = [s["mean"]["real_cost"] for s in results["settings"].values()]
    assert all(torch.isfinite(torch.tensor(real)))


@pytest.mark.parametrize(
    "overrides, words",
    [
        ([], ["'env'", "env.id", "env.cost"]),
        (["env.id=Pendulum-v1"], ["'env.cost'", "no torch cost", "env.cost=module:function"]),
        (["env.id=Pendulum-v1", "env.cost=no_such_module_x:f"], ["'env.cost'", "PYTHONPATH"]),
        (["env.id=Pendulum-v1", "env.cost={costs}:nope"], ["'env.cost'", "nope", "pendulum"]),
        (["env.id=Pendulum-v1", "env.cost={costs}"], ["'env.cost'", "module:function"]),
        (["env.id=Pendulum-v1", "env.cost={costs}:two_args"], ["cost(obs, action, next_obs)"]),
        (["env.id=Pendulum-v1", "env.cost={costs}:per_dim"], ["one value per step", "[2, 3]"]),
        (
            ["env.id=Pendulum-v1", "env.cost={costs}:pendulum", "env.kwargs={gravity: 3}"],
            ["'env.kwargs'", "gravity", "'g'"],
        ),
        (
            ["env.id=Pendulum-v1", "env.cost={costs}:pendulum", "env.kwargs={g: fast}"],
            ["'env.kwargs.g'", "a number"],
        ),
        (
            ["env.id=Pendulum-v1", "env.cost={costs}:pendulum", "env.state_names=[a]"],
            ["'env.state_names'", "3 observation dims"],
        ),
        (["env.id=no_such_envs_x:Y-v0", "env.cost={costs}:pendulum"], ["'env.id'", "import"]),
        (["env.id=CartPole-v1", "env.cost={costs}:pendulum"], ["'env.id'", "Discrete"]),
    ],
)
def test_a_bad_env_section_is_one_error_line_before_any_work(
    costs, tmp_path, capsys, overrides, words
):
    out = tmp_path / "run"
    overrides = [o.replace("{costs}", costs) for o in overrides]
    code = main(["control", str(GYM / "control_smoke.yaml"), *overrides, f"output_dir={out}"])
    err = capsys.readouterr().err
    assert code == 2 and len(_errors(err)) == 1, err
    assert all(w in _errors(err)[0] for w in words), err
    assert not out.exists()


def test_a_gym_id_as_env_name_needs_a_cost_before_any_work(tmp_path, capsys):
    out = tmp_path / "run"
    recipe = ROOT / "recipes" / "drone" / "control_smoke.yaml"
    code = main(["control", str(recipe), "env.name=Pendulum-v1", f"output_dir={out}"])
    err = capsys.readouterr().err
    assert code == 2 and len(_errors(err)) == 1 and "give env.cost=" in err, err
    assert not out.exists()
    code = main(["control", str(recipe), "env.id=Pendulum-v1", f"output_dir={out}"])
    err = capsys.readouterr().err
    assert code == 2 and "'drone' names a shipped env" in err and not out.exists(), err


def test_the_recipe_env_gives_the_cost_names_and_bounds(costs):
    cfg = load_recipe(
        GYM / "control_smoke.yaml", ["env.id=Pendulum-v1", f"env.cost={costs}:pendulum"]
    )
    assert cfg.env.name == "Pendulum-v1" and cfg.output_dir.endswith("Pendulum-v1/seed0")
    assert env_entry(cfg).cost_fn_path == f"{costs}:pendulum"
    obs = torch.tensor([[1.0, 0.0, 2.0]])
    assert cost_fn(cfg)(obs, torch.zeros(1, 1), obs).tolist() == pytest.approx([0.4])
    model = planning_model(cfg, LSTMWorldModel(3, 1))
    assert model.action_low.tolist() == [-2.0] and model.action_high.tolist() == [2.0]
    drone = load_recipe(ROOT / "recipes" / "drone" / "control_smoke.yaml")
    assert planning_model(drone, LSTMWorldModel(12, 4)).action_high.tolist() == [1.0] * 4


def test_a_shipped_env_takes_a_users_cost(costs, tmp_path, monkeypatch):
    (tmp_path / f"{costs}_drone.py").write_text(
        "def hover(obs, action, next_obs):\n    return next_obs[..., 2].sub(1).abs()\n"
    )
    cfg = load_recipe(
        ROOT / "recipes" / "drone" / "control_smoke.yaml", [f"env.cost={costs}_drone:hover"]
    )
    assert env_entry(cfg).name == "drone" and cost_fn(cfg).__name__ == "hover"
    with pytest.raises(RecipeError, match="'env.cost'.*no attribute 'land'"):
        load_recipe(
            ROOT / "recipes" / "drone" / "control_smoke.yaml", [f"env.cost={costs}_drone:land"]
        )


def test_a_module_env_id_names_the_run_without_its_module(tmp_path, monkeypatch):
    module = f"user_envs_{uuid.uuid4().hex[:8]}"
    text = textwrap.dedent(USER_ENV).replace("{env_id}", "DriftName-v0")
    (tmp_path / f"{module}.py").write_text(text.replace("{module}", module))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "USER_ENVS", {})
    cfg = load_recipe(
        GYM / "explore_smoke.yaml",
        [f"env.id={module}:DriftName-v0", f"env.cost={module}:drift_cost"],
    )
    assert cfg.env.name == "DriftName-v0"
    assert cfg.output_dir == "outputs/smoke/explore/DriftName-v0/seed0"


TERMINATIONS = """
import torch


def fallen(obs, action, next_obs):
    return next_obs[..., 2].abs() > 8.0


def not_bool(obs, action, next_obs):
    return next_obs[..., 2]
"""


def test_env_termination_is_imported_and_checked_before_any_work(costs, tmp_path, capsys):
    terms = f"gym_recipe_terms_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{terms}.py").write_text(TERMINATIONS)  # tmp_path is on sys.path (costs)
    base = ["env.id=Pendulum-v1", f"env.cost={costs}:pendulum", f"output_dir={tmp_path / 'o'}"]
    for term, expected in (
        ("not_bool", "'env.termination': termination(obs [2, 3, 3], action [2, 3, 1]"),
        ("nope", f"'env.termination': termination '{terms}:nope': module '{terms}' has no"),
    ):
        args = [*base, f"env.termination={terms}:{term}"]
        code = main(["control", str(GYM / "control_smoke.yaml"), *args])
        err = capsys.readouterr().err
        assert code == 2 and expected in err, err
        assert not (tmp_path / "o").exists()  # refused before any work
    cfg = load_recipe(GYM / "control_smoke.yaml", [*base, f"env.termination={terms}:fallen"])
    model = planning_model(cfg, LSTMWorldModel(3, 1, window=cfg.models.window))
    assert model.termination_fn.__name__ == "fallen"


PUBLISHED = ROOT / "docs" / "results"


@pytest.mark.parametrize(
    "recipe, env_id, published",
    [
        ("online_pendulum", "Pendulum-v1", "online/Pendulum-v1_one_step"),
        ("online_mountain_car", "MountainCarContinuous-v0", "online/MountainCarContinuous-v0"),
        (
            "online_inverted_pendulum",
            "InvertedPendulum-v5",
            "standard_tasks/InvertedPendulum-v5_one_step_beta2_pad",
        ),
        (
            "online_inverted_pendulum_shaped",
            "InvertedPendulum-v5",
            "online/InvertedPendulum-v5_upright",
        ),
        ("online_reacher", "Reacher-v5", "standard_tasks/Reacher-v5_pets_cem"),
        (
            "online_inverted_double_pendulum",
            "InvertedDoublePendulum-v5",
            "standard_tasks/InvertedDoublePendulum-v5",
        ),
        ("online_half_cheetah", "HalfCheetah-v5", "standard_tasks/HalfCheetah-v5"),
    ],
)
def test_each_standard_task_recipe_is_valid_and_matches_its_published_runs(
    recipe, env_id, published
):
    """The task recipes validate (MuJoCo's only where it is installed) and hold exactly the
    config of the runs published from them (keys a resumed run may change aside)."""
    if env_id.endswith("-v5"):  # gymnasium's MuJoCo tasks
        pytest.importorskip("mujoco")
    cfg = load_recipe(GYM / f"{recipe}.yaml", ["seed=0"])
    assert cfg.env.id == env_id and cfg.env.cost.startswith("torchrl_recon.envs.gym_costs:")
    assert cfg.random_steps >= cfg.env.episode_steps
    assert cfg.steps_per_iteration % cfg.env.episode_steps == 0  # whole episodes an iteration
    published = PUBLISHED / published / "seed0" / "config.yaml"
    if not published.exists():
        pytest.skip(f"no published run of {recipe}")
    from torchrl_recon.experiments.run_dir import config_differences, read_config

    ours = OmegaConf.to_container(cfg, resolve=True)
    assert config_differences(OmegaConf.to_container(read_config(published.parent)), ours) == []
