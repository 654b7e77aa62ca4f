"""Experiment plumbing: recipes, validation, run directories, loggers, plots, summaries, CLI."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import platform
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf
from scipy import stats

from tests.experiments import grouping
from torchrl_recon.cli import main, run_recipe
from torchrl_recon.evaluation.mpc import METRICS
from torchrl_recon.experiments import runner
from torchrl_recon.experiments.config import ControlSetting, EstimatorSpec, PlannerConfig
from torchrl_recon.experiments.loggers import make_logger
from torchrl_recon.experiments.recipe import RecipeError, compose_recipe, load_recipe, validate
from torchrl_recon.experiments.registry import EXPERIMENT_TYPES, get_type
from torchrl_recon.experiments.run_dir import (
    RunDirConflict,
    prepare_run_dir,
    release_run_dir,
    write_results,
)
from torchrl_recon.experiments.stages import StopRequested
from torchrl_recon.reports import format_table, save_figures, summarize
from torchrl_recon.reports.plots import plot_control_errors, plot_table1, plot_trajectory
from torchrl_recon.runs.provenance import git_info

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
ENVS = ("industrial_benchmark", "drone", "minitaur")
# recipes/gym need env.id and env.cost: tests/experiments/test_gym_recipes.py; recipes/dmc need
# the dmc extra: tests/envs/test_dmc.py
ALL_RECIPES = sorted(
    p for p in RECIPES.glob("*/*.yaml") if p.parent.name not in ("all_envs", "gym", "dmc")
)
SWEEP_RECIPES = sorted(RECIPES.glob("all_envs/*.yaml"))


# ------------------------------------------------------------------------------------------
# hand-made results


def explore_result(seed: int, random: list[float], active: list[float], env: str = "drone") -> dict:
    def arm(v):
        mean = sum(v) / len(v)
        std = math.sqrt(sum((x - mean) ** 2 for x in v) / (len(v) - 1)) if len(v) > 1 else 0.0
        return {"mse": v, "mean": mean, "std": std}

    r, a = arm(random), arm(active)
    return {
        "experiment": "explore",
        "env": env,
        "seed": seed,
        "mse_units": "standardised squared error",
        "arms": {"random": r, "active": a},
        "ratio": a["mean"] / r["mean"],
        "test": {"name": "Welch t-test", "statistic": -1.0, "p_value": 0.3},
        "data": {
            "initial_steps": 300,
            "random_arm_steps": 100,
            "active_arm_steps": 100,
            "active_feasible_fraction": 0.5,
        },
        "wall_time_s": {"initial_random": 1.0},
    }


def episode(mse: float) -> dict:
    return {
        "prediction_mse": mse,
        "cost_error": 2 * mse,
        "real_cost": 10.0 + mse,
        "predicted_cost": 10.0 - mse,
        "replans": 3,
        "mean_u": 0.5,
        "feasible_fraction": 1.0,
    }


def stats_mean(values: list[float]) -> float:
    """The mean a control run records: over the episodes with a planned step (NaN if none)."""
    return sum(values) / len(values) if values else float("nan")


def control_result(seed: int, mses: dict[str, list[float]], env: str = "drone") -> dict:
    settings = {}
    for name, values in mses.items():
        eps = [episode(v) for v in values]
        keys = [k for k in METRICS if k in eps[0]]
        mean = {k: stats_mean([e[k] for e in eps if not math.isnan(e[k])]) for k in keys}
        std = {k: 0.1 for k in keys}
        settings[name] = {"episodes": eps, "mean": mean, "std": std}
    length, n = 12, 4
    return {
        "experiment": "control",
        "env": env,
        "seed": seed,
        "replan_threshold": 1.5,
        "settings": settings,
        "trajectory_example": {
            "setting": "baseline",
            "real": [[math.sin(t / 3 + i) for i in range(n)] for t in range(length)],
            "predicted": [[math.sin(t / 3 + i) + 0.1 for i in range(n)] for t in range(length)],
            "uncertainty": [0.1 * t for t in range(length)],
            "replanned": [t % 5 == 0 for t in range(length)],
            "state_names": [f"x{i}" for i in range(n)],
        },
        "wall_time_s": {"random_data": 1.0},
    }


# ------------------------------------------------------------------------------------------
# recipes


@pytest.mark.parametrize("path", ALL_RECIPES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_recipe_loads_and_validates(path):
    cfg = load_recipe(path)
    assert cfg.experiment in path.stem
    assert cfg.env.name == path.parent.name
    assert f"seed{cfg.seed}" in cfg.output_dir


@pytest.mark.parametrize("stem", ["explore", "control", "calibrate"])
def test_validate_is_idempotent_on_an_already_typed_config(stem):
    """One recipe of each kind (validation reads the same schema for every env)."""
    cfg = load_recipe(RECIPES / "drone" / f"{stem}.yaml")
    again = validate(cfg)
    assert OmegaConf.to_container(again) == OmegaConf.to_container(cfg)


def _own_settings(stem: str, settings: list[dict]) -> list[dict]:
    """The settings an all_envs control recipe keeps from its env's control.yaml."""
    by_name = {s["name"]: s for s in settings}
    if stem == "control_bands":  # the baseline and the three u bands
        return settings[:4]
    if stem == "control_gradient":
        return [by_name[n] for n in ("baseline", "gradient_beta_0.1", "gradient_beta_0.2")]
    relative = []  # control_relative_beta: the gradient settings with their β read as relative
    for beta in ("0.1", "0.2"):
        setting = dict(by_name[f"gradient_beta_{beta}"])
        setting.update(name=f"gradient_relative_beta_{beta}", beta_relative=True)
        relative.append(setting)
    return [by_name["baseline"], *relative]


@pytest.mark.parametrize(
    "path",  # explore's sweep in make test; the four control sweeps in make test-all
    [p if p.stem == "explore" else pytest.param(p, marks=pytest.mark.slow) for p in SWEEP_RECIPES],
    ids=lambda p: p.name,
)
def test_all_envs_sweep_runs_each_env_recipe(path):
    """Every job of recipes/all_envs/<kind>.yaml is its env's own recipe with the job's seed;
    the control_* ones keep only some of its settings (see ``_own_settings``)."""
    from torchrl_recon.experiments.compose import compose_recipe, sweep_jobs

    jobs = sweep_jobs(compose_recipe(path, with_hydra=True), [])
    envs = {"drone", "industrial_benchmark", "minitaur"}
    kind = path.stem.split("_")[0]
    expected_jobs = {"explore": 15, "control": 3, "control_bands": 15}
    expected_jobs.update(control_relative_beta=15, control_gradient=9)
    assert len(jobs) == expected_jobs[path.stem]
    checked = set()
    for job in jobs:
        values = dict(o.split("=") for o in job)
        env, seed = values[f"{kind}_env"], values["seed"]
        assert set(values) == {f"{kind}_env", "seed"}, job  # a job is its env and its seed
        envs.discard(env)
        if env in checked:  # one job per env is loaded: the others differ in the seed only
            continue
        checked.add(env)
        cfg = OmegaConf.to_container(load_recipe(path, job))
        own = OmegaConf.to_container(load_recipe(RECIPES / env / f"{kind}.yaml", [f"seed={seed}"]))
        if path.stem.startswith("control_"):
            assert cfg.pop("settings") == _own_settings(path.stem, own.pop("settings"))
            tree = path.stem + ("_seeds" if path.stem == "control_relative_beta" else "")
            assert cfg.pop("output_dir") == f"outputs/{tree}/{env}/seed{seed}"
            own.pop("output_dir")
        assert cfg == own
    assert not envs


def test_recipe_outside_recipes_extends_a_shipped_one(tmp_path):
    user = tmp_path / "mine.yaml"
    user.write_text("defaults:\n  - /drone/explore_smoke@_here_\n  - _self_\nretrainings: 3\n")
    cfg = load_recipe(user, ["threads=2", "env.kwargs={delta: 0.1}"])
    assert (cfg.env.name, cfg.retrainings, cfg.threads, cfg.env.kwargs.delta) == (
        "drone",
        3,
        2,
        0.1,
    )


def test_a_kept_composition_is_copied_and_made_again_when_a_file_changes(tmp_path, monkeypatch):
    """``compose_recipe`` keeps what Hydra composed: each call gets its own copy, and a change
    to any YAML file of the recipe's folders (here its base, same size) or to the working
    directory composes it again."""
    (tmp_path / "base.yaml").write_text("seed: 1\nthreads: 1\n")
    user = tmp_path / "mine.yaml"
    user.write_text("defaults:\n  - base\n  - _self_\nthreads: 2\n")
    first = compose_recipe(user, ["+extra=1"])
    first.seed = 9  # the caller's copy
    assert (first.seed, compose_recipe(user, ["+extra=1"]).seed) == (9, 1)
    hydra = compose_recipe(user, ["+extra=1"], with_hydra=True)
    assert "hydra" in hydra and "hydra" not in compose_recipe(user, ["+extra=1"])
    (tmp_path / "base.yaml").write_text("seed: 2\nthreads: 1\n")
    assert compose_recipe(user, ["+extra=1"]).seed == 2
    monkeypatch.chdir(tmp_path)
    again = compose_recipe(user, ["+extra=1"], with_hydra=True)
    assert again.hydra.runtime.cwd == str(tmp_path) != hydra.hydra.runtime.cwd


def test_recipe_set_is_complete():
    names = {f"{p.parent.name}/{p.name}" for p in ALL_RECIPES}
    for env in ENVS:
        for kind in ("explore", "control", "calibrate"):
            for suffix in ("", "_smoke") + (("_reduced",) if kind != "calibrate" else ()):
                assert f"{env}/{kind}{suffix}.yaml" in names


def _schema_keys(schema) -> set[str]:
    flat = OmegaConf.to_container(OmegaConf.structured(schema))
    out = set()

    def walk(node, prefix):
        if isinstance(node, dict) and node and prefix not in ("env.kwargs",):
            for k, v in node.items():
                walk(v, f"{prefix}.{k}" if prefix else k)
        else:
            out.add(prefix)

    walk(flat, "")
    return out


@pytest.mark.parametrize("env", ENVS)
@pytest.mark.parametrize("kind", ("explore", "control", "calibrate"))
def test_full_recipes_hold_every_key(env, kind):
    raw = OmegaConf.to_container(compose_recipe(RECIPES / env / f"{kind}.yaml"))
    lists = {"settings", "estimators"}
    keys = _schema_keys(get_type(kind).schema) - lists
    flat = set()

    def walk(node, prefix):
        if isinstance(node, dict) and node and not prefix.endswith("kwargs"):
            for k, v in node.items():
                walk(v, f"{prefix}.{k}" if prefix else k)
        else:
            flat.add(prefix)

    walk({k: v for k, v in raw.items() if k not in lists}, "")
    assert keys <= flat, f"missing in {env}/{kind}.yaml: {sorted(keys - flat)}"
    if kind == "calibrate":
        spec_fields = {f.name for f in dataclasses.fields(EstimatorSpec)}
        assert [e["kind"] for e in raw["estimators"]] == [
            "reconstruction",
            "ensemble",
            "mc_dropout",
            "rnd",
            "world_model_ensemble",
        ]
        for e in raw["estimators"]:
            assert set(e) == spec_fields
    if kind == "control":
        setting_fields = {f.name for f in dataclasses.fields(ControlSetting)}
        planner_fields = {f.name for f in dataclasses.fields(PlannerConfig)}
        for s in raw["settings"]:
            assert set(s) == setting_fields
            assert set(s["planner"]) == planner_fields


@pytest.mark.parametrize("env", ENVS)
def test_paper_scale_numbers(env):
    e = load_recipe(RECIPES / env / "explore.yaml")
    assert e.initial_random_steps == 10000
    assert (e.validation.trajectories, e.validation.steps) == (100, 100)
    assert (e.guided.steps, e.env.episode_steps, e.guided.ratio) == (15000, 100, 1.2)
    assert (e.random_steps, e.retrainings) == (15000, 10)
    assert (
        e.models.window,
        e.models.world_model.hidden_size,
        e.models.uncertainty.hidden_size,
    ) == (10, 32, 100)
    c = load_recipe(RECIPES / env / "control.yaml")
    assert (c.random_episodes, c.random_episode_steps, c.episodes) == (10, 500, 10)
    assert (c.warmup_random_steps, c.models.window) == (10, 10)
    assert c.env.episode_steps <= 500
    assert all(s.planner.kwargs.horizon == 200 for s in c.settings)
    by_name = {s.name: s for s in c.settings}
    assert by_name["baseline"].planner.kind == "shooting" and by_name["baseline"].beta == 0
    assert by_name["baseline"].band is None
    for name, (lo, hi) in {"u_low": (0, 0.33), "u_mid": (0.33, 0.66), "u_high": (0.66, 1)}.items():
        band = by_name[name].band
        assert (band.low, band.high, band.kind, by_name[name].beta) == (lo, hi, "quantile", 0)
    for beta in (0.1, 0.2):
        s = by_name[f"gradient_beta_{beta}"]
        assert (s.planner.kind, s.alpha, s.beta) == ("gradient", 1.0, beta)
    thresholds = [s.cost_threshold for s in c.settings if s.cost_threshold is not None]
    assert bool(thresholds) == (env == "drone")


def test_drone_relative_beta_recipe_changes_only_beta():
    """Its models and baseline are control.yaml's, so its results compare with that run's."""
    full = OmegaConf.to_container(load_recipe(RECIPES / "drone" / "control.yaml"))
    rel = OmegaConf.to_container(load_recipe(RECIPES / "drone" / "control_relative_beta.yaml"))
    for key in set(full) - {"settings", "output_dir"}:
        assert rel[key] == full[key], key
    full_by_name = {s["name"]: s for s in full["settings"]}
    assert rel["settings"][0] == full_by_name["baseline"]
    for s in rel["settings"][1:]:
        absolute = full_by_name[s["name"].replace("relative_", "")]
        assert s["beta_relative"] and not absolute["beta_relative"]
        assert {**s, "name": absolute["name"], "beta_relative": False} == absolute


@pytest.mark.parametrize("env", ENVS)
def test_smoke_recipes_shrink_every_size(env):
    e = load_recipe(RECIPES / env / "explore_smoke.yaml")
    assert e.models.world_model.activation == "relu"  # inherited from explore.yaml (defaults)
    assert e.logger.backend == "csv" and "smoke" in e.output_dir
    assert e.initial_random_steps <= 500 and e.guided.steps <= 200 and e.random_steps <= 200
    assert e.retrainings == 2 and e.validation.trajectories <= 5
    assert e.training.world_model.steps <= 50 and e.guided.planner.kwargs.horizon <= 10
    c = load_recipe(RECIPES / env / "control_smoke.yaml")
    assert c.logger.backend == "csv" and "smoke" in c.output_dir
    assert c.episodes == 2 and c.random_episodes * c.random_episode_steps <= 500
    assert all(s.planner.kwargs.horizon <= 10 for s in c.settings)
    full = load_recipe(RECIPES / env / "control.yaml")
    assert [s.name for s in c.settings] == [s.name for s in full.settings]


def test_overrides_and_seed_interpolation():
    cfg = load_recipe(
        RECIPES / "drone" / "control_smoke.yaml",
        ["seed=7", "settings.0.beta=0.3", "+settings.1.cost_threshold=5", "env.kwargs.delta=0.1"],
    )
    assert cfg.output_dir.endswith("seed7")
    assert cfg.settings[0].beta == 0.3 and cfg.settings[1].cost_threshold == 5.0
    assert cfg.env.kwargs == {"delta": 0.1}


RECIPE_ERRORS = [  # (recipe of recipes/drone, override, words the error line must hold)
    ("explore_smoke", "guided.foo=1", ["unknown key", "guided.foo", "GuidedConfig"]),
    ("explore_smoke", "+bogus=1", ["unknown key", "bogus"]),
    ("explore_smoke", "seed=abc", ["wrong type", "seed"]),
    ("explore_smoke", "validation.trajectories=1.5", ["wrong type", "validation.trajectories"]),
    ("explore_smoke", "env.name=pendulum", ["env.name", "pendulum", "drone"]),
    ("explore_smoke", "guided.planner.kind=mpc", ["guided.planner.kind", "mpc", "mppi"]),
    ("explore_smoke", "logger.backend=tensorboard", ["logger.backend"]),
    ("explore_smoke", "experiment=train", ["experiment"]),
    ("control_smoke", "settings.2.foo=1", ["unknown key", "settings[2].foo"]),
    ("control_smoke", "settings.0.planner.kind=x", ["settings[0].planner.kind"]),
    ("control_smoke", "settings.1.band.kind=abs", ["settings[1].band.kind"]),
    ("control_smoke", "settings.1.band.low=0.9", ["settings[1].band", "above"]),
    ("control_smoke", "settings.1.name=baseline", ["duplicate", "baseline"]),
    ("control_smoke", "replan.error_threshold=0", ["replan.error_threshold", "positive"]),
    ("explore_smoke", "seed=0,1", ["sweep", "-m"]),
    ("explore_smoke", "stop_after=guided", ["stop_after", "guided_data_<n>"]),
    ("control_smoke", "stop_after=setting_x", ["stop_after", "setting_u_low"]),
    ("explore_smoke", "models.uncertainty.kind=gp", ["models.uncertainty", "gp", "rnd"]),
    (
        "explore_smoke",
        "+models.uncertainty.kwargs.members=3",
        ["models.uncertainty", "members", "accepts"],
    ),
    ("calibrate_smoke", "estimators.1.name=reconstruction", ["duplicate", "reconstruction"]),
    ("calibrate_smoke", "estimators.2.kwargs.dropout=1.5", ["estimators[2]", "dropout"]),
    ("calibrate_smoke", "outcomes.control_recipe=nope.yaml", ["outcomes.control_recipe"]),
    ("calibrate_smoke", "timing.horizons=[]", ["timing.horizons"]),
    ("calibrate_smoke", "stop_after=fit_gp", ["stop_after", "fit_rnd"]),
]
# Refused before the other checks (a wrong type, an unknown key, a choice not offered, a sweep):
# the line names only that problem, so these run alone.
RECIPE_ERRORS_ALONE = {
    "guided.foo=1",
    "+bogus=1",
    "seed=abc",
    "validation.trajectories=1.5",
    "logger.backend=tensorboard",
    "experiment=train",
    "settings.2.foo=1",
    "settings.1.band.kind=abs",
    "seed=0,1",
}
RECIPE_ERROR_GROUPS = grouping.pack(RECIPE_ERRORS, RECIPE_ERRORS_ALONE)


@pytest.mark.parametrize(
    "recipe, cases", RECIPE_ERROR_GROUPS, ids=grouping.ids(RECIPE_ERROR_GROUPS)
)
def test_recipe_errors_name_the_key(recipe, cases):
    """Each bad value's words inside its own problem of the one error line (distinct top-level
    keys share a composition: ``tests/experiments/grouping.py``)."""
    with pytest.raises(RecipeError) as info:
        load_recipe(RECIPES / "drone" / f"{recipe}.yaml", [o for o, _ in cases])
    assert isinstance(info.value, ValueError)
    line = str(info.value)
    found = grouping.problems(line) if len(cases) > 1 else [line]
    for override, words in cases:
        assert any(all(w in p for w in words) for p in found), (override, words, line)


def test_unknown_key_in_recipe_file(tmp_path):
    base = yaml.safe_load((RECIPES / "industrial_benchmark" / "explore.yaml").read_text())
    base["guided"]["ratoi"] = 1.5
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(base))
    with pytest.raises(RecipeError, match=r"unknown key 'guided.ratoi'"):
        load_recipe(path)
    base["guided"].pop("ratoi")
    base["env"].pop("name")
    path.write_text(yaml.safe_dump(base))
    with pytest.raises(RecipeError, match="env.name"):
        load_recipe(path)


def test_missing_recipe_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "nope.yaml")):
        load_recipe(tmp_path / "nope.yaml")
    child = tmp_path / "child.yaml"
    child.write_text("defaults: [missing_base, _self_]\nseed: 1\n")
    with pytest.raises(RecipeError, match=r"child.yaml: .*missing_base"):
        load_recipe(child)


def test_validate_drops_hydra_node():
    cfg = compose_recipe(RECIPES / "drone" / "explore_smoke.yaml", with_hydra=True)
    assert "hydra" in cfg and "hydra" not in validate(cfg)


# ------------------------------------------------------------------------------------------
# run directories


def _smoke(tmp_path, *overrides):
    return load_recipe(
        RECIPES / "drone" / "explore_smoke.yaml",
        [f"output_dir={tmp_path}/run/seed${{seed}}", *overrides],
    )


def test_prepare_run_dir_writes_config_and_meta(tmp_path):
    cfg = _smoke(tmp_path, "seed=3")
    run_dir = prepare_run_dir(cfg, argv=["torchrl-recon", "explore", "x.yaml", "seed=3"])
    try:
        assert run_dir == (tmp_path / "run" / "seed3").resolve()
        saved = OmegaConf.load(run_dir / "config.yaml")
        assert OmegaConf.to_container(saved) == OmegaConf.to_container(cfg, resolve=True)
        assert saved.output_dir == str(tmp_path / "run" / "seed3")
        meta = json.loads((run_dir / "meta.json").read_text())
    finally:
        release_run_dir(run_dir)
    assert meta["seed"] == 3 and meta["experiment"] == "explore" and meta["env"] == "drone"
    for pkg in (
        "python",
        "torch",
        "torchrl",
        "tensordict",
        "gymnasium",
        "numpy",
        "pybullet",
        "torchrl-recon",
    ):
        assert meta["versions"][pkg], pkg
    commit = meta["git"]["commit"]
    assert commit == "unknown" or (len(commit) == 40 and int(commit, 16) >= 0)
    assert meta["git"]["dirty"] in (True, False, None)
    assert meta["hostname"]
    assert dt.datetime.fromisoformat(meta["started_utc"]).utcoffset() == dt.timedelta(0)
    assert meta["argv"] == ["torchrl-recon", "explore", "x.yaml", "seed=3"]
    assert meta["resumed"] is False


def test_meta_records_no_absolute_path(tmp_path, monkeypatch):
    inside, outside = tmp_path / "cwd", tmp_path / "elsewhere"
    inside.mkdir()
    monkeypatch.chdir(inside)
    recipe = str(RECIPES / "drone" / "explore_smoke.yaml")
    for out, expected in ((inside / "runs" / "seed0", "runs/seed0"), (outside / "seed0", "seed0")):
        cfg = load_recipe(recipe, [f"output_dir={out}"])
        argv = ["torchrl-recon", "explore", recipe, f"output_dir={out}", "seed=0"]
        extra = {"job_overrides": [f"output_dir={out}"]}
        run_dir = prepare_run_dir(cfg, argv=argv, extra_meta=extra)
        release_run_dir(run_dir)
        meta = json.loads((run_dir / "meta.json").read_text())
        assert meta["run_dir"] == expected
        # a shipped recipe by its name
        assert meta["argv"][2:] == ["drone/explore_smoke.yaml", f"output_dir={expected}", "seed=0"]
        assert meta["job_overrides"] == [f"output_dir={expected}"]
        assert str(tmp_path) not in json.dumps(meta)


def test_a_run_first_started_outside_a_checkout_resumes(tmp_path, capsys):
    """An earlier start that recorded ``"git": null`` (or no commit) is no commit change."""
    cfg = _smoke(tmp_path, "seed=1")
    run_dir = prepare_run_dir(cfg, argv=["torchrl-recon"])
    release_run_dir(run_dir)
    meta = json.loads((run_dir / "meta.json").read_text())
    (run_dir / "meta.json").write_text(json.dumps({**meta, "git": None}))
    run_dir = prepare_run_dir(cfg, argv=["torchrl-recon"])
    release_run_dir(run_dir)
    meta = json.loads((run_dir / "meta.json").read_text())
    assert meta["resumed"] and meta["previous"][-1]["git"] is None
    assert "warning" not in capsys.readouterr().err


def test_git_info_outside_a_checkout(tmp_path):
    assert git_info(tmp_path) == {"commit": "unknown", "dirty": None}


def test_changed_config_is_refused_but_logger_progress_stop_after_may_change(tmp_path):
    run_dir = prepare_run_dir(_smoke(tmp_path))
    release_run_dir(run_dir)
    with pytest.raises(RunDirConflict, match=r"retrainings: 2 -> 3"):
        prepare_run_dir(_smoke(tmp_path, "retrainings=3"))
    resumed = prepare_run_dir(
        _smoke(tmp_path, "logger.backend=none", "progress=true", "stop_after=validation")
    )
    release_run_dir(resumed)
    meta = json.loads((resumed / "meta.json").read_text())
    assert meta["resumed"] is True and len(meta["previous"]) == 1
    assert OmegaConf.load(resumed / "config.yaml").stop_after == "validation"


def test_a_config_yaml_torn_at_a_line_end_is_refused_naming_it(tmp_path):
    """A torn ``config.yaml`` that still parses (cut after a whole line) reads as another
    configuration: refused before anything is written, the message naming the file."""
    run_dir = prepare_run_dir(_smoke(tmp_path))
    release_run_dir(run_dir)
    config = run_dir / "config.yaml"
    lines = config.read_text().splitlines(keepends=True)
    # cut before the top-level key at or above the middle: no key is left without its value
    cut = max(i for i in range(1, len(lines) // 2 + 1) if not lines[i][0].isspace())
    config.write_text("".join(lines[:cut]))
    torn = config.read_bytes()
    with pytest.raises(RunDirConflict) as err:
        prepare_run_dir(_smoke(tmp_path))
    first = str(err.value).splitlines()[0]
    assert first.endswith("a different configuration (its config.yaml):"), first
    assert "restore config.yaml if it was damaged" in str(err.value)
    assert config.read_bytes() == torn


def test_resume_accepts_a_run_made_before_a_schema_key_existed(tmp_path):
    run_dir = prepare_run_dir(_smoke(tmp_path))
    release_run_dir(run_dir)
    saved = OmegaConf.load(run_dir / "config.yaml")
    del saved.models.uncertainty["kind"]  # as written before the key was added
    OmegaConf.save(saved, run_dir / "config.yaml")
    release_run_dir(prepare_run_dir(_smoke(tmp_path)))  # the default compares equal
    with pytest.raises(RunDirConflict, match=r"models.uncertainty.kind: 'reconstruction' -> 'rnd'"):
        prepare_run_dir(_smoke(tmp_path, "models.uncertainty.kind=rnd"))


def test_second_process_on_same_dir_is_refused(tmp_path):
    import subprocess
    import sys

    run_dir = prepare_run_dir(_smoke(tmp_path))
    try:
        code = (
            "import fcntl, sys; f = open(sys.argv[1], 'w')\n"
            "try:\n fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)\nexcept OSError:\n sys.exit(3)\n"
        )
        proc = subprocess.run([sys.executable, "-c", code, str(run_dir / ".lock")], check=False)
        assert proc.returncode == 3
    finally:
        release_run_dir(run_dir)


def test_write_results_adds_meta(tmp_path):
    run_dir = prepare_run_dir(_smoke(tmp_path))
    release_run_dir(run_dir)
    res = explore_result(0, [1.0, 2.0], [0.5, float("nan")])
    path = write_results(run_dir, res)
    back = json.loads(path.read_text())
    assert back["arms"]["random"]["mse"] == [1.0, 2.0]
    assert math.isnan(back["arms"]["active"]["mse"][1])
    assert back["meta"]["seed"] == 0 and "finished_utc" in back["meta"]


# ------------------------------------------------------------------------------------------
# loggers


def test_csv_logger_logs_hparams_and_scalars(tmp_path):
    cfg = _smoke(tmp_path)
    logger = make_logger(cfg, tmp_path)
    logger.log_scalar("x", 1.5, step=0)
    logger.shutdown()
    root = tmp_path / "explore_drone_seed0"
    assert (root / "scalars" / "x.csv").read_text().strip() == "0,1.5"
    hparams = next((root / "texts").glob("hparams*")).read_text()
    assert "guided.planner.kind: shooting" in hparams and "seed: 0" in hparams
    assert make_logger(_smoke(tmp_path, "logger.backend=none"), tmp_path) is None


# ------------------------------------------------------------------------------------------
# plots


def test_plots_write_pngs(tmp_path):
    explore = explore_result(0, [10.0, 12.0], [7.0, 8.0])
    control = control_result(
        0, {"baseline": [1.0, 2.0], "u_low": [0.5, 0.7], "gradient_beta_0.1": [0.4, 0.6]}
    )
    paths = save_figures(explore, tmp_path / "e") + save_figures(control, tmp_path / "c")
    assert sorted(p.name for p in paths) == ["control_errors.png", "table1.png", "trajectory.png"]
    for p in paths:
        assert p.is_file() and p.stat().st_size > 1000
    several = [
        explore_result(s, [10.0 + s, 11.0], [7.0, 8.0 + s], env=e)
        for s in range(3)
        for e in ("drone", "minitaur")
    ]
    figs = {
        "table1_seeds.png": plot_table1(several),
        "errors.png": plot_control_errors(control),
        "traj.png": plot_trajectory(control["trajectory_example"], max_dims=2),
    }
    for name, fig in figs.items():
        fig.savefig(tmp_path / name)
        assert (tmp_path / name).stat().st_size > 1000
    assert len(figs["traj.png"].axes) == 4  # 2 state dims, each with a twin u axis
    assert len(figs["errors.png"].axes) == 4  # MSE, cost error, real cost, re-plans


# ------------------------------------------------------------------------------------------
# summaries


RANDOM = [10.0, 12.0, 11.0, 13.0, 9.0]
ACTIVE = [7.0, 8.0, 8.0, 9.0, 6.0]


def _write(tmp_path, results):
    for r in results:
        d = tmp_path / f"{r['experiment']}_{r['env']}_seed{r['seed']}"
        d.mkdir(parents=True)
        (d / "results.json").write_text(json.dumps(r))


def test_summarize_explore_statistics(tmp_path):
    # per-seed arm means are RANDOM / ACTIVE (each the mean of two retrainings)
    _write(
        tmp_path,
        [
            explore_result(s, [r - 1, r + 1], [a - 0.5, a + 0.5])
            for s, (r, a) in enumerate(zip(RANDOM, ACTIVE, strict=True))
        ],
    )
    summary = summarize([tmp_path])
    s = summary["envs"]["drone"]
    assert summary["experiment"] == "explore" and s["seeds"] == [0, 1, 2, 3, 4]
    assert s["per_seed"]["random"] == RANDOM and s["per_seed"]["active"] == ACTIVE
    assert s["arms"]["random"]["mean"] == pytest.approx(11.0)
    assert s["arms"]["random"]["std"] == pytest.approx(math.sqrt(2.5))
    assert s["arms"]["active"]["mean"] == pytest.approx(7.6)
    assert s["arms"]["active"]["std"] == pytest.approx(math.sqrt(1.3))
    assert s["ratio"] == pytest.approx(7.6 / 11.0)
    t = s["tests"]["paired_t"]
    assert t["statistic"] == pytest.approx(-3.4 / (math.sqrt(0.3) / math.sqrt(5)))
    assert t["p_value"] == pytest.approx(stats.ttest_rel(ACTIVE, RANDOM).pvalue)
    w = s["tests"]["wilcoxon"]
    assert w["statistic"] == 0.0 and w["p_value"] == pytest.approx(2 / 32)
    table = format_table(summary)
    assert "drone" in table and "11 ± 1.581" in table and "7.6 ± 1.14" in table


def test_summarize_few_seeds_reports_nan(tmp_path):
    _write(tmp_path, [explore_result(0, [10.0, 12.0], [7.0, 8.0])])
    s = summarize([tmp_path / "explore_drone_seed0" / "results.json"])["envs"]["drone"]
    assert math.isnan(s["tests"]["paired_t"]["p_value"])
    assert "at least 2 seeds" in s["tests"]["paired_t"]["note"]
    assert "at least 5 seeds" in s["tests"]["wilcoxon"]["note"]
    assert "not computed" in format_table(summarize([tmp_path]))


def test_summarize_control_pools_episodes(tmp_path):
    _write(
        tmp_path,
        [
            control_result(0, {"baseline": [1.0, 3.0]}),
            control_result(1, {"baseline": [5.0, float("nan")]}),  # NaN: no planned step
        ],
    )
    s = summarize([tmp_path])["envs"]["drone"]["settings"]["baseline"]
    assert s["n_episodes"] == 4 and s["seeds"] == [0, 1]
    assert s["mean"]["prediction_mse"] == pytest.approx(3.0)
    assert s["std"]["prediction_mse"] == pytest.approx(2.0)
    assert s["mean"]["cost_error"] == pytest.approx(6.0)


def test_summarize_refuses_mixed_kinds_and_empty(tmp_path):
    _write(
        tmp_path,
        [control_result(0, {"baseline": [1.0]}), explore_result(0, [1.0, 2.0], [1.0, 1.0])],
    )
    with pytest.raises(ValueError, match="one experiment kind"):
        summarize([tmp_path])
    with pytest.raises(FileNotFoundError):
        summarize([tmp_path / "explore_drone_seed0" / "stages"])


def test_format_table_of_single_results():
    text = format_table(explore_result(2, [10.0, 12.0], [7.0, 8.0]))
    assert "seed 2" in text and "random" in text and "11 ± 1.414" in text and "Welch" in text
    text = format_table(control_result(0, {"baseline": [1.0, 3.0], "u_low": [0.5]}))
    assert "baseline" in text and "u_low" in text and "prediction_mse" in text


# ------------------------------------------------------------------------------------------
# runner and command line


def _fake_experiments(monkeypatch, stop=False):
    def fn(ctx):
        if stop:
            raise StopRequested("validation")
        assert (ctx.run_dir / "config.yaml").is_file()
        return explore_result(ctx.seed, [10.0, 12.0], [7.0, 8.0], env=ctx.cfg.env.name)

    explore = dataclasses.replace(EXPERIMENT_TYPES["explore"], run=fn)
    monkeypatch.setitem(EXPERIMENT_TYPES, "explore", explore)


def test_runner_writes_results_figures_and_table(tmp_path, monkeypatch, capsys):
    _fake_experiments(monkeypatch)
    results = runner.run(_smoke(tmp_path))
    run_dir = tmp_path / "run" / "seed0"
    assert results["ratio"] == pytest.approx(7.5 / 11)
    assert json.loads((run_dir / "results.json").read_text())["meta"]["seed"] == 0
    assert (run_dir / "table1.png").stat().st_size > 1000
    assert (run_dir / "explore_drone_seed0" / "scalars" / "results" / "ratio.csv").is_file()
    assert "ratio active / random" in capsys.readouterr().out


def test_runner_reports_stop(tmp_path, monkeypatch, capsys):
    _fake_experiments(monkeypatch, stop=True)
    assert runner.run(_smoke(tmp_path, "stop_after=validation")) is None
    out = capsys.readouterr().out
    assert (
        "stopped after stage 'validation'" in out and "Re-running the same command resumes" in out
    )
    assert not (tmp_path / "run" / "seed0" / "results.json").exists()


def test_cli_runs_recipe_through_hydra_without_writing_to_cwd(tmp_path, monkeypatch):
    _fake_experiments(monkeypatch)
    monkeypatch.chdir(tmp_path)
    recipe = RECIPES / "drone" / "explore_smoke.yaml"
    out = tmp_path / "out"
    assert run_recipe("explore", recipe, [f"output_dir={out}/seed${{seed}}", "seed=4"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    run_dir = out / "seed4"
    assert {"config.yaml", "meta.json", "results.json", "table1.png"} <= {
        p.name for p in run_dir.iterdir()
    }
    assert not (run_dir / ".hydra").exists()
    meta = json.loads((run_dir / "meta.json").read_text())
    assert meta["job_overrides"][-1] == "seed=4"
    # the runner raised glibc's malloc thresholds before the run (on a glibc Linux, as CI's)
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    assert meta["malloc_keeps_freed_memory"] is glibc


def test_cli_refuses_bad_recipes_before_any_work(tmp_path, capsys):
    recipe = RECIPES / "drone" / "explore_smoke.yaml"
    assert run_recipe("explore", recipe, ["guided.foo=1"]) == 2
    assert run_recipe("explore", recipe, ["seed=0,x"], multirun=True) == 2
    assert run_recipe("control", recipe, []) == 2
    assert run_recipe("explore", tmp_path / "none.yaml", []) == 2
    err = capsys.readouterr().err
    assert "guided.foo" in err and "'seed'" in err and "explore" in err and "none.yaml" in err


def test_cli_help_lists_experiments(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for word in ("explore", "control", "summarize", "Table 1", "Fig. 3", "-m seed="):
        assert word in out
    with pytest.raises(SystemExit):
        main(["explore", "--help"])
    assert "\n  drone/explore\n" in capsys.readouterr().out  # the shipped recipes, by name


def test_cli_summarize(tmp_path, capsys):
    _write(tmp_path, [explore_result(s, [10.0, 12.0 + s], [7.0, 8.0]) for s in range(2)])
    assert main(["summarize", str(tmp_path), "--out", str(tmp_path / "summary")]) == 0
    out = capsys.readouterr().out
    assert "Table 1" in out and "drone" in out
    assert (tmp_path / "summary" / "summary_explore.json").is_file()
    assert (tmp_path / "summary" / "table1.png").stat().st_size > 1000
    assert main(["summarize", str(tmp_path / "summary")]) == 2
