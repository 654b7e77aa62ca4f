"""Each stage of the three experiment kinds on its own (tiny configs from the smoke recipes),
the registry's stage names, the one mean ± std rule, and no import cycle in experiments/."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import pytest
import torch
from omegaconf import DictConfig, OmegaConf

import torchrl_recon
from tests.compilers import needs_cpp_compiler
from tests.experiments.tiny import TINY as TINY_OVERRIDES
from torchrl_recon.experiments import calibrate, control, explore
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.fit_stages import fit_stage
from torchrl_recon.experiments.recipe import load_recipe, validate
from torchrl_recon.experiments.recipe_models import build_models
from torchrl_recon.experiments.recipe_planning import planning_model
from torchrl_recon.experiments.registry import EXPERIMENT_TYPES, get_type
from torchrl_recon.planners.beta import window_uncertainty
from torchrl_recon.reports.stats import mean_std

PACKAGE = Path(torchrl_recon.__file__).parent
RECIPES = PACKAGE.parent / "recipes" / "industrial_benchmark"
TINY = [
    *TINY_OVERRIDES,
    "num_envs=1",  # the stages one env at a time (batches: tests/experiments/test_batched_envs.py)
]


def _ctx(tmp_path: Path, kind: str, *overrides: str) -> RunContext:
    cfg = load_recipe(RECIPES / f"{kind}_smoke.yaml", [*TINY, *overrides])
    return RunContext(cfg, tmp_path)


def test_explore_stages_one_by_one(tmp_path):
    ctx = _ctx(
        tmp_path,
        "explore",
        "env.episode_steps=10",
        "initial_random_steps=30",
        "validation.trajectories=2",
        "validation.steps=4",
        "guided.planner.kwargs.horizon=3",
        "guided.planner.kwargs.num_candidates=8",
    )
    initial = explore.random_data_stage(ctx, "initial_random", frames=30, keys=explore.DATA_KEYS)
    assert initial.numel() == 30 and ctx.stages.done("initial_random")
    world, estimator, _ = explore.models_stage(ctx, initial, "initial_models")
    assert (tmp_path / "checkpoints" / "initial_models.pt").is_file()
    validation = explore.validation_stage(ctx)
    assert validation.shape == (2, 3 + 4)
    record, data = explore.guided_round_stage(ctx, world, estimator, 0, 1, 10)
    assert data.numel() == record["steps"] == 10 and record["plans"] >= record["feasible_plans"]
    scale = torch.ones(initial["observation"].shape[-1])
    arms = {"random": initial, "active": initial}
    record = explore.retrain_stage(ctx, 0, [0, 1], arms, validation, scale)
    assert ctx.stages.done("retrain_0") and record["retrainings"] == [0, 1]
    for arm in ("random", "active"):
        assert len(record[arm]["mse"]) == 2 and all(math.isfinite(v) for v in record[arm]["mse"])
    # same data and same initialisation: both arms' retraining i fit to the same weights
    assert record["random"]["mse"] == pytest.approx(record["active"]["mse"], rel=1e-5)
    assert record["random"]["mse"][0] != record["random"]["mse"][1]


def test_control_stages_one_by_one(tmp_path):
    ctx = _ctx(
        tmp_path,
        "control",
        "random_episodes=2",
        "random_episode_steps=12",
        "env.episode_steps=8",
        "episodes=1",
    )
    data = control.random_data_stage(ctx, "random_data", frames=24, episode_steps=12)
    world, estimator, _ = explore.models_stage(ctx, data, "models")
    u = window_uncertainty(data, estimator, sequence_length=ctx.cfg.training.slice_len)
    threshold = control.replan_threshold(ctx.cfg, u)
    assert threshold > 0 and u.device.type == "cpu"
    setting = ctx.cfg.settings[0]
    setting.planner.kwargs.horizon, setting.planner.kwargs.num_candidates = 3, 8
    model = planning_model(ctx.cfg, world, estimator)
    controller = control.Controller(model, threshold, 1.0, control.state_scale(data))
    record = control.setting_stage(ctx, setting, controller)
    assert len(record["episodes"]) == 1
    assert math.isnan(record["std"]["real_cost"])  # one episode: no spread to measure


@needs_cpp_compiler  # the switch checks for one when the model is built
@pytest.mark.parametrize("kind", ["control", "explore", "online"])
def test_planning_compile_reaches_the_planning_model(kind, tmp_path):
    """``planning_compile`` is the planning model's ``compile`` (its pass compiles at the first
    plan; a run with it is checked against eager by hand: the control smoke's results moved at
    float rounding only). Each value is set on one loaded recipe and validated again, as a
    load validates it, not composed again: Hydra's parse of a value is not the property here
    (~0.5 s a composition)."""
    base = _ctx(tmp_path, kind).cfg

    def recipe(**values) -> DictConfig:
        return validate(OmegaConf.merge(base, values))

    for value, mode in ((False, None), (True, "default"), ("reduce-overhead", "reduce-overhead")):
        cfg = recipe(planning_compile=value)
        assert cfg.planning_compile == value
        world, estimator = build_models(cfg, 6, 3)
        assert planning_model(cfg, world, estimator).compile_mode == mode
    cfg = recipe(planning_compile=True, planning_threads=2)
    model = planning_model(cfg, *build_models(cfg, 6, 3))
    assert model.threads == 2 and model.executor.blocks_in_threads(model)


def test_fit_cuda_graph_reaches_the_retrainings(tmp_path, monkeypatch):
    """``fit_cuda_graph`` is the retrainings' ``fit_population(cuda_graph=...)`` (here the fit
    runs without it: the CPU has no CUDA graph; its CUDA test is in tests/test_device.py)."""
    seen = []
    real = explore.fit_population

    def spy(*args, cuda_graph, **kwargs):
        seen.append(cuda_graph)
        return real(*args, **kwargs)

    monkeypatch.setattr(explore, "fit_population", spy)
    for value in (False, True):
        ctx = _ctx(tmp_path / str(value), "explore", f"fit_cuda_graph={str(value).lower()}")
        data = explore.random_data_stage(ctx, "initial_random", frames=40, keys=explore.DATA_KEYS)
        scale = torch.ones(data["observation"].shape[-1])
        arms = {"random": data, "active": data}
        explore.retrain_stage(ctx, 0, [0], arms, data.reshape(4, -1)[:, :12], scale)
    assert seen == [False, True]


def test_calibrate_stages_one_by_one(tmp_path, monkeypatch):
    ctx = _ctx(
        tmp_path,
        "calibrate",
        "random_steps=24",
        "random_episode_steps=12",
        "evaluation.trajectories=3",
        "evaluation.horizon=3",
        "evaluation.ood_windows=4",
    )
    data = calibrate.random_data_stage(ctx, "random_data", frames=24, episode_steps=12)
    world, estimators, fits = calibrate.fit_stages(ctx, data)
    assert set(fits) == {"world_model", *estimators}
    assert all("val_loss" in record for record in fits.values())
    scale = torch.ones(data["observation"].shape[-1])
    evaluation = calibrate.evaluation_stage(ctx, world, estimators, scale)
    assert set(evaluation["estimators"]) == set(estimators)
    # the timing stage times on the models' device (on CUDA: until the device is done)
    seen = []

    def fake_timer(fns, repeats, *, device=None):
        seen.append(device)
        return dict.fromkeys(fns, 1.0)

    monkeypatch.setattr(calibrate, "interleaved_median_ms", fake_timer)
    times = calibrate.timing(ctx.cfg, world, estimators, data)
    assert seen and all(d == ctx.device for d in seen)
    assert set(times[f"H{ctx.cfg.timing.horizons[0]}"]) == {"cem_without_u_ms", *estimators}
    if any(ctx.cfg.outcomes[f"{k}_recipe"] for k in ("explore", "control")):
        with pytest.raises(ValueError, match="outcomes run other recipes"):
            calibrate.outcome_stages(ctx)  # a context without a runner


def test_fit_stage_resumes_from_its_checkpoint(tmp_path):
    ctx = _ctx(tmp_path, "control", "random_episodes=2", "random_episode_steps=12")
    data = control.random_data_stage(ctx, "random_data", frames=24, episode_steps=12)
    world, estimator = build_models(
        ctx.cfg, data["observation"].shape[-1], data["action"].shape[-1], ctx.device
    )
    first = fit_stage(ctx, "models", data, {"world_model": world, "uncertainty": estimator})
    assert set(first) >= {"world_model_val_loss", "uncertainty_val_loss"}
    fresh, fresh_u = build_models(
        ctx.cfg, data["observation"].shape[-1], data["action"].shape[-1], ctx.device
    )
    again = fit_stage(ctx, "models", data, {"world_model": fresh, "uncertainty": fresh_u})
    assert again == first  # read back, not refitted
    for a, b in zip(world.parameters(), fresh.parameters(), strict=True):
        assert torch.equal(a, b)


def test_stage_names_of_the_registry():
    assert list(EXPERIMENT_TYPES) == ["explore", "control", "calibrate", "online"]
    cfg = load_recipe(RECIPES / "control_smoke.yaml")
    control = get_type("control")
    names = control.stage_list(cfg)
    assert names[:2] == ["random_data", "models"] and names[2] == "setting_baseline"
    assert control.is_stage(cfg, "setting_baseline") and not control.is_stage(cfg, "setting_x")
    explore = get_type("explore")
    assert explore.is_stage(None, "retrain_3") and explore.is_stage(None, "guided_data_0")
    assert not explore.is_stage(None, "retrain_active_3")
    assert "retrain_<n>" in explore.stage_list(None)


def test_one_mean_std_rule():
    assert mean_std([]) == pytest.approx((math.nan, math.nan), nan_ok=True)
    mean, std = mean_std([4.0])
    assert mean == 4.0 and math.isnan(std)
    assert mean_std([1.0, 3.0]) == pytest.approx((2.0, math.sqrt(2.0)))


def test_reports_read_results_without_the_experiments():
    """Reports depend on results alone: a user summarising published runs needs no runner."""
    for path in (PACKAGE / "reports").glob("*.py"):
        found = [m for m in _imports(path) if m.startswith("torchrl_recon.experiments")]
        assert not found, f"{path.name} imports {found}"


def _imports(path: Path) -> set[str]:
    """Modules of torchrl_recon a file imports, at any depth (functions included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m.startswith("torchrl_recon.")}


def test_experiments_have_no_import_cycle():
    files = {
        f"torchrl_recon.{package}.{p.stem}": p
        for package in ("experiments", "reports")
        for p in (PACKAGE / package).glob("*.py")
        if p.stem != "__init__"
    }
    files["torchrl_recon.cli"] = PACKAGE / "cli.py"
    graph = {name: {m for m in _imports(path) if m in files} for name, path in files.items()}
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in graph[node]:
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " → ".join([*trail, node, nxt]))
            if nxt not in state:
                visit(nxt, [*trail, node])
        state[node] = 2

    for name in graph:
        if name not in state:
            visit(name, [])
