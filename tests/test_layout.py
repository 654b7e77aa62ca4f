"""The package's layout: few modules at its root, and the old paths of the modules that moved to
``torchrl_recon.runs`` still import for one release, each with one ``DeprecationWarning`` naming
its new path, as the very module at that path."""

from __future__ import annotations

import importlib
import sys
import warnings
from pathlib import Path

import pytest

import torchrl_recon
from torchrl_recon.runs._moved import MOVED

PACKAGE = Path(torchrl_recon.__file__).parent
ROOT_MODULES = {"cli", "configs", "devices", "errors", "plugins"}


def test_the_root_holds_at_most_five_modules():
    found = {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    assert found == ROOT_MODULES and len(found) <= 5
    for old in MOVED:  # no file left behind at an old path
        assert not (PACKAGE / f"{old.rsplit('.', 1)[1]}.py").exists()


def _forget(old: str) -> None:
    """Undo an earlier import of ``old`` (sys.modules and the package's attribute)."""
    sys.modules.pop(old, None)
    name = old.rsplit(".", 1)[1]
    if torchrl_recon.__dict__.get(name) is sys.modules.get(MOVED[old]):
        delattr(torchrl_recon, name)


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
    assert getattr(torchrl_recon, old.rsplit(".", 1)[1]) is module


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
