"""Aggregate ``results.json`` files across seeds, print results as plain-text tables and save
their figures: one path for every experiment kind, each kind's own part looked up in the
registry (:mod:`~torchrl_recon.experiments.registry`).

Explore (Table 1): per seed, the arm means over retrainings; across seeds, mean ± sample std
(ddof = 1) of those per-seed means for each arm, the ratio active / random of the means, a
paired t-test across seeds and a Wilcoxon signed-rank test (from 5 seeds). Control (Fig. 3):
per setting, mean ± sample std over all episodes of all seeds (NaN values left out).
Calibrate: per estimator, mean ± std across seeds of every number of its row.

Results are data too: each ``results.json`` is checked before it is used
(:func:`~torchrl_recon.experiments.results_check.check_results`: finite numbers, means equal to
the mean of their values, the ratio equal to active / random), and published ones against the
SHA-256 manifest of their folder's records archive (:mod:`~torchrl_recon.archive`).
A file that fails is one :class:`~torchrl_recon.errors.DamagedFileError` naming it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from torchrl_recon.archive import verify_results
from torchrl_recon.experiments.registry import get_type
from torchrl_recon.experiments.results_check import check_results
from torchrl_recon.experiments.run_dir import read_results


def find_results(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """``results.json`` files: given directly, or found anywhere below the given directories,
    except those of runs inside another run (a comparison's outcome runs, part of its results).

    Only paths are returned, written as given (relative stays relative), each file once; read
    each with :func:`~torchrl_recon.experiments.run_dir.read_results` (plain JSON, checked).
    """
    found: list[Path] = []
    for p in paths:
        p = Path(p)
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


def summarize(paths: Iterable[str | os.PathLike[str]]) -> dict[str, Any]:
    """Aggregate ``results.json`` files (or directories holding them) of one experiment kind.

    Returns:
        ``{"experiment": kind, "files": [...], "envs": {env: summary}}``; for
        explore, each env summary holds ``seeds``, ``per_seed`` (arm means and ratio of each
        seed), ``arms`` (``mean``, ``std`` across seeds, ``n_seeds``, and the std over all
        retrainings of all seeds), ``ratio`` (active / random mean) and ``tests``
        (``paired_t`` and ``wilcoxon``, NaN with a ``note`` when there are too few seeds). For
        control, ``seeds`` and ``settings: {name: {"mean", "std", "n_episodes", "seeds"}}``
        over all episodes of all seeds (so it can be plotted with ``plot_control_errors``).
        ``archives`` lists the records archives the published files were verified against.

    Raises:
        FileNotFoundError: a path does not exist or no ``results.json`` was found.
        DamagedFileError: a ``results.json`` is not JSON or not an experiment's results
            (read as plain JSON by :func:`~torchrl_recon.experiments.run_dir.read_results`),
            fails :func:`~torchrl_recon.experiments.results_check.check_results`, or (published)
            differs from its folder's manifest
            (:func:`~torchrl_recon.archive.verify_results`).
        ValueError: the files mix experiment kinds, or one env repeats a seed.
    """
    files = find_results(paths)
    if not files:
        raise FileNotFoundError("No results.json found in the given paths.")
    results = [read_results(f) for f in files]
    for f, r in zip(files, results, strict=True):
        check_results(r, f)
    archives = verify_results(files)
    kinds = sorted({r.get("experiment") for r in results}, key=str)
    if len(kinds) != 1:
        raise ValueError(
            f"summarize takes results of one experiment kind, got {kinds}; summarise them separately."
        )
    kind = kinds[0]
    by_env: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        by_env.setdefault(r["env"], []).append(r)
    experiment = _kind_of(kind)
    envs = {env: experiment.summarize_env(runs) for env, runs in by_env.items()}
    processors = sorted({processor(r) for r in results})
    return {
        "experiment": kind,
        "files": [f.as_posix() for f in files],
        "envs": envs,
        "processors": processors,
        "archives": archives,
    }


def processor(results: Mapping[str, Any]) -> str:
    """The device a run was made on, from its ``meta``: results are bit-identical only on the
    same commit and the same kind of processor.

    Examples:
        >>> meta = {"device": {"device": "cpu", "cpu_model": "AMD EPYC", "cpu_capability": "AVX512"}}
        >>> processor({"meta": meta})
        'cpu: AMD EPYC (AVX512)'
        >>> processor({"meta": {}})
        'not recorded'
    """
    info = results.get("meta", {}).get("device")
    if not info:
        return "not recorded"
    if str(info.get("device", "")).startswith("cuda"):
        return f"{info['device']}: {info.get('name')} (CPU {info.get('cpu_model')})"
    return f"{info.get('device')}: {info.get('cpu_model')} ({info.get('cpu_capability')})"


def relative_to(path: str | os.PathLike[str], root: str | os.PathLike[str]) -> str:
    """``path`` as a POSIX path relative to the folder ``root`` (``..`` where it must).

    Examples:
        >>> relative_to("runs/drone/seed0/results.json", "runs/drone/summary")
        '../seed0/results.json'
    """
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(root))).as_posix()


def _kind_of(name: Any):
    try:
        return get_type(name)
    except ValueError:
        raise ValueError(f"Unknown experiment kind {name!r} in results.") from None


def format_table(results_or_summary: Mapping[str, Any]) -> str:
    """A plain-text table of one results dict or of a :func:`summarize` output (which ends with
    the processors the runs were made on)."""
    r = results_or_summary
    try:
        kind = get_type(r.get("experiment"))
    except ValueError:
        raise ValueError(f"format_table: unknown experiment {r.get('experiment')!r}.") from None
    text = kind.summary_table(r) if "envs" in r else kind.result_table(r)
    if "processors" in r:
        text += "\nmade on: " + "; ".join(r["processors"])
    for a in r.get("archives", []):
        text += (
            f"\nverified: {a['results']} results.json and {a['members']} records of "
            f"{a['archive']} against its SHA-256 manifest"
        )
    return text


def _save(figures: list[tuple[str, Figure]], directory: Path) -> list[Path]:
    paths = []
    for name, fig in figures:
        fig.savefig(directory / name, dpi=120)
        paths.append(directory / name)
    return paths


def save_figures(results: Mapping[str, Any], run_dir: str | os.PathLike[str]) -> list[Path]:
    """Write the figures of one results dict into ``run_dir``; return their paths.

    explore: ``table1.png``; control: ``control_errors.png`` and, when the results hold a
    trajectory example, ``trajectory.png``; calibrate: ``calibration.png``.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        kind = get_type(results.get("experiment"))
    except ValueError:
        raise ValueError(
            f"save_figures: unknown experiment {results.get('experiment')!r}."
        ) from None
    return _save(kind.figures(results), run_dir)


def save_summary(
    summary: Mapping[str, Any], results: list[Mapping[str, Any]], out: str | os.PathLike[str]
) -> list[Path]:
    """Write ``summary_<kind>.json`` and the summary's figures into ``out``; return the paths
    (the JSON first).

    The file paths the summary names (``files``, ``archives``) are written relative to ``out``
    (``../seed0/results.json``): a summary holds no absolute path of the machine it was made on.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    kind = summary["experiment"]
    path = out / f"summary_{kind}.json"
    written = {
        **summary,
        "files": [relative_to(f, out) for f in summary.get("files", [])],
        "archives": [
            {**a, "archive": relative_to(a["archive"], out)} for a in summary.get("archives", [])
        ],
    }
    path.write_text(json.dumps(written, indent=1))
    return [path, *_save(get_type(kind).summary_figures(summary, results), out)]
