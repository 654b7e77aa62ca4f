"""Recipe values are checked before any work: each bad value is refused, naming its key, before
the run directory exists (``recipe.validate``, used by the CLI's precheck and by every job)."""

from __future__ import annotations

import inspect
import os
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from tests.experiments.grouping import ids, pack, problems
from torchrl_recon.cli import run_recipe
from torchrl_recon.envs import get_entry, make_env
from torchrl_recon.experiments.recipe import RecipeError, compose_recipe, load_recipe
from torchrl_recon.experiments.runner import interrupted_message, last_finished_stage

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
ENVS = ("industrial_benchmark", "drone", "minitaur")

BAD = [
    # (recipe, override, words the one error line must hold)
    ("industrial_benchmark/explore_smoke", "guided.ratio=nan", ["'guided.ratio'", "finite", "nan"]),
    ("industrial_benchmark/explore_smoke", "guided.ratio=inf", ["'guided.ratio'", "finite"]),
    ("industrial_benchmark/explore_smoke", "guided.ratio=-1", ["'guided.ratio'", "above 1"]),
    ("industrial_benchmark/explore_smoke", "guided.ratio=1.0", ["'guided.ratio'", "above 1"]),
    (
        "industrial_benchmark/explore_smoke",
        "guided.cap=1.1",
        ["'guided.cap'", "above guided.ratio"],
    ),
    ("industrial_benchmark/explore_smoke", "guided.beta=0.5", ["'guided.beta'", "<= 0"]),
    ("industrial_benchmark/explore_smoke", "guided.steps=0", ["'guided.steps'", ">= 1"]),
    ("industrial_benchmark/explore_smoke", "initial_random_steps=0", ["'initial_random_steps'"]),
    ("industrial_benchmark/explore_smoke", "initial_random_steps=30", ["two trajectories"]),
    (
        "industrial_benchmark/explore_smoke",
        "env.episode_steps=10",
        ["'env.episode_steps'", "slice"],
    ),
    ("industrial_benchmark/explore_smoke", "random_steps=0", ["'random_steps'", ">= 1"]),
    ("industrial_benchmark/explore_smoke", "validation.steps=0", ["'validation.steps'"]),
    ("industrial_benchmark/explore_smoke", "training.val_fraction=0", ["'training.val_fraction'"]),
    ("industrial_benchmark/explore_smoke", "training.val_fraction=1", ["(0, 1)"]),
    ("industrial_benchmark/explore_smoke", "training.world_model.lr=-1", ["world_model.lr", "> 0"]),
    ("industrial_benchmark/explore_smoke", "training.uncertainty.lr=nan", ["uncertainty.lr"]),
    ("industrial_benchmark/explore_smoke", "training.uncertainty.patience=0", ["patience"]),
    ("industrial_benchmark/explore_smoke", "training.world_model.eval_every=0", ["eval_every"]),
    (
        "industrial_benchmark/explore_smoke",
        "training.slice_len=5",
        ["'training.slice_len'", "window"],
    ),
    ("industrial_benchmark/explore_smoke", "training.num_slices=0", ["'training.num_slices'"]),
    (
        "industrial_benchmark/explore_smoke",
        "training.window_sampling=steps",
        ["'training.window_sampling'", "steps"],
    ),
    ("industrial_benchmark/explore_smoke", "models.window=0", ["'models.window'", ">= 1"]),
    ("industrial_benchmark/explore_smoke", "models.world_model.activation=gelu", ["activation"]),
    (
        "drone/control_smoke",
        "settings.7.planner.kwargs.lr=0",
        ["'settings[7].planner.kwargs.lr'", "positive", "got 0"],
    ),
    (
        "industrial_benchmark/explore_smoke",
        "guided.planner.kwargs.iterations=2",
        ["'guided.planner.kwargs'", "RandomShootingPlanner", "['iterations']", "num_candidates"],
    ),
    (
        "industrial_benchmark/explore_smoke",
        "guided.planner.kwargs.num_candidates=nan",
        ["'guided.planner.kwargs.num_candidates'", "finite"],
    ),
    ("industrial_benchmark/explore_smoke", "guided.planner.kind=cem", ["num_elites", "64"]),
    ("industrial_benchmark/explore_smoke", "env.kwargs.setpoint=abc", ["setpoint", "a number"]),
    ("industrial_benchmark/explore_smoke", "+env.kwargs.foo=1", ["'foo'", "setpoint"]),
    ("industrial_benchmark/explore_smoke", "output_dir=' '", ["'output_dir'"]),
    (
        "minitaur/explore_smoke",
        "env.name=drone",
        ["'env.kwargs'", "'drone'", "action_mode", "delta"],
    ),
    ("minitaur/explore_smoke", "env.kwargs.motor_kp=inf", ["'env.kwargs.motor_kp'", "finite"]),
    ("drone/control_smoke", "settings.1.beta=nan", ["'settings[1].beta'", "nan"]),
    ("drone/control_smoke", "settings.0.alpha=-1", ["'settings[0].alpha'"]),
    ("drone/control_smoke", "settings.1.band.high=inf", ["'settings[1].band.high'"]),
    ("drone/control_smoke", "settings.0.name=a/b", ["'settings[0].name'", "file"]),
    (
        "drone/control_smoke",
        "settings.7.planner.kwargs.steps=0",
        ["'settings[7].planner.kwargs.steps'", ">= 1", "got 0"],
    ),
    (
        "drone/control_smoke",
        "settings.7.planner.kind=shooting",
        ["'settings[7].planner.kwargs'", "['lr', 'restarts', 'steps']"],
    ),
    (
        "drone/control_smoke",
        "~settings.7.planner.kwargs.horizon",
        ["'settings[7].planner.kwargs'", "GradientPlanner", "horizon"],
    ),
    ("drone/control_smoke", "replan.threshold_quantile=0", ["'replan.threshold_quantile'"]),
    ("drone/control_smoke", "replan.threshold_scale=0", ["'replan.threshold_scale'"]),
    ("drone/control_smoke", "replan.every=0", ["'replan.every'"]),
    ("drone/control_smoke", "random_episodes=1", ["'random_episodes'", ">= 2"]),
    ("drone/control_smoke", "episodes=0", ["'episodes'"]),
    ("drone/control_smoke", "num_envs=0", ["'num_envs'", ">= 1", "got 0"]),
    ("industrial_benchmark/explore_smoke", "num_envs=1.5", ["num_envs", "1.5"]),
    ("drone/control_smoke", "warmup_random_steps=30", ["'env.episode_steps'", "warmup"]),
    ("drone/control_smoke", "env.kwargs.goal=[1,2]", ["'env.kwargs.goal'", "3"]),
    (
        "drone/calibrate_smoke",
        "estimators.2.kwargs.dropout=nan",
        ["'estimators[2].kwargs.dropout'"],
    ),
    ("drone/calibrate_smoke", "evaluation.ood_state_shift=0", ["ood_state_shift"]),
    ("drone/control_smoke", "planning_compile=maybe", ["'planning_compile'", "reduce-overhead"]),
    ("gym/online_smoke", "planning_compile=1", ["'planning_compile'", "got 1"]),
    ("drone/calibrate_smoke", "planning_compile=true", ["unknown key 'planning_compile'"]),
    ("drone/control_smoke", "planning_threads=0", ["'planning_threads'", ">= 1", "got 0"]),
    ("gym/online_smoke", "planning_threads=2", ["'planning_compile'", "planning_threads above 1"]),
    ("drone/calibrate_smoke", "random_steps=60", ["'random_steps'", "two trajectories"]),
    (
        "drone/calibrate_smoke",
        "outcomes.explore_overrides=['guided.ratio=0.5']",
        ["'outcomes.explore_recipe'", "'guided.ratio'", "explore_smoke.yaml"],
    ),
]


# Checked before the others (a value of the wrong type, an unknown key or keyword, a choice not
# offered): the line names only that problem, so these run alone.
ALONE = {
    "num_envs=1.5",
    "+env.kwargs.foo=1",
    "env.name=drone",
    "training.window_sampling=steps",
    "guided.planner.kwargs.iterations=2",
    "planning_compile=true",
    "planning_threads=2",
}


GROUPS = pack(BAD, ALONE)


@pytest.mark.parametrize("recipe, cases", GROUPS, ids=ids(GROUPS))
def test_bad_values_are_refused_before_the_run_directory_exists(recipe, cases, tmp_path, capsys):
    kind = Path(recipe).name.split("_")[0]
    out = tmp_path / "run"
    overrides = [override for override, _ in cases]
    code = run_recipe(kind, RECIPES / f"{recipe}.yaml", [f"output_dir={out}", *overrides])
    err = capsys.readouterr().err
    assert code == 2
    assert not out.exists()
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    parts = problems(lines[0]) if len(cases) > 1 else lines[0:1]  # one per bad value
    for override, words in cases:
        assert any(all(w in p for w in words) for p in parts), (override, words, lines[0])


def test_every_problem_is_named_on_one_line():
    with pytest.raises(RecipeError) as info:
        load_recipe(
            RECIPES / "drone" / "explore_smoke.yaml",
            ["guided.ratio=nan", "retrainings=0", "training.val_fraction=2"],
        )
    message = str(info.value)
    assert "\n" not in message
    for key in ("'guided.ratio'", "'retrainings'", "'training.val_fraction'"):
        assert key in message


def test_an_env_keyword_whose_default_is_infinite_may_be_infinite():
    assert get_entry("minitaur").keywords()["distance_limit"] == float("inf")
    cfg = load_recipe(
        RECIPES / "minitaur" / "explore_smoke.yaml", ["env.kwargs.distance_limit=inf"]
    )
    assert cfg.env.kwargs.distance_limit == float("inf")
    with pytest.raises(RecipeError, match="distance_limit"):
        load_recipe(RECIPES / "minitaur" / "explore_smoke.yaml", ["env.kwargs.distance_limit=nan"])


@pytest.mark.parametrize("name", ENVS)
def test_env_keywords_come_from_the_env_class_signature(name):
    entry = get_entry(name)
    params = inspect.signature(entry.env_class().__init__).parameters
    assert set(entry.keywords()) == set(params) - {"self"}
    with pytest.raises(TypeError) as info:
        entry.check_kwargs({"not_a_keyword": 1})
    message = str(info.value)
    assert repr(name) in message and "not_a_keyword" in message
    assert all(k in message for k in entry.keywords())
    with pytest.raises(TypeError, match=f"{name!r}.*not_a_keyword"):
        make_env(name, seed=0, not_a_keyword=1)


def _one_recipe_per_folder_in_make_test(paths: list[Path]) -> list:
    """Each folder's first recipe runs in make test, the rest in make test-all (0.3 s each)."""
    seen: set[str] = set()
    params = []
    for path in paths:
        marks = [pytest.mark.slow] if path.parent.name in seen else []
        seen.add(path.parent.name)
        params.append(pytest.param(path, marks=marks, id=f"{path.parent.name}/{path.stem}"))
    return params


@pytest.mark.parametrize(
    "path", _one_recipe_per_folder_in_make_test(sorted(RECIPES.glob("*/*.yaml")))
)
def test_output_dir_follows_env_name(path):
    raw = compose_recipe(path)
    written = OmegaConf.to_container(raw, resolve=False)["output_dir"]
    assert "${env.name}" in written, f"{path}: output_dir does not interpolate env.name"
    assert path.parent.name not in written
    other = next(e for e in ENVS if e != path.parent.name)
    cfg = OmegaConf.merge(raw, {"env": {"name": other, "kwargs": {}}})
    resolved = OmegaConf.to_container(cfg, resolve=True)["output_dir"]
    assert Path(resolved).parent.name == other


def test_ib_recipe_with_drone_writes_below_drone():
    cfg = load_recipe(RECIPES / "industrial_benchmark" / "explore_smoke.yaml", ["env.name=drone"])
    assert cfg.output_dir == "outputs/smoke/explore/drone/seed0"
    same = load_recipe(RECIPES / "industrial_benchmark" / "explore_smoke.yaml")
    assert same.output_dir == "outputs/smoke/explore/industrial_benchmark/seed0"


def test_interrupted_message_names_the_last_finished_stage(tmp_path):
    assert last_finished_stage(tmp_path) is None
    assert interrupted_message(tmp_path).startswith("interrupted before any stage finished")
    stages = tmp_path / "stages"
    (stages / "setting_a").mkdir(parents=True)
    now = time.time()
    for i, name in enumerate(("random_data", "models", "setting_a")):
        (stages / f"{name}.json").write_text("{}")
        os.utime(stages / f"{name}.json", (now + i, now + i))
    (stages / "models.rng.pt").write_bytes(b"")
    (stages / "setting_a" / "part_0.json").write_text("{}")
    os.utime(stages / "models.json", (now + 10, now + 10))
    assert last_finished_stage(tmp_path) == "models"
    assert interrupted_message(tmp_path) == (
        f"interrupted after stage 'models' of {tmp_path}; run the same command to resume"
    )


@pytest.mark.parametrize("recipe", ["industrial_benchmark/explore_smoke", "gym/online_smoke"])
def test_fit_cuda_graph_off_cuda_or_beside_compile_is_refused_before_any_work(
    recipe, tmp_path, capsys
):
    out = tmp_path / "run"
    kind = Path(recipe).name.split("_")[0]
    graph = ["fit_cuda_graph=true"] + (["world_model_members=2"] if kind == "online" else [])
    for extra, words in (
        (["device=cpu"], "'device' must be a CUDA device with fit_cuda_graph"),
        (
            ["device=cuda", "training.world_model.compile=true"],
            "'training.world_model.compile' must be false with fit_cuda_graph",
        ),
    ):
        code = run_recipe(kind, RECIPES / f"{recipe}.yaml", [f"output_dir={out}", *graph, *extra])
        err = capsys.readouterr().err
        assert code == 2 and words in err and "Traceback" not in err, err
    assert not out.exists()
