"""A built wheel holds the shipped recipes, and a (non-editable) install finds them by name from
any folder; ``torchrl-recon recipes`` lists them."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from torchrl_recon.cli import main, shipped_recipes
from torchrl_recon.experiments.compose import RECIPES_DIR

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow  # 11 s wheel build
def test_the_wheel_holds_the_recipes_and_an_install_finds_them_by_name(tmp_path):
    source = tmp_path / "source"  # built from a copy: the checkout gets no build/ or egg-info
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(
        ROOT / "torchrl_recon",
        source / "torchrl_recon",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    build = [*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp_path), str(source)]
    subprocess.run(build, check=True, cwd=tmp_path)
    (wheel,) = tmp_path.glob("torchrl_recon-*.whl")
    shipped = sorted(p.relative_to(RECIPES_DIR).as_posix() for p in RECIPES_DIR.rglob("*.yaml"))
    prefix = "torchrl_recon/recipes/"
    with zipfile.ZipFile(wheel) as whl:
        held = sorted(n[len(prefix) :] for n in whl.namelist() if n.startswith(prefix))
    assert held == shipped and "drone/explore.yaml" in held

    target, elsewhere = tmp_path / "site", tmp_path / "elsewhere"
    subprocess.run([*pip, "install", "--no-deps", "--target", str(target), str(wheel)], check=True)
    elsewhere.mkdir()
    code = (
        "import torchrl_recon; from torchrl_recon.experiments.recipe import resolve_recipe_path; "
        "print(torchrl_recon.__file__); print(resolve_recipe_path('drone/explore'))"
    )
    env = {**os.environ, "PYTHONPATH": str(target)}
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=elsewhere, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    package, recipe = out.stdout.split()
    assert Path(package).is_relative_to(target), "imported the checkout, not the installed wheel"
    assert Path(recipe) == target / "torchrl_recon" / "recipes" / "drone" / "explore.yaml"


def test_recipes_command_lists_the_shipped_recipes_by_kind_and_name(capsys):
    assert main(["recipes"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].split() == ["kind", "recipe", "about"]
    listed = [line.split()[:2] for line in lines[2:]]
    assert ["explore", "drone/explore"] in listed and ["calibrate", "minitaur/calibrate"] in listed
    assert ["control", "all_envs/control_bands"] in listed
    assert len(listed) == len(shipped_recipes()) == len(list(RECIPES_DIR.glob("*/*.yaml")))
    assert "Active (uncertainty-guided) vs random exploration on the Drone." in out
    assert main(["recipes", "calibrate"]) == 0
    kinds = {line.split()[0] for line in capsys.readouterr().out.splitlines()[2:]}
    assert kinds == {"calibrate"}
