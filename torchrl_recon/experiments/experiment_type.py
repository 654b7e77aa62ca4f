"""What an experiment kind is: everything the CLI, the runner and the recipe checks need to run
it (how its results are shown is its :class:`~torchrl_recon.reports.Report`)."""

from __future__ import annotations

import itertools
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from types import ModuleType
from typing import Any

from omegaconf import DictConfig

from torchrl_recon.experiments.context import RecipeLoader, RunContext

_FIELD = re.compile(r"\{(\w+)\}")


@dataclass(frozen=True)
class ExperimentType:
    """One experiment kind.

    Attributes:
        name: the command and the recipes' ``experiment`` value.
        help: one line for ``torchrl-recon --help``.
        schema: the recipe's config dataclass (``torchrl_recon.experiments.config``).
        stages: stage name templates in run order; ``{x}`` stands for a value (``{n}`` a count).
        run: runs (or resumes) the experiment in a :class:`RunContext`; returns its results.
        check: the kind's own value checks ``check(cfg, errors, recipes)``.
        list_field: ``(key, item schema)`` of a list whose items have a schema of their own.
        stage_values: ``cfg → {field: values}`` of the templates' fields the recipe fixes.
    """

    name: str
    help: str
    schema: type
    stages: tuple[str, ...]
    run: Callable[[RunContext], dict[str, Any]]
    check: Callable[[DictConfig, Any, RecipeLoader], None]
    list_field: tuple[str, type] | None = None
    stage_values: Callable[[DictConfig], Mapping[str, Sequence[str]]] = lambda cfg: {}

    @classmethod
    def of_module(cls, module: ModuleType, **given: Any) -> ExperimentType:
        """The kind a module defines: the ``given`` fields, its ``STAGES``, and each other
        field the module defines by name (``run``, ``check``, ...)."""
        found = {f.name: getattr(module, f.name) for f in fields(cls) if hasattr(module, f.name)}
        return cls(**{**found, "stages": module.STAGES, **given})

    def stage_list(self, cfg: DictConfig | None) -> list[str]:
        """The stage names of ``cfg``'s run; a template's field the recipe leaves open is shown
        as ``<field>`` (``guided_data_<n>``).

        Examples:
            >>> from torchrl_recon.experiments.registry import get_type
            >>> get_type("explore").stage_list(None)[3]
            'guided_data_<n>'
        """
        values, names = self.stage_values(cfg) if cfg is not None else {}, []
        for template in self.stages:
            keys = [k for k in _FIELD.findall(template) if k in values]
            shown = _FIELD.sub(lambda m: m[0] if m[1] in values else f"<{m[1]}>", template)
            for combo in itertools.product(*(values[k] for k in keys)):
                names.append(shown.format(**dict(zip(keys, combo, strict=True))))
        return names

    def is_stage(self, cfg: DictConfig | None, name: str) -> bool:
        """Whether ``name`` is a stage of ``cfg``'s run (what ``stop_after`` may name): one of
        :meth:`stage_list`'s, with a number for ``<n>`` and any value for another ``<field>``."""
        shown = [re.escape(s).replace("<n>", r"\d+") for s in self.stage_list(cfg)]
        return any(re.fullmatch(re.sub(r"<\w+>", ".+", s), name) for s in shown)
