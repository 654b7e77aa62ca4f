"""What an experiment kind is: one :class:`ExperimentType` holds everything the CLI, the
runner, the recipe checks, ``summarize`` and the figures need to know about it."""

from __future__ import annotations

import itertools
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from types import ModuleType
from typing import Any

from matplotlib.figure import Figure
from omegaconf import DictConfig

from torchrl_recon.experiments.context import RecipeLoader, RunContext

Results = Mapping[str, Any]
Figures = list[tuple[str, Figure]]
"""Figures as (file name, figure) pairs."""
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
        summarize_env: the across-seeds summary of one env's results.
        result_table: the text table of one results dict.
        summary_table: the text table of one :func:`~.summary.summarize` output.
        headline: the results' numbers logged as scalars (``results/<key>``).
        figures: the figures of one results dict.
        summary_figures: the figures of a summary, ``(summary, results)``.
        list_field: ``(key, item schema)`` of a list whose items have a schema of their own.
        stage_values: ``cfg → {field: values}`` of the templates' fields the recipe fixes.
        outcome: the headline numbers of a results dict when run as a child of another.
    """

    name: str
    help: str
    schema: type
    stages: tuple[str, ...]
    run: Callable[[RunContext], dict[str, Any]]
    check: Callable[[DictConfig, Any, RecipeLoader], None]
    summarize_env: Callable[[list[dict[str, Any]]], dict[str, Any]]
    result_table: Callable[[Results], str]
    summary_table: Callable[[Results], str]
    headline: Callable[[Results], dict[str, float]]
    figures: Callable[[Results], Figures] = lambda results: []
    summary_figures: Callable[[Results, list[Results]], Figures] = lambda s, r: []
    list_field: tuple[str, type] | None = None
    stage_values: Callable[[DictConfig], Mapping[str, Sequence[str]]] = lambda cfg: {}
    outcome: Callable[[Results], dict[str, Any]] | None = None

    @classmethod
    def of_module(cls, module: ModuleType, stages: ModuleType, **given: Any) -> ExperimentType:
        """The kind a module defines: the ``given`` fields, ``run`` and ``STAGES`` from its
        ``stages`` module, and each other field the module defines by name (``check``, ...)."""
        found = {f.name: getattr(module, f.name) for f in fields(cls) if hasattr(module, f.name)}
        return cls(**{**found, "run": stages.run, "stages": stages.STAGES, **given})

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
