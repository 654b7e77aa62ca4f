"""The package's layout: few modules at its root, the estimators in their own subpackage (their
names still exported by ``torchrl_recon.modules``), and the old paths of the modules that moved
(to ``torchrl_recon.runs``, ``torchrl_recon.estimators``, ``torchrl_recon.devices``,
``torchrl_recon.trainers.configs``) still import for one release, each with one
``DeprecationWarning`` naming its new path, as the very module at that path."""

from __future__ import annotations

import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import torchrl_recon
from torchrl_recon.runs._moved import MOVED

PACKAGE = Path(torchrl_recon.__file__).parent
ROOT_MODULES = {"cli", "devices", "errors", "plugins"}


def test_the_root_holds_at_most_five_modules():
    found = {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    assert found == ROOT_MODULES and len(found) <= 5


def _old_file(old: str) -> Path:
    return PACKAGE.parent.joinpath(*old.split("."))


@pytest.mark.parametrize("old", sorted(MOVED))
def test_no_file_is_left_at_an_old_path(old):
    assert not _old_file(old).with_suffix(".py").exists() and not _old_file(old).is_dir()


def _forget(old: str) -> None:
    """Undo an earlier import of ``old`` (sys.modules and its package's attribute)."""
    sys.modules.pop(old, None)
    parent, name = old.rsplit(".", 1)
    package = importlib.import_module(parent)
    if name in vars(package) and vars(package)[name] is sys.modules.get(MOVED[old]):
        delattr(package, name)


def _deprecations(caught) -> list[str]:
    return [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_path_imports_the_new_module_with_one_warning(old):
    new = MOVED[old]
    _forget(old)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
        again = importlib.import_module(old)  # warned once: the second import is sys.modules'
    assert module is again is importlib.import_module(new) is sys.modules[old]
    assert _deprecations(caught) == [f"{old} moved to {new}; import it from there"]
    assert module.__name__ == module.__spec__.name == new  # the new module's identity is kept
    parent, name = old.rsplit(".", 1)
    assert getattr(importlib.import_module(parent), name) is module


def test_from_an_old_path_import_a_name_points_at_the_user_line():
    _forget("torchrl_recon.timing")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from torchrl_recon.timing import interleaved_median_ms  # noqa: PLC0415
    from torchrl_recon.runs.timing import interleaved_median_ms as new

    assert interleaved_median_ms is new
    [warning] = [w for w in caught if issubclass(w.category, DeprecationWarning)]
    assert "torchrl_recon.runs.timing" in str(warning.message)
    assert warning.filename == __file__  # the stacklevel names the user's import


def test_from_the_package_import_an_old_name():
    _forget("torchrl_recon.files")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from torchrl_recon import files  # noqa: PLC0415
    import torchrl_recon.runs.files

    assert files is torchrl_recon.runs.files
    assert _deprecations(caught) == [
        "torchrl_recon.files moved to torchrl_recon.runs.files; import it from there"
    ]


def test_the_package_never_imports_an_old_path():
    """The library's own code imports the new paths (the shim is for users' code only)."""
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        for old in MOVED:
            for spelling in (f"import {old}\n", f"from {old} import", f"import {old} "):
                assert spelling not in text or path.name == "_moved.py", f"{path}: {old}"


def test_the_estimators_are_their_own_subpackage_and_still_exported_by_modules():
    import torchrl_recon.estimators as estimators  # noqa: PLC0415
    import torchrl_recon.modules as modules  # noqa: PLC0415

    for name in estimators.__all__:
        assert getattr(modules, name) is getattr(estimators, name), name
        assert name in modules.__all__
    assert {c.__module__.rsplit(".", 1)[0] for c in estimators.ESTIMATORS.values()} == {
        "torchrl_recon.estimators"
    }
    from torchrl_recon.devices import module_device, module_dtype  # noqa: PLC0415

    assert (modules.module_device, modules.module_dtype) == (module_device, module_dtype)


def test_importing_a_package_s_names_does_not_warn():
    """``from torchrl_recon.modules import ReconstructionUncertainty`` is a user's import, not
    an old path."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from torchrl_recon.estimators import ReconstructionUncertainty as new  # noqa: PLC0415
        from torchrl_recon.modules import (  # noqa: PLC0415
            ReconstructionUncertainty,
            module_device,
        )
    assert ReconstructionUncertainty is new and module_device.__module__ == "torchrl_recon.devices"
    assert _deprecations(caught) == []


# Entered from the estimators, from the modules, from a module of each: one interpreter imports
# each afresh (torch stays; the library's modules are dropped between entries).
FIRST_IMPORTS = """
import sys
import torch, tensordict, torchrl  # noqa: F401
for first in sys.argv[1:]:
    for name in [n for n in sys.modules if n.startswith("torchrl_recon")]:
        del sys.modules[name]
    __import__(first)
    import torchrl_recon.estimators as e, torchrl_recon.modules as m
    assert m.ReconstructionUncertainty is e.ReconstructionUncertainty, first
    assert e.ESTIMATORS["reconstruction"] is m.ReconstructionUncertainty, first
"""


def test_either_package_imports_first():
    """``torchrl_recon.modules`` re-exports the estimators, which import its modules: whichever
    a fresh interpreter imports first, both end up whole."""
    firsts = ["torchrl_recon.estimators", "torchrl_recon.estimators.uncertainty"]
    firsts += ["torchrl_recon.estimators.population", "torchrl_recon.modules"]
    firsts += ["torchrl_recon.modules.checks", "torchrl_recon.modules.world_model"]
    subprocess.run([sys.executable, "-c", FIRST_IMPORTS, *firsts], check=True, timeout=300)
