"""Aggregate ``results.json`` files across seeds, and print results as plain-text tables.

Explore (Table 1): per seed, the arm means over retrainings; across seeds, mean ± sample std
(ddof = 1) of those per-seed means for each arm, the ratio active / random of the means, a
paired t-test across seeds (``scipy.stats.ttest_rel``, needs ≥ 2 seeds) and a Wilcoxon
signed-rank test (``scipy.stats.wilcoxon``, reported from 5 seeds on).

Control (Fig. 3): per setting, mean ± sample std over all episodes of all seeds (NaN values,
from episodes without a planned step, are left out).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchrl_recon.experiments.control import METRICS as CONTROL_METRICS
from torchrl_recon.experiments.run_dir import read_results

MIN_SEEDS_TTEST = 2
MIN_SEEDS_WILCOXON = 5


def find_results(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """``results.json`` files: given directly, or found anywhere below the given directories.

    Only paths are returned; read each with
    :func:`~torchrl_recon.experiments.run_dir.read_results` (plain JSON, checked).
    """
    found: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_file():
            found.append(p)
        elif p.is_dir():
            found.extend(sorted(p.rglob("results.json")))
        else:
            raise FileNotFoundError(f"No such file or directory: {p}")
    unique = list(dict.fromkeys(f.resolve() for f in found))
    return unique


def _mean_std(values: Sequence[float]) -> tuple[float, float]:
    arr = np.asarray(values, dtype=float)
    if arr.size == 0:
        return float("nan"), float("nan")
    mean = float(arr.mean())
    std = float(arr.std(ddof=1)) if arr.size > 1 else float("nan")
    return mean, std


def _not_computed(n: int, minimum: int) -> dict[str, Any]:
    """A test entry for too few seeds: NaN statistic and p-value, and why."""
    nan = float("nan")
    note = f"not computed: needs at least {minimum} seeds, got {n}"
    return {"statistic": nan, "p_value": nan, "n": n, "note": note}


def _explore_env_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    seeds = [r.get("seed") for r in runs]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"explore results of env {runs[0]['env']!r} repeat a seed: {seeds}")
    per_seed = {arm: [float(r["arms"][arm]["mean"]) for r in runs] for arm in ("random", "active")}
    arms = {}
    for arm, means in per_seed.items():
        mean, std = _mean_std(means)
        pooled = [float(v) for r in runs for v in r["arms"][arm]["mse"]]
        arms[arm] = {
            "mean": mean,
            "std": std,
            "n_seeds": len(means),
            "std_all_retrainings": float(np.std(pooled, ddof=1))
            if len(pooled) > 1
            else float("nan"),
            "n_retrainings": len(pooled),
        }
    random_mean, active_mean = arms["random"]["mean"], arms["active"]["mean"]
    ratio = active_mean / random_mean if random_mean else float("nan")
    n = len(runs)
    tests: dict[str, Any] = {}
    if n >= MIN_SEEDS_TTEST:
        from scipy import stats

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            t = stats.ttest_rel(per_seed["active"], per_seed["random"])
        tests["paired_t"] = {
            "statistic": float(t.statistic),
            "p_value": float(t.pvalue),
            "n": n,
            "note": "paired t-test across seeds of the per-seed arm means (active vs random)",
        }
    else:
        tests["paired_t"] = _not_computed(n, MIN_SEEDS_TTEST)
    if n >= MIN_SEEDS_WILCOXON:
        from scipy import stats

        diffs = np.subtract(per_seed["active"], per_seed["random"])
        if np.all(diffs == 0):
            w_stat, w_p, note = float("nan"), 1.0, "all paired differences are zero"
        else:
            w = stats.wilcoxon(per_seed["active"], per_seed["random"])
            w_stat, w_p = float(w.statistic), float(w.pvalue)
            note = "Wilcoxon signed-rank test across seeds (two-sided)"
        tests["wilcoxon"] = {"statistic": w_stat, "p_value": w_p, "n": n, "note": note}
    else:
        tests["wilcoxon"] = _not_computed(n, MIN_SEEDS_WILCOXON)
    return {
        "seeds": seeds,
        "per_seed": {
            "random": per_seed["random"],
            "active": per_seed["active"],
            "ratio": [
                a / r if r else float("nan")
                for a, r in zip(per_seed["active"], per_seed["random"], strict=True)
            ],
            "within_seed_test": [r.get("test") for r in runs],
        },
        "arms": arms,
        "ratio": ratio,
        "tests": tests,
        "mse_units": runs[0].get("mse_units", ""),
    }


def _control_env_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    seeds = [r.get("seed") for r in runs]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"control results of env {runs[0]['env']!r} repeat a seed: {seeds}")
    names: list[str] = []
    for r in runs:
        names.extend(n for n in r["settings"] if n not in names)
    settings: dict[str, Any] = {}
    for name in names:
        episodes = [ep for r in runs for ep in r["settings"].get(name, {}).get("episodes", [])]
        metrics = [m for m in CONTROL_METRICS if any(m in ep for ep in episodes)]
        mean, std = {}, {}
        for m in metrics:
            # episodes without a planned step report NaN metrics: left out, as in run_control
            values = [float(ep[m]) for ep in episodes if m in ep]
            mean[m], std[m] = _mean_std([v for v in values if math.isfinite(v)])
        settings[name] = {
            "mean": mean,
            "std": std,
            "n_episodes": len(episodes),
            "seeds": [r.get("seed") for r in runs if name in r["settings"]],
        }
    return {"seeds": seeds, "settings": settings}


CALIBRATION_COLUMNS = (
    ("spearman", "Spearman(Σu, err)"),
    ("auroc_error_above_median", "AUROC err>median"),
    ("ood_auroc_state_shift", "OOD AUROC states"),
    ("ood_auroc_action_bound", "OOD AUROC actions"),
    ("score_ratio_H{h}", "score time ×AE H={h}"),
    ("cem_ratio_H{h}", "CEM time ×AE H={h}"),
    ("explore_ratio", "explore active/random"),
)


def _calibrate_env_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per estimator, mean ± std across seeds of every numeric entry of its row."""
    runs = sorted(runs, key=lambda r: r.get("seed", 0))
    estimators: dict[str, Any] = {}
    for name in runs[0]["estimators"]:
        rows = [r["estimators"][name] for r in runs if name in r["estimators"]]
        keys = [k for k, v in rows[0].items() if isinstance(v, (int, float))]
        stats = {k: _mean_std([row[k] for row in rows]) for k in keys}
        estimators[name] = {
            "mean": {k: m for k, (m, _) in stats.items()},
            "std": {k: sd for k, (_, sd) in stats.items()},
            "n_seeds": len(rows),
        }
    return {
        "seeds": [r.get("seed") for r in runs],
        "horizons": runs[0].get("horizons", []),
        "estimators": estimators,
    }


def summarize(paths: Iterable[str | os.PathLike[str]]) -> dict[str, Any]:
    """Aggregate ``results.json`` files (or directories holding them) of one experiment kind.

    Returns:
        ``{"experiment": "explore" | "control", "files": [...], "envs": {env: summary}}``; for
        explore, each env summary holds ``seeds``, ``per_seed`` (arm means and ratio of each
        seed), ``arms`` (``mean``, ``std`` across seeds, ``n_seeds``, and the std over all
        retrainings of all seeds), ``ratio`` (active / random mean) and ``tests``
        (``paired_t`` and ``wilcoxon``, NaN with a ``note`` when there are too few seeds). For
        control, ``seeds`` and ``settings: {name: {"mean", "std", "n_episodes", "seeds"}}``
        over all episodes of all seeds (so it can be plotted with ``plot_control_errors``).

    Raises:
        FileNotFoundError: a path does not exist or no ``results.json`` was found.
        DamagedFileError: a ``results.json`` is not JSON or not an experiment's results
            (read as plain JSON by :func:`~torchrl_recon.experiments.run_dir.read_results`).
        ValueError: the files mix experiment kinds, or one env repeats a seed.
    """
    files = find_results(paths)
    if not files:
        raise FileNotFoundError("No results.json found in the given paths.")
    results = [read_results(f) for f in files]
    kinds = sorted({r.get("experiment") for r in results}, key=str)
    if len(kinds) != 1:
        raise ValueError(
            f"summarize takes results of one experiment kind, got {kinds}; summarise them separately."
        )
    kind = kinds[0]
    by_env: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        by_env.setdefault(r["env"], []).append(r)
    if kind == "explore":
        envs = {env: _explore_env_summary(runs) for env, runs in by_env.items()}
    elif kind == "control":
        envs = {env: _control_env_summary(runs) for env, runs in by_env.items()}
    elif kind == "calibrate":
        envs = {env: _calibrate_env_summary(runs) for env, runs in by_env.items()}
    else:
        raise ValueError(f"Unknown experiment kind {kind!r} in results.")
    processors = sorted({processor(r) for r in results})
    return {
        "experiment": kind,
        "files": [str(f) for f in files],
        "envs": envs,
        "processors": processors,
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


# ----------------------------------------------------------------------------------------------
# Tables


def _fmt(x: Any, digits: int = 4) -> str:
    if x is None:
        return "-"
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(v):
        return "nan"
    if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
        return f"{v:.{max(digits - 1, 1)}e}"
    return f"{v:.{digits}g}"


def _pm(mean: Any, std: Any) -> str:
    return f"{_fmt(mean)} ± {_fmt(std)}"


def _render(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows, strict=True)]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    out = [line, "-" * len(line)]
    out += ["  ".join(str(c).ljust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(out)


def _explore_result_table(r: Mapping[str, Any]) -> str:
    arms = r["arms"]
    rows = [
        [arm, _pm(arms[arm]["mean"], arms[arm]["std"]), str(len(arms[arm].get("mse", [])))]
        for arm in ("random", "active")
        if arm in arms
    ]
    text = [
        f"explore — {r.get('env')} seed {r.get('seed')}: validation MSE over retrainings",
        _render(["arm", "MSE mean ± std", "retrainings"], rows),
        f"ratio active / random: {_fmt(r.get('ratio'))}",
    ]
    test = r.get("test")
    if test:
        text.append(
            f"{test.get('name', 'test')}: statistic {_fmt(test.get('statistic'))}, "
            f"p = {_fmt(test.get('p_value'))}"
        )
    if r.get("mse_units"):
        text.append(f"MSE: {r['mse_units']}")
    return "\n".join(text)


def _control_table(title: str, settings: Mapping[str, Any], count_key: str) -> str:
    metrics = [m for m in CONTROL_METRICS if any(m in s.get("mean", {}) for s in settings.values())]
    rows = []
    for name, s in settings.items():
        n = s.get(count_key)
        if n is None:
            n = len(s.get("episodes", []))
        rows.append([name, str(n)] + [_pm(s["mean"].get(m), s["std"].get(m)) for m in metrics])
    return title + "\n" + _render(["setting", "episodes", *metrics], rows)


def _calibrate_table(title: str, rows_by_name: Mapping[str, Any], horizon: int) -> str:
    """One row per estimator; ``rows_by_name[name]`` maps column keys to numbers."""
    keys = [k.format(h=horizon) for k, _ in CALIBRATION_COLUMNS]
    header = ["estimator", *(label.format(h=horizon) for _, label in CALIBRATION_COLUMNS)]
    rows = [[name, *(_fmt(row.get(k), 3) for k in keys)] for name, row in rows_by_name.items()]
    return title + "\n" + _render(header, rows)


def format_table(results_or_summary: Mapping[str, Any]) -> str:
    """A plain-text table of one results dict or of a :func:`summarize` output (which ends with
    the processors the runs were made on)."""
    text = _table(results_or_summary)
    if "processors" in results_or_summary:
        text += "\nmade on: " + "; ".join(results_or_summary["processors"])
    return text


def _table(results_or_summary: Mapping[str, Any]) -> str:
    r = results_or_summary
    kind = r.get("experiment")
    if "envs" in r:  # a summary
        if kind == "explore":
            rows = []
            for env, s in r["envs"].items():
                t, w = s["tests"]["paired_t"], s["tests"]["wilcoxon"]
                rows.append(
                    [
                        env,
                        str(len(s["seeds"])),
                        _pm(s["arms"]["random"]["mean"], s["arms"]["random"]["std"]),
                        _pm(s["arms"]["active"]["mean"], s["arms"]["active"]["std"]),
                        _fmt(s["ratio"], 3),
                        _fmt(t["p_value"], 3),
                        _fmt(w["p_value"], 3),
                    ]
                )
            notes = sorted(
                {
                    s["tests"][k]["note"]
                    for s in r["envs"].values()
                    for k in ("paired_t", "wilcoxon")
                    if s["tests"][k]["note"].startswith("not computed")
                }
            )
            text = (
                "Table 1 — validation MSE, mean ± std across seeds of the per-seed means\n"
                + _render(
                    ["env", "seeds", "random", "active", "active/random", "t-test p", "Wilcoxon p"],
                    rows,
                )
            )
            if notes:
                text += "\n" + "\n".join(f"note: {n}" for n in notes)
            return text
        if kind == "control":
            parts = []
            for env, s in r["envs"].items():
                title = f"control — {env}, seeds {s['seeds']}: mean ± std over all episodes"
                parts.append(_control_table(title, s["settings"], "n_episodes"))
            return "\n\n".join(parts)
        if kind == "calibrate":
            parts = []
            for env, s in r["envs"].items():
                title = f"uncertainty estimators — {env}, seeds {s['seeds']}: mean across seeds"
                means = {name: e["mean"] for name, e in s["estimators"].items()}
                parts.append(_calibrate_table(title, means, (s["horizons"] or [0])[0]))
            return "\n\n".join(parts)
        raise ValueError(f"format_table: unknown experiment {kind!r}.")
    if kind == "explore":
        return _explore_result_table(r)
    if kind == "control":
        title = (
            f"control — {r.get('env')} seed {r.get('seed')}: mean ± std over episodes"
            f" (re-plan threshold {_fmt(r.get('replan_threshold'))})"
        )
        return _control_table(title, r["settings"], "n_episodes")
    if kind == "calibrate":
        title = (
            f"uncertainty estimators — {r.get('env')} seed {r.get('seed')} "
            f"(times as ratios to {r.get('reference_estimator')!r}, measured in the same run)"
        )
        return _calibrate_table(title, r["estimators"], (r.get("horizons") or [0])[0])
    raise ValueError(f"format_table: unknown experiment {kind!r}.")
