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
        stage_values: the values of the templates' fields the recipe fixes (``cfg → {field:
            values}``).
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
        """The kind a module defines: the ``given`` fields (``name``, ``help``, ``schema``, ...),
        ``run`` and ``STAGES`` from its ``stages`` module, and each other field the module
        defines by name (``check``, ``summarize_env``, ``result_table``, ...)."""
        found = {f.name: getattr(module, f.name) for f in fields(cls) if hasattr(module, f.name)}
        return cls(**{**found, "run": stages.run, "stages": stages.STAGES, **given})

    def _fields(self, cfg: DictConfig | None) -> Mapping[str, Sequence[str]]:
        return self.stage_values(cfg) if cfg is not None else {}

    def stage_list(self, cfg: DictConfig | None) -> list[str]:
        """The stage names of ``cfg``'s run; a template whose fields the recipe leaves open is
        shown as ``guided_data_<n>``.

        Examples:
            >>> from torchrl_recon.experiments.registry import get_type
            >>> get_type("explore").stage_list(None)[3]
            'guided_data_<n>'
        """
        values, names = self._fields(cfg), []
        for template in self.stages:
            fields = re.findall(r"\{(\w+)\}", template)
            if not all(f in values for f in fields):
                names.append(re.sub(r"\{(\w+)\}", r"<\1>", template))
                continue
            for combo in itertools.product(*(values[f] for f in fields)):
                names.append(template.format(**dict(zip(fields, combo, strict=True))))
        return names

    def is_stage(self, cfg: DictConfig | None, name: str) -> bool:
        """Whether ``name`` is a stage of ``cfg``'s run (what ``stop_after`` may name)."""
        values = self._fields(cfg)

        def field(f: str) -> str:
            if f not in values:
                return r"\d+" if f == "n" else ".+"
            return "(" + "|".join(re.escape(str(v)) for v in values[f]) + ")"

        parts = [re.split(r"\{(\w+)\}", t) for t in self.stages]
        patterns = [
            "".join(field(p) if i % 2 else re.escape(p) for i, p in enumerate(t)) for t in parts
        ]
        return any(re.fullmatch(p, name) for p in patterns)
