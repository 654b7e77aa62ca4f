"""The fits' speed options are read from a recipe in one place (``experiments/fit_speed.py``):
each fit's keywords, a learned reward's uncompiled fit, online's schedule, and no other module
of ``experiments/`` (but the schema, ``config.py``) spelling ``cuda_graph``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

import torchrl_recon
from torchrl_recon.experiments.fit_speed import check_fit_device, compiles_fits, fit_speed
from torchrl_recon.experiments.fit_stages import fit_kwargs
from torchrl_recon.experiments.online import recipe_schedule
from torchrl_recon.experiments.recipe import load_recipe

EXPERIMENTS = Path(torchrl_recon.__file__).parent / "experiments"
SMOKE = EXPERIMENTS.parents[1] / "recipes" / "gym" / "online_smoke.yaml"
BASE = ["env.id=Pendulum-v1", "env.cost=torchrl_recon.envs.gym_costs:pendulum"]


def test_only_the_schema_and_fit_speed_spell_the_cuda_graph_option():
    spelled = sorted(p.name for p in EXPERIMENTS.glob("*.py") if "cuda_graph" in p.read_text())
    assert spelled == ["config.py", "fit_speed.py"]


def test_each_fit_takes_its_speed_from_the_recipe():
    cfg = load_recipe(SMOKE, BASE)
    cfg.training.world_model.compile = cfg.fit_cuda_graph = True  # past the recipe check

    class Ctx:
        logger = None

    Ctx.cfg = cfg
    world = fit_kwargs(Ctx, "world_model", "p/", population=True)
    assert world["compile"] is True and world["cuda_graph"] is True
    assert world["steps"] == cfg.training.world_model.steps and world["log_prefix"] == "p/"
    reward = fit_kwargs(Ctx, "reward", "r/")  # the world model's block, uncompiled
    assert reward["compile"] is False and "cuda_graph" not in reward
    assert reward["steps"] == cfg.training.world_model.steps
    assert fit_kwargs(Ctx, "uncertainty", "u/")["compile"] is False
    schedule = recipe_schedule(cfg)
    assert schedule.compile and schedule.cuda_graph and not schedule.uncertainty["compile"]
    assert compiles_fits(cfg)


def test_a_run_made_before_the_keys_fits_eagerly():
    old = OmegaConf.create({"device": "cpu", "training": {"world_model": {"steps": 3}}})
    assert fit_speed(old, population=True) == {"compile": False, "cuda_graph": False}
    assert not compiles_fits(old)
    check_fit_device(old, torch.device("cpu"))  # nothing asked for: nothing refused
    with pytest.raises(ValueError, match="'fit_cuda_graph' needs a CUDA device"):
        check_fit_device(OmegaConf.merge(old, {"fit_cuda_graph": True}), torch.device("cpu"))
