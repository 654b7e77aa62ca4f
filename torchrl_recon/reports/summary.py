"""Aggregate ``results.json`` files across seeds, print them as plain-text tables and save their
figures, each kind's part (``summarize_env``, tables, figures) from its :class:`~.report.Report`. Each
file is checked first (:func:`~.results_check.check_results`), a
published one also against its folder's SHA-256 manifest (:mod:`~torchrl_recon.runs.archive`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from torchrl_recon.devices import processor
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.reports.registry import get_report
from torchrl_recon.reports.report import Figures
from torchrl_recon.reports.results_check import check_results
from torchrl_recon.runs.archive import verify_results
from torchrl_recon.runs.files import read_json


def read_results(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A ``results.json`` file (or the one in a run directory) as checked plain JSON.

    Examples:
        >>> import tempfile
        >>> run_dir = Path(tempfile.mkdtemp())
        >>> _ = (run_dir / "results.json").write_text('{"experiment": "explore", "env": "drone"}')
        >>> read_results(run_dir)["env"]
        'drone'
    """
    path = Path(path) / "results.json" if Path(path).is_dir() else Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"No results file at {path}.")
    remedy = "re-run the experiment to write it again, or leave that run directory out."
    results = read_json(path, remedy=remedy)
    if not isinstance(results, dict) or not isinstance(results.get("experiment"), str):
        raise DamagedFileError(
            f"{path} is not the results of an experiment (no 'experiment'); {remedy}"
        )
    return results


def find_results(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """``results.json`` files, each once and written as given: the files given, and those below
    the directories given except those of runs inside another run (part of its results)."""
    found: list[Path] = []
    for p in map(Path, paths):
        if p.is_file():
            found.append(p)
        elif p.is_dir():
            below = sorted(p.rglob("results.json"))
            runs = {f.parent for f in below}
            found.extend(f for f in below if not runs.intersection(f.parent.parents))
        else:
            raise FileNotFoundError(f"No such file or directory: {p}")
    unique: dict[Path, Path] = {}
    for f in found:
        unique.setdefault(f.resolve(), f)
    return list(unique.values())


def summarize_by_kind(
    paths: Iterable[str | os.PathLike[str]],
) -> list[tuple[dict[str, Any], list[dict[str, Any]]]]:
    """Each experiment kind's :func:`summarize` of the ``results.json`` files found at
    ``paths``, with the results it read (each file read and checked once), by kind's name."""
    paths = list(paths)
    if not (files := find_results(paths)):
        raise FileNotFoundError(f"no results.json found below {', '.join(map(str, paths))}")
    by_kind: dict[str, list[tuple[Path, dict[str, Any]]]] = {}
    for f in files:
        check_results(r := read_results(f), f)
        by_kind.setdefault(r["experiment"], []).append((f, r))
    return [
        (_summary(kind, found), [r for _, r in found]) for kind, found in sorted(by_kind.items())
    ]


def summarize(paths: Iterable[str | os.PathLike[str]]) -> dict[str, Any]:
    """Aggregate the ``results.json`` files of one experiment kind found at ``paths`` into
    ``{"experiment", "files", "envs": {env: <the kind's summarize_env>}, "processors",
    "archives"}`` (the records archives the published files were verified against).

    Raises:
        FileNotFoundError: a path does not exist or no ``results.json`` was found.
        DamagedFileError: a file is not an experiment's results, fails its checks or differs
            from its folder's manifest.
        ValueError: the files mix experiment kinds, or one env repeats a seed (any kind).
    """
    found = summarize_by_kind(paths)
    if len(found) != 1:
        kinds = [s["experiment"] for s, _ in found]
        raise ValueError(
            f"summarize takes results of one experiment kind, got {kinds}; summarise them separately."
        )
    return found[0][0]


def _summary(kind: str, found: list[tuple[Path, dict[str, Any]]]) -> dict[str, Any]:
    by_env: dict[str, list[dict[str, Any]]] = {}
    for _, r in found:
        by_env.setdefault(r["env"], []).append(r)
    for env, runs in by_env.items():  # e.g. two variants of one env: each folder alone
        seeds = [r.get("seed") for r in sorted(runs, key=lambda r: r.get("seed", 0))]
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"{kind} results of env {env!r} repeat a seed: {seeds}")
    files = [f for f, _ in found]
    return {
        "experiment": kind,
        "files": [f.as_posix() for f in files],
        "envs": {env: get_report(kind).summarize_env(runs) for env, runs in by_env.items()},
        "processors": sorted({processor(r.get("meta", {}).get("device")) for _, r in found}),
        "archives": verify_results(files),
    }


def relative_to(path: str | os.PathLike[str], root: str | os.PathLike[str]) -> str:
    """``path`` as a POSIX path relative to the folder ``root`` (``..`` where it must).

    Examples:
        >>> relative_to("runs/drone/seed0/results.json", "runs/drone/summary")
        '../seed0/results.json'
    """
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(root))).as_posix()


def format_table(results_or_summary: Mapping[str, Any]) -> str:
    """A plain-text table of one results dict or of a :func:`summarize` output (which ends with
    the processors the runs were made on and the archives verified)."""
    r = results_or_summary
    kind = get_report(r.get("experiment"))
    text = kind.summary_table(r) if "envs" in r else kind.result_table(r)
    if "processors" in r:
        text += "\nmade on: " + "; ".join(r["processors"])
    for a in r.get("archives", []):
        text += (
            f"\nverified: {a['results']} results.json and {a['members']} records of "
            f"{a['archive']} against its SHA-256 manifest"
        )
    return text


def _save(figures: Figures, directory: Path) -> list[Path]:
    for name, fig in figures:
        fig.savefig(directory / name, dpi=120)
    return [directory / name for name, _ in figures]


def save_figures(results: Mapping[str, Any], run_dir: str | os.PathLike[str]) -> list[Path]:
    """Write the figures of one results dict (its kind's ``figures``) into ``run_dir``; return
    their paths."""
    kind = get_report(results.get("experiment"))
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    return _save(kind.figures(results), Path(run_dir))


def save_summary(
    summary: Mapping[str, Any], results: list[Mapping[str, Any]], out: str | os.PathLike[str]
) -> list[Path]:
    """Write ``summary_<kind>.json`` and the summary's figures into ``out``; return the paths
    (the JSON first). The paths the summary names (``files``, ``archives``) are written relative
    to ``out`` (``../seed0/results.json``): a summary holds no absolute path of its machine."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"summary_{summary['experiment']}.json"
    files = [relative_to(f, out) for f in summary.get("files", [])]
    archives = summary.get("archives", [])
    archives = [{**a, "archive": relative_to(a["archive"], out)} for a in archives]
    path.write_text(json.dumps({**summary, "files": files, "archives": archives}, indent=1))
    figures = get_report(summary["experiment"]).summary_figures(summary, results)
    return [path, *_save(figures, out)]
