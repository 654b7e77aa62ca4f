"""The old paths of the modules that moved, kept importable for one release.

``torchrl_recon.timing`` (and ``allocator``, ``archive``, ``files``, ``interrupts``,
``provenance``) moved to ``torchrl_recon.runs.<name>``; the uncertainty estimators from
``torchrl_recon.modules.<name>`` to ``torchrl_recon.estimators.<name>`` (the registry,
``modules.estimators``, to ``estimators.registry``); ``torchrl_recon.modules.device`` into
``torchrl_recon.devices``; the config store ``torchrl_recon.configs`` to
``torchrl_recon.trainers.configs``; the fit loops, ``torchrl_recon.training`` (a name too close
to ``torchrl_recon.trainers``, TorchRL's ``Trainer`` and its hooks), to ``torchrl_recon.fitting``
(:data:`MOVED` lists them all). :func:`install` (called when
``torchrl_recon`` is imported) adds a finder to :data:`sys.meta_path` that answers an import of
an old path with the module at its new one, the same object, and one ``DeprecationWarning``
naming the new path. No file is left at the old path.

Examples:
    >>> import sys, warnings
    >>> sys.modules.pop("torchrl_recon.timing", None) and None
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     import torchrl_recon.timing
    >>> import torchrl_recon.runs.timing
    >>> torchrl_recon.timing is torchrl_recon.runs.timing
    True
    >>> print(caught[0].message)
    torchrl_recon.timing moved to torchrl_recon.runs.timing; import it from there
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from types import ModuleType

MOVED = {
    **{
        f"torchrl_recon.{name}": f"torchrl_recon.runs.{name}"
        for name in ("allocator", "archive", "files", "interrupts", "provenance", "timing")
    },
    **{
        f"torchrl_recon.modules.{name}": f"torchrl_recon.estimators.{name}"
        for name in ("uncertainty", "reconstruction", "population", "ensemble", "mc_dropout")
        + ("rnd", "world_model_ensemble", "_one_step")
    },
    "torchrl_recon.modules.estimators": "torchrl_recon.estimators.registry",
    "torchrl_recon.modules.device": "torchrl_recon.devices",
    "torchrl_recon.configs": "torchrl_recon.trainers.configs",
    **{
        f"torchrl_recon.training{name}": f"torchrl_recon.fitting{name}"
        for name in ("", ".checkpoint", ".early_stopping", ".fit", ".fit_data", ".fit_graph")
        + (".fit_step", ".online")
    },
}
"""Each old dotted path and the module now at its place."""


class _MovedLoader(importlib.abc.Loader):
    """Loads an old path as the module at its new one (imported, never executed twice)."""

    def __init__(self, new: str) -> None:
        self.new = new

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        module = importlib.import_module(self.new)
        self._spec = module.__spec__  # the import system sets the old path's spec: put it back
        # stacklevel 2: the import statement (the warnings module skips importlib's frames)
        warnings.warn(
            f"{spec.name} moved to {self.new}; import it from there", DeprecationWarning, 2
        )
        return module

    def exec_module(self, module: ModuleType) -> None:
        module.__spec__ = self._spec


class _MovedFinder(importlib.abc.MetaPathFinder):
    """Finds the old paths of :data:`MOVED` (and nothing else)."""

    def find_spec(self, fullname, path=None, target=None):
        new = MOVED.get(fullname)
        return None if new is None else importlib.util.spec_from_loader(fullname, _MovedLoader(new))


def install() -> None:
    """Put the finder first on :data:`sys.meta_path` (once): a module of a moved package
    (``torchrl_recon.training.fit``) would otherwise be found by the path finder in the new
    package's folder and run a second time under its old name."""
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _MovedFinder())
