"""``torchrl_recon.planners`` exports what a user calls (issue 59 item 6); the names it exported
before stay importable from it for one release, with a DeprecationWarning naming their module."""

from __future__ import annotations

import ast
import importlib
import re
import warnings
from pathlib import Path

import pytest

import torchrl_recon.planners as planners

# The names the package exported before, and the module each is public in now.
MOVED = {
    "PlanFlags": "base",
    "PlanOutput": "base",
    "cost_to_u_ratio": "beta",
    "window_uncertainty": "beta",
    "bounds_from_spec": "bounds",
    "check_bounds_match": "bounds",
    "Gaussian": "cem",
    "run_aside": "cpu_threads",
    "run_blocks": "cpu_threads",
    "EliteMemory": "elite_memory",
    "COMPILE_MODES": "executors",
    "compile_mode": "executors",
    "threaded_pass": "executors",
    "WorldModelPlanningEnv": "model_env",
    "colored_noise": "noise",
    "TerminationFn": "planning_model",
    "check_step_fn": "planning_model",
    "PLANNERS": "registry",
    "check_planner_kwargs": "registry",
    "get_planner_class": "registry",
    "Iteration": "sampling",
    "BatchedWorldModelEnv": "torchrl_models",
    "CONTEXT_ACTION": "torchrl_models",
    "CONTEXT_OBS": "torchrl_models",
    "LSTMWorldModelModule": "torchrl_models",
    "TorchRLWorldModelAdapter": "torchrl_models",
}


def test_the_package_exports_at_most_16_names_each_importable():
    assert len(planners.__all__) <= 16, planners.__all__
    assert len(set(planners.__all__)) == len(planners.__all__)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a kept name imports without a warning
        for name in planners.__all__:
            assert getattr(planners, name) is not None
            exec(f"from torchrl_recon.planners import {name}", {})
    assert dir(planners) == sorted(planners.__all__)
    assert not set(MOVED) & set(planners.__all__)


@pytest.mark.parametrize("name", sorted(MOVED))
def test_a_moved_name_imports_from_the_package_with_a_deprecation_warning(name):
    home = f"torchrl_recon.planners.{MOVED[name]}"
    module = importlib.import_module(home)
    assert name in module.__all__  # public in its module
    with pytest.warns(DeprecationWarning) as caught:
        namespace = {}
        exec(f"from torchrl_recon.planners import {name}", namespace)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert message == f"torchrl_recon.planners.{name} is deprecated; import it from {home}"
    assert caught[0].filename == "<string>"  # points at the import, not at the package
    assert namespace[name] is getattr(module, name)
    with pytest.warns(DeprecationWarning, match=home):
        assert getattr(planners, name) is getattr(module, name)


def test_an_unknown_name_is_still_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        planners.nothing  # noqa: B018
    with pytest.raises(ImportError):
        exec("from torchrl_recon.planners import nothing", {})


def test_no_code_of_the_repository_imports_a_moved_name_from_the_package():
    """The library, its tests, benchmarks, examples and docs scripts import a moved name from its
    module, so that none of them warns."""
    root = Path(planners.__file__).resolve().parents[2]
    moved = "|".join(MOVED)
    dotted = re.compile(rf"\btorchrl_recon\.planners\.({moved})\b")
    left = []
    for folder in ("torchrl_recon", "tests", "benchmarks", "examples", "docs"):
        for path in sorted((root / folder).rglob("*.py")):
            if path in (Path(__file__).resolve(), Path(planners.__file__).resolve()):
                continue
            text = path.read_text()
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, ast.ImportFrom) and node.module == "torchrl_recon.planners":
                    left += [
                        f"{path}:{node.lineno} {a.name}" for a in node.names if a.name in MOVED
                    ]
            left += [f"{path}: {m.group(0)}" for m in dotted.finditer(text)]
    assert not left, left
