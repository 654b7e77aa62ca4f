"""Episodes and data collection with ``num_envs`` envs stepped as one batch (``SerialEnv``):
control episodes per batch (per-episode metrics, seeds, resume between batches) and valid
exploration data (distinct, contiguous trajectories)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

import torchrl_recon
from tests.experiments.tiny import TINY
from torchrl_recon.data import TRAJ_KEY, make_sequence_buffer, split_by_trajectory
from torchrl_recon.experiments import control, explore
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.recipe import load_recipe
from torchrl_recon.experiments.recipe_env import build_env
from torchrl_recon.experiments.recipe_planning import planning_model, setting_objective
from torchrl_recon.planners.beta import window_uncertainty

RECIPES = Path(torchrl_recon.__file__).parents[1] / "recipes" / "drone"
# A drone that tilts past 0.01 rad ends its episode: episodes of a batch end at different steps.
CONTROL = [
    *TINY,
    "num_envs=2",
    "episodes=3",
    "random_episodes=2",
    "random_episode_steps=12",
    "env.episode_steps=20",
    "warmup_random_steps=3",
    "+env.kwargs.max_tilt=0.01",
    "settings.0.planner.kwargs.horizon=3",
    "settings.0.planner.kwargs.num_candidates=8",
]


def _control(run_dir: Path, *overrides: str) -> tuple[RunContext, control.Controller]:
    """A control run's context and controller (its random data and models stages done)."""
    cfg = load_recipe(RECIPES / "control_smoke.yaml", [*CONTROL, *overrides])
    ctx = RunContext(cfg, run_dir)
    data = control.random_data_stage(ctx, "random_data", frames=24, episode_steps=12)
    world, estimator, _ = explore.models_stage(ctx, data, "models")
    length = max(cfg.models.window, cfg.training.slice_len)  # as control.run
    u = window_uncertainty(data, estimator, sequence_length=length)
    model = planning_model(cfg, world, estimator)
    threshold = control.replan_threshold(cfg, u)
    return ctx, control.Controller(model, threshold, 1.0, control.state_scale(data))


def _parts(run_dir: Path, setting: str) -> dict[str, str]:
    folder = run_dir / "stages" / f"setting_{setting}"
    return {p.name: p.read_text() for p in sorted(folder.glob("part_*.json"))}


def test_batched_control_setting_one_record_per_episode_same_seed_same_numbers_and_resume(
    tmp_path,
):
    ctx, controller = _control(tmp_path / "a")
    setting = ctx.cfg.settings[0]
    record = control.setting_stage(ctx, setting, controller)
    episodes = record["episodes"]
    assert len(episodes) == 3 and all("real_cost" in m for m in episodes)
    # batches [0, 1] and [2]: one part record each
    assert list(_parts(tmp_path / "a", setting.name)) == ["part_0.json", "part_1.json"]
    assert len(json.loads(_parts(tmp_path / "a", setting.name)["part_0.json"])["episodes"]) == 2
    assert len({m["steps"] for m in episodes}) > 1  # the episodes ended at different steps
    assert record["trajectory_example"]["setting"] == setting.name

    # The same seed in another directory: the same numbers.
    ctx_b, controller_b = _control(tmp_path / "b")
    again = control.setting_stage(ctx_b, setting, controller_b)
    assert again["episodes"] == episodes

    # Stopped after the first batch: the resumed run computes the second batch only.
    stage = tmp_path / "b" / "stages" / f"setting_{setting.name}"
    first = (stage / "part_0.json").read_text()
    (stage / "part_1.json").unlink()
    stage.with_suffix(".json").unlink()
    ctx_c, controller_c = _control(tmp_path / "b")
    resumed = control.setting_stage(ctx_c, setting, controller_c)
    assert resumed["episodes"] == episodes
    assert (stage / "part_0.json").read_text() == first


def test_each_env_of_a_batch_plays_the_episode_of_its_own_seed(tmp_path):
    """Replaying a batched episode's actions in a single env of that episode's seed gives the
    same observations, rewards and end: the cut trajectory is that env's episode."""
    ctx, controller = _control(tmp_path)
    setting = ctx.cfg.settings[0]
    objective, _ = setting_objective(setting, 1.0)
    planner = control.build_planner(setting.planner, controller.model, objective)
    tds = control.episode_batch(ctx, setting, planner, controller, range(0, 2))
    steps = ctx.cfg.env.episode_steps
    assert len(tds) == 2 and any(len(td) < steps for td in tds)
    for e, td in enumerate(tds):
        assert not td["next", "done"][:-1].any()
        assert bool(td["next", "done"][-1]) or len(td) == steps
        seed = ctx.stage_seed(f"setting_{setting.name}_{e}")
        env = build_env(ctx.cfg, seed=seed, episode_steps=steps)
        replay = env.rollout(steps, actions=list(td["action"]), break_when_any_done=True)
        env.close()
        assert len(replay) == len(td)
        torch.testing.assert_close(replay["observation"], td["observation"], rtol=0, atol=0)
        torch.testing.assert_close(replay["next", "reward"], td["next", "reward"], rtol=0, atol=0)
        assert control.episode_metrics(td, controller.scale)["steps"] == len(td)


def _assert_contiguous_trajectories(data) -> None:
    """Every trajectory id is one block of consecutive steps counting up from its first."""
    ids = data.get(TRAJ_KEY)
    change = torch.ones_like(ids, dtype=torch.bool)
    change[1:] = ids[1:] != ids[:-1]
    block_ids = ids[change]
    assert len(block_ids.unique()) == len(block_ids), ids.tolist()  # one block per id
    count = data["step_count"].squeeze(-1)
    inside = ~change
    assert (count[1:][inside[1:]] == count[:-1][inside[1:]] + 1).all()


def test_batched_exploration_data_is_valid(tmp_path):
    cfg = load_recipe(
        RECIPES / "explore_smoke.yaml",
        [
            *TINY,
            "num_envs=3",
            "env.episode_steps=10",
            "initial_random_steps=60",
            "validation.trajectories=5",
            "validation.steps=4",
            "validation.policy=offset_noise",
            "guided.planner.kwargs.horizon=3",
            "guided.planner.kwargs.num_candidates=8",
        ],
    )
    ctx = RunContext(cfg, tmp_path)
    initial = explore.random_data_stage(ctx, "initial_random", frames=60, keys=explore.DATA_KEYS)
    assert initial.numel() == 60
    assert len(initial.get(TRAJ_KEY).unique()) == 6  # 3 envs × 2 episodes, told apart
    _assert_contiguous_trajectories(initial)
    train, val = split_by_trajectory(initial, 0.2, seed=0)
    rb = make_sequence_buffer(len(train), slice_len=6, num_slices=4)
    rb.extend(train)
    sample = rb.sample().reshape(4, 6)
    assert (sample.get(TRAJ_KEY) == sample.get(TRAJ_KEY)[:, :1]).all()  # no window crosses

    validation = explore.validation_stage(ctx)
    assert validation.shape == (5, 7)
    assert (validation["step_count"].squeeze(-1) == torch.arange(7)).all()

    world, estimator, _ = explore.models_stage(ctx, initial, "initial_models")
    record, data = explore.guided_round_stage(ctx, world, estimator, 0, 1, 40)
    assert data.numel() == record["steps"] == 40
    _assert_contiguous_trajectories(data)
