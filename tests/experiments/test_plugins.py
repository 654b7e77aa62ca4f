"""A user's own planner and estimator named in a recipe (``kind: module:Class`` with the class's
own ``kwargs``), the shipped kinds in the same form, one error line for a wrong class or
keyword, choices as plain strings, and old run directories (flat planner blocks) read back."""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

import torchrl_recon
from tests.experiments import grouping
from tests.experiments.tiny import TINY
from tests.normalized import fitted
from torchrl_recon.cli import main, run_recipe
from torchrl_recon.experiments.config import upgrade_legacy_config
from torchrl_recon.experiments.recipe import RecipeError, load_recipe
from torchrl_recon.experiments.recipe_planning import build_planner
from torchrl_recon.experiments.run_dir import check_run_dir, read_config
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import Objective, PlanningModel
from torchrl_recon.planners.registry import PLANNERS

ROOT = Path(torchrl_recon.__file__).parents[1]
DRONE = ROOT / "recipes" / "drone"

PARTS = '''
from torchrl_recon.modules import ReconstructionUncertainty
from torchrl_recon.planners import RandomShootingPlanner


class MyPlanner(RandomShootingPlanner):
    """Random shooting that counts its plans."""

    plans = 0

    def __init__(self, model, objective, *, horizon, num_candidates=16, label="mine"):
        super().__init__(model, objective, horizon=horizon, num_candidates=num_candidates)
        self.label = label

    def plan(self, *args, **kwargs):
        type(self).plans += 1
        return super().plan(*args, **kwargs)


class MyAutoencoder(ReconstructionUncertainty):
    """The autoencoder, with a keyword of its own."""

    built = []

    def __init__(self, obs_dim, action_dim, *, window=10, hidden_size=100, activation="relu",
                 code_scale=1.0):
        super().__init__(obs_dim, action_dim, window=window, hidden_size=hidden_size,
                         activation=activation)
        type(self).built.append((obs_dim, hidden_size, code_scale))


class NotAPlanner:
    def __init__(self, model, objective, *, horizon):
        pass
'''

CONTROL = [
    *TINY,
    "episodes=1",
    "random_episodes=2",
    "random_episode_steps=12",
    "env.episode_steps=12",
    "warmup_random_steps=3",
    "progress=false",
]


@pytest.fixture
def parts(tmp_path, monkeypatch) -> str:
    """The user's module on sys.path; returns its (unique) name."""
    name = f"user_parts_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{name}.py").write_text(PARTS)
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


def test_a_users_planner_and_estimator_run_from_a_recipe(parts, tmp_path, capsys):
    import importlib

    out = tmp_path / "run"
    setting = f"{{name: mine, planner: {{kind: '{parts}:MyPlanner', kwargs: {{horizon: 3, num_candidates: 8, label: x}}}}}}"
    args = ["control", str(DRONE / "control_smoke.yaml"), *CONTROL, f"output_dir={out}"]
    args += [f"settings=[{setting}]", f"models.uncertainty.kind={parts}:MyAutoencoder"]
    args += ["+models.uncertainty.kwargs.code_scale=0.5"]
    assert main(args) == 0, capsys.readouterr().err
    module = importlib.import_module(parts)
    assert module.MyPlanner.plans > 0
    assert (12, 4, 0.5) in module.MyAutoencoder.built  # the drone's 12 states, TINY's width
    results = json.loads((out / "results.json").read_text())
    assert set(results["settings"]) == {"mine"}
    saved = OmegaConf.load(out / "config.yaml")
    assert saved.settings[0].planner.kind == f"{parts}:MyPlanner"
    assert saved.models.uncertainty.kwargs == {"code_scale": 0.5}
    assert main(args) == 0  # resumes: the stored config compares equal


WRONG = [
    (
        ["settings.0.planner.kind={m}:NotAPlanner"],
        ["'settings[0].planner.kind'", "PlannerBase"],
    ),
    (
        ["settings.0.planner.kind=no_such_module_q:P"],
        ["'settings[0].planner.kind'", "cannot import", "PYTHONPATH"],
    ),
    (
        ["settings.0.planner.kind={m}:Nope"],
        ["'settings[0].planner.kind'", "no attribute 'Nope'"],
    ),
    (["settings.0.planner.kind=mpc"], ["'settings[0].planner.kind'", "'mpc'", "'mppi'"]),
    (
        ["settings.0.planner.kind={m}:MyPlanner", "+settings.0.planner.kwargs.colour=1"],
        ["'settings[0].planner.kwargs'", "['colour']", "'label'"],
    ),
    (
        ["models.uncertainty.kind={m}:MyPlanner"],
        ["'models.uncertainty.kind'", "UncertaintyEstimator"],
    ),
    (
        ["models.uncertainty.kind={m}:MyAutoencoder", "+models.uncertainty.kwargs.nope=1"],
        ["'models.uncertainty.kwargs'", "['nope']", "code_scale"],
    ),
    (
        ["+models.uncertainty.kwargs.hidden_size=3"],
        ["'models.uncertainty.kwargs'", "hidden_size", "models.uncertainty.hidden_size"],
    ),
    (
        [
            "~guided.planner.kwargs",
            "+guided.planner.kwargs={horizon: 10}",
            "guided.planner.kind=gradient",
        ],
        ["'guided.planner'", "guided.beta = 0.0", "non-zero"],
    ),
]
# A settings case and a models case share one run (distinct top-level keys, each checked on its
# own; each case's words inside its own problem of the line: tests/experiments/grouping.py)
WRONG_GROUPS = [[WRONG[0], WRONG[5]], [WRONG[1], WRONG[6]], [WRONG[2], WRONG[7]]]
WRONG_GROUPS += [[WRONG[3]], [WRONG[4]], [WRONG[8]]]
assert sorted(map(str, sum(WRONG_GROUPS, []))) == sorted(map(str, WRONG))  # each case once


@pytest.mark.parametrize(
    "cases", WRONG_GROUPS, ids=["+".join(o[0] for o, _ in g) for g in WRONG_GROUPS]
)
def test_a_wrong_class_or_keyword_is_one_line_naming_the_key(parts, cases, tmp_path, capsys):
    overrides = [o.replace("{m}", parts) for case, _ in cases for o in case]
    explore = any(o.lstrip("~+").startswith("guided") for o in overrides)
    recipe = DRONE / ("explore_smoke.yaml" if explore else "control_smoke.yaml")
    out = tmp_path / "run"
    code = run_recipe(recipe.stem.split("_")[0], recipe, [f"output_dir={out}", *overrides])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and not out.exists()
    assert len(lines) == 1 and "Traceback" not in err, err
    found = grouping.problems(lines[0]) if len(cases) > 1 else lines[0:1]
    for case, words in cases:
        assert any(all(w in p for w in words) for p in found), (case, words, lines[0])


@pytest.mark.parametrize(
    "kind, kwargs",
    [
        ("shooting", {"horizon": 4, "num_candidates": 8}),
        ("cem", {"horizon": 4, "num_candidates": 8, "num_elites": 2, "iterations": 2}),
        ("gradient", {"horizon": 4, "restarts": 2, "steps": 3, "lr": 0.1}),
    ],
)
def test_shipped_kinds_take_their_own_keywords(kind, kwargs):
    model = PlanningModel(fitted(LSTMWorldModel(3, 2, window=2)), lambda o, a, n: o.sum(-1))
    planner = build_planner(OmegaConf.create({"kind": kind, "kwargs": kwargs}), model, Objective())
    assert type(planner) is PLANNERS[kind]
    assert all(getattr(planner, k) == v for k, v in kwargs.items())
    result = planner.plan(torch.zeros(2, 3), torch.zeros(2, 2), torch.zeros(3))
    assert result.actions.shape == (4, 2)


def test_shipped_kind_in_a_recipe():
    cfg = load_recipe(
        DRONE / "control_smoke.yaml",
        [
            "settings.0.planner.kind=cem",
            "+settings.0.planner.kwargs.num_elites=4",
            "+settings.0.planner.kwargs.iterations=2",
        ],
    )
    assert OmegaConf.to_container(cfg.settings[0].planner) == {
        "kind": "cem",
        "kwargs": {"horizon": 10, "num_candidates": 64, "num_elites": 4, "iterations": 2},
    }


def _legacy(planner: dict) -> dict:
    """The flat planner block a run directory stored before planner blocks took kwargs."""
    flat = {"horizon": 50, "num_candidates": 1000, "iterations": 5, "num_elites": 100}
    flat.update({"restarts": 16, "gradient_steps": 50, "lr": 0.05})
    own = dict(planner["kwargs"])
    if "steps" in own:
        own["gradient_steps"] = own.pop("steps")
    return {"kind": planner["kind"], **flat, **own}


@pytest.mark.parametrize("recipe", ["control_smoke", "explore_smoke"])
def test_an_old_run_directory_resumes_with_the_same_recipe(recipe, tmp_path):
    cfg = load_recipe(DRONE / f"{recipe}.yaml", [f"output_dir={tmp_path}"])
    old = OmegaConf.to_container(cfg, resolve=True)
    blocks = old["settings"] if "settings" in old else [old["guided"]]
    for block in blocks:
        block["planner"] = _legacy(block["planner"])
    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(old)))
    check_run_dir(cfg)  # no RunDirConflict
    assert OmegaConf.to_container(read_config(tmp_path)) == OmegaConf.to_container(cfg)
    changed = load_recipe(
        DRONE / f"{recipe}.yaml",
        [
            f"output_dir={tmp_path}",
            f"{'settings.0' if 'settings' in old else 'guided'}.planner.kwargs.horizon=7",
        ],
    )
    with pytest.raises(Exception, match="planner.kwargs.horizon: 10 -> 7"):
        check_run_dir(changed)


@pytest.mark.parametrize(
    "folder", ["control_gradient/drone/seed0", "explore/industrial_benchmark/seed0"]
)
def test_published_run_configs_read_back_in_the_new_form(folder, tmp_path):
    shutil.copy(ROOT / "docs" / "results" / folder / "config.yaml", tmp_path / "config.yaml")
    cfg = read_config(tmp_path)
    blocks = cfg.settings if "settings" in cfg else [cfg.guided]
    for block in blocks:
        assert set(block.planner) == {"kind", "kwargs"}
        assert "gradient_steps" not in block.planner.kwargs
    kinds = {b.planner.kind for b in blocks}
    assert kinds <= set(PLANNERS)
    assert upgrade_legacy_config(cfg) is cfg  # already in the new form


def test_choices_are_plain_strings_in_the_stored_config_and_named_when_wrong():
    cfg = load_recipe(DRONE / "control_smoke.yaml")
    text = OmegaConf.to_yaml(cfg)
    assert "mode: uncertainty" in text and "backend: csv" in text and "Replan" not in text
    assert cfg.replan.mode == "uncertainty" and f"{cfg.replan.mode}" == "uncertainty"
    assert json.dumps({"m": cfg.replan.mode}) == '{"m": "uncertainty"}'
    with pytest.raises(RecipeError) as info:
        load_recipe(DRONE / "control_smoke.yaml", ["replan.mode=sometimes"])
    message = str(info.value)
    assert "\n" not in message
    assert "'replan.mode' must be one of ['every_step', 'every_n', 'uncertainty']" in message
    assert "got 'sometimes'" in message
