"""benchmarks/fit_comparison.py runs at a tiny size and prints each arm's figures; its library arm
is ``fit_models``' world-model fit step for step."""

from __future__ import annotations

import dataclasses
import importlib.util
import io
import json
import re
from contextlib import redirect_stdout
from pathlib import Path

import pytest
import torch

pytest.importorskip("mujoco")

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "fit_comparison.py"
TINY = ["--seeds", "0", "1", "--frames", "240", "--steps", "4", "--eval-every", "2"]
TINY += ["--test-frames", "60", "120"]


def _script():
    spec = importlib.util.spec_from_file_location("fit_comparison", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow  # ~10 s: two MuJoCo collections per seed and 12 tiny fits per seed
def test_fit_comparison_prints_each_arms_figures(tmp_path):
    script, out, path = _script(), io.StringIO(), tmp_path / "fits.jsonl"
    with redirect_stdout(out):
        records = script.main([*TINY, "--out", str(path)])
    text = out.getvalue()
    number = r"[0-9.]+ ± [0-9.]+"
    for train, arms in script.TRAIN_ARMS.items():
        for arm in arms:
            row = rf"^\| {train} \| {re.escape(arm)} \| " + rf"{number} \| " * 6
            assert re.search(row, text, re.M), f"no row of figures for {train} / {arm}:\n{text}"
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert len(lines) == len(records) == sum(len(a) for a in script.TRAIN_ARMS.values())
    assert all(len(r["per_seed"]) == 2 for r in lines)
    recipe = next(r for r in lines if (r["train"], r["arm"]) == ("random", "library (recipe)"))
    assert [s["steps_run"] for s in recipe["per_seed"]] == [4, 4]


def test_library_arm_is_fit_models_world_model_fit():
    from torchrl_recon.experiments.online import recipe_schedule
    from torchrl_recon.experiments.recipe import load_recipe, resolve_recipe_path
    from torchrl_recon.experiments.recipe_models import build_world_model
    from torchrl_recon.fitting.online import fit_models

    script = _script()
    cfg = load_recipe(resolve_recipe_path(script.RECIPE))
    schedule = dataclasses.replace(recipe_schedule(cfg), steps=4, eval_every=2)
    data = script.random_data(200, 0)
    torch.manual_seed(0)
    ours = build_world_model(cfg, 9, 1)
    torch.manual_seed(0)
    theirs = build_world_model(cfg, 9, 1)
    fit_models(theirs, None, data, schedule, seed=3, warm=False)
    record = script.library_fit(ours, data, schedule, seed=3)
    assert record["steps_run"] == 4
    for key, value in theirs.state_dict().items():
        assert torch.equal(ours.state_dict()[key], value), key
