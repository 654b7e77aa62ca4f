"""The library's parts in TorchRL's config store, and the examples that launch the online agent
from it and from a hand-built Trainer, at smoke scale."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.utils import instantiate

from tests.scripts import load_script
from torchrl_recon.envs import make_env
from torchrl_recon.modules import ESTIMATORS, LSTMWorldModel
from torchrl_recon.planners import Objective
from torchrl_recon.planners.registry import PLANNERS
from torchrl_recon.trainers import OnlineTrainer, configs

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SMOKE = [
    "trainer.iterations=1",
    "trainer.random_steps=40",
    "trainer.steps_per_iteration=20",
    "trainer.progress=false",
    "env.max_episode_steps=20",
    "planner.num_candidates=16",
    "planner.num_elites=4",
    "planner.horizon=4",
    "schedule.steps=4",
    "schedule.refit_steps=2",
    "schedule.eval_every=2",
    "schedule.slice_len=8",
    "schedule.num_slices=4",
]


def test_every_part_is_stored_beside_torchrls_own():
    repo = ConfigStore.instance().repo
    for group, name in configs.CONFIGS:
        assert f"{name}.yaml" in repo[group], (group, name)
    assert "sac.yaml" in repo["trainer"] and "online.yaml" in repo["trainer"]
    assert "adam.yaml" in repo["optimizer"]  # TorchRL's groups stay whole


@pytest.mark.parametrize("kind", sorted(PLANNERS))
def test_each_planner_config_has_its_keywords_and_builds_it(kind):
    cls, config = PLANNERS[kind], configs.PLANNER_CONFIGS[kind]
    keywords = [p for p in inspect.signature(cls).parameters if p not in ("model", "objective")]
    assert sorted(
        f.name for f in config.__dataclass_fields__.values() if f.name[0] != "_"
    ) == sorted(keywords)
    env = make_env("Pendulum-v1", seed=0)
    model = configs.make_planning_model(
        LSTMWorldModel(3, 1), env, "torchrl_recon.envs.gym_costs:pendulum"
    )
    planner = instantiate(config(horizon=3))(model, Objective())
    assert type(planner) is cls and planner.horizon == 3


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
def test_each_estimator_config_builds_it_with_the_envs_sizes(kind):
    estimator = instantiate(configs.ESTIMATOR_CONFIGS[kind](window=4))(3, 1)
    assert type(estimator) is ESTIMATORS[kind] and estimator.window == 4


def test_a_config_missing_a_required_value_fails_at_instantiation():
    with pytest.raises(Exception, match="seed"):
        instantiate(configs.MakeEnvConfig(name="Pendulum-v1"))


def test_the_config_example_composes_from_the_store_and_learns_at_smoke_size():
    with initialize_config_dir(str(EXAMPLES / "config_trainer"), version_base="1.3"):
        cfg = compose("config", overrides=SMOKE)
    trainer = instantiate(cfg.trainer)
    assert isinstance(trainer, OnlineTrainer)
    trainer.train()
    assert [r.policy for r in trainer.records] == ["random", "mpc"]
    assert trainer.collected_frames == 60


def test_the_torchrl_trainer_example_prints_the_returns(capsys):
    script = load_script(EXAMPLES / "torchrl_trainer.py")
    mean, random = script.main(["--smoke", "--frames", "80"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == f"return {mean:.1f} random {random:.1f}"
    assert last.startswith("return -") and " random -" in last
