"""What an experiment kind is: one :class:`ExperimentType` holds everything the CLI, the
runner and the recipe checks need to know to run it (how its results are shown is its
:class:`~torchrl_recon.reports.Report`)."""

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
        schema: the recipe's config dataclass (:mod:`~torchrl_recon.experiments.config`).
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
        """The stage names of ``cfg``'s run; a template with a field the recipe leaves open is
        shown as ``guided_data_<n>``.

        Examples:
            >>> from torchrl_recon.experiments.registry import get_type
            >>> get_type("explore").stage_list(None)[3]
            'guided_data_<n>'
        """
        values, names = self.stage_values(cfg) if cfg is not None else {}, []
        for template in self.stages:
            keys = _FIELD.findall(template)
            if not all(k in values for k in keys):
                names.append(_FIELD.sub(r"<\1>", template))
                continue
            for combo in itertools.product(*(values[k] for k in keys)):
                names.append(template.format(**dict(zip(keys, combo, strict=True))))
        return names

    def is_stage(self, cfg: DictConfig | None, name: str) -> bool:
        """Whether ``name`` is a stage of ``cfg``'s run (what ``stop_after`` may name)."""
        values = self.stage_values(cfg) if cfg is not None else {}

        def field(match: re.Match[str]) -> str:  # a template's {key} as a pattern
            if (key := match[1]) not in values:
                return r"\d+" if key == "n" else ".+"
            return "(" + "|".join(re.escape(str(v)) for v in values[key]) + ")"

        escaped = [re.escape(t) for t in self.stages]  # {key} is escaped as \{key\}
        return any(re.fullmatch(re.sub(r"\\\{(\w+)\\\}", field, t), name) for t in escaped)
