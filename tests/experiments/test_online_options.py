"""Every option the online kind accepts either works there or is refused in one line before any
work: iterations shorter than an episode (no episode would end: NaN results), several envs (only
the random data would be batched), a cumulative re-planning threshold with MPC every step (never
read); window sampling reaches every refit, and fit_cuda_graph the first fit too."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_recon.data import TRAJ_KEY, StepUniformSliceSampler
from torchrl_recon.experiments import fit_stages
from torchrl_recon.experiments.online import recipe_schedule
from torchrl_recon.experiments.recipe import RecipeError, load_recipe
from torchrl_recon.fitting import online
from torchrl_recon.fitting.online import FitSchedule, fit_models
from torchrl_recon.modules import LSTMWorldModel

SMOKE = Path(__file__).resolve().parents[2] / "recipes" / "gym" / "online_smoke.yaml"
BASE = ["env.id=Pendulum-v1", "env.cost=torchrl_recon.envs.gym_costs:pendulum"]


@pytest.mark.parametrize(
    "overrides, message",
    [
        (
            ["steps_per_iteration=20"],
            r"'steps_per_iteration' must be at least env.episode_steps = 25",
        ),
        (["num_envs=2"], r"'num_envs' must be 1 in the online kind"),
        (
            ["replan.threshold_on=cumulative"],
            r"'replan.threshold_on' must be step unless replan.mode is uncertainty",
        ),
    ],
)
def test_an_option_the_online_kind_cannot_honour_is_refused_in_one_line(overrides, message):
    with pytest.raises(RecipeError, match=message):
        load_recipe(SMOKE, [*BASE, *overrides])


def test_a_cumulative_threshold_is_taken_where_it_is_read():
    cfg = load_recipe(SMOKE, [*BASE, "replan.mode=uncertainty", "replan.threshold_on=cumulative"])
    assert cfg.replan.threshold_on == "cumulative"


def test_step_window_sampling_reaches_every_refit(monkeypatch):
    cfg = load_recipe(SMOKE, [*BASE, "training.window_sampling=step"])
    schedule = recipe_schedule(cfg)
    assert schedule.sampling == "step"
    seen, original = [], online.sequence_buffers

    def spy(parts, **kwargs):
        buffers = original(parts, **kwargs)
        seen.extend(type(b.sampler) for b in buffers)
        return buffers

    n = 120
    data = TensorDict(
        {
            "observation": torch.randn(n, 3),
            "action": torch.rand(n, 1),
            ("next", "observation"): torch.randn(n, 3),
            TRAJ_KEY: torch.arange(n) // 30,
        },
        [n],
    )
    small = FitSchedule(**{**schedule.__dict__, "steps": 2, "refit_steps": 2, "eval_every": 1})
    world = LSTMWorldModel(3, 1, window=4)
    monkeypatch.setattr(online, "sequence_buffers", spy)
    fit_models(world, None, data, small, seed=0, warm=False)
    fit_models(world, None, data, small, seed=1, warm=True)
    assert seen and all(t is StepUniformSliceSampler for t in seen), seen


def test_fit_cuda_graph_reaches_the_first_fit_of_members(monkeypatch):
    calls = []

    def fake_fit(module):
        def fit(module, buffer, **kwargs):
            calls.append(kwargs.get("cuda_graph"))
            return type("R", (), {"best_val_loss": 0.0})()

        return fit

    monkeypatch.setattr(fit_stages, "world_model_fit", fake_fit)
    cfg = load_recipe(SMOKE, BASE)
    n = 120
    data = TensorDict(
        {
            "observation": torch.randn(n, 3),
            "action": torch.rand(n, 1),
            ("next", "observation"): torch.randn(n, 3),
            TRAJ_KEY: torch.arange(n) // 30,
        },
        [n],
    )

    class Ctx:
        logger = None

    # a fit of members always takes the key (off unless set); one world model never does
    for graph, members, expected in ((True, 2, True), (True, None, None), (False, 2, False)):
        Ctx.cfg = cfg.copy()
        Ctx.cfg.fit_cuda_graph = graph  # set past the recipe check, which needs CUDA for it
        world = LSTMWorldModel(3, 1, window=4, num_members=members)
        fit_stages.fit_module(Ctx, world, data, seed=0, prefix="models/")
        assert calls[-1] is expected
