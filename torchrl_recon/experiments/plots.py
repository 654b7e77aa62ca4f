"""Figures of the experiments (matplotlib, Agg canvas; no pyplot state, nothing shown).

* :func:`plot_table1`: Table 1 as bars, random vs active exploration, per environment.
* :func:`plot_control_errors`: Fig. 3 style, one bar per control setting for prediction MSE,
  cumulative-cost prediction error, real cumulative cost and re-plans per episode.
* :func:`plot_trajectory`: Fig. 2 style, predicted vs real states over an episode with the
  predicted uncertainty u on a twin axis and the re-planning instants marked.
* :func:`plot_calibration`: uncertainty estimators side by side (error ranking, OOD
  detection, cost relative to the autoencoder).
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

ARM_COLORS = {"random": "tab:gray", "active": "tab:orange"}

CONTROL_PANELS = (
    ("prediction_mse", "prediction MSE\n(predicted vs real states)"),
    ("cost_error", "|predicted − real|\ncumulative cost"),
    ("real_cost", "real cumulative cost"),
    ("replans", "re-plans per episode"),
)


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _nan_to_zero(values: Sequence[float]) -> list[float]:
    return [0.0 if v is None or not math.isfinite(float(v)) else float(v) for v in values]


def plot_table1(results: Sequence[Mapping[str, Any]]) -> Figure:
    """Bars of the validation MSE of random vs active exploration (Table 1), one group per env.

    With several results of one env (seeds), bars show the mean ± std across seeds of the
    per-seed arm means (sample std), and dots the per-seed means. With a single result, the
    bar is its mean ± std across its retrainings, and dots the individual retrainings.
    The title gives active / random mean.
    """
    if not results:
        raise ValueError("plot_table1 needs at least one explore results dict.")
    by_env: dict[str, list[Mapping[str, Any]]] = {}
    for res in results:
        if res.get("experiment") != "explore":
            raise ValueError(f"plot_table1 takes explore results, got {res.get('experiment')!r}.")
        by_env.setdefault(res["env"], []).append(res)
    envs = list(by_env)
    fig = _figure(max(5.5, 2.2 * len(envs) + 1.5), 4.2)
    ax = fig.add_subplot()
    width = 0.38
    ratios = []
    units = by_env[envs[0]][0].get("mse_units", "")
    for i, env in enumerate(envs):
        runs = by_env[env]
        means = {}
        for j, arm in enumerate(("random", "active")):
            if len(runs) == 1:
                points = [float(v) for v in runs[0]["arms"][arm]["mse"]]
                mean = float(runs[0]["arms"][arm]["mean"])
                std = float(runs[0]["arms"][arm]["std"])
            else:
                points = [float(r["arms"][arm]["mean"]) for r in runs]
                mean = float(np.mean(points))
                std = float(np.std(points, ddof=1))
            means[arm] = mean
            x = i + (j - 0.5) * width
            ax.bar(
                x,
                mean,
                width,
                yerr=std if math.isfinite(std) else 0.0,
                capsize=4,
                color=ARM_COLORS[arm],
                label=arm if i == 0 else None,
                alpha=0.85,
            )
            jitter = np.linspace(-0.08, 0.08, len(points)) if len(points) > 1 else [0.0]
            ax.scatter(x + np.asarray(jitter), points, s=10, color="black", zorder=3, linewidths=0)
        ratio = means["active"] / means["random"] if means["random"] else float("nan")
        ratios.append(f"{env} {ratio:.3g} ({len(runs)} seed{'s' if len(runs) > 1 else ''})")
    ax.set_xticks(range(len(envs)), envs)
    ax.set_ylabel("validation MSE")
    ax.set_title(
        "Table 1: validation MSE, random vs active exploration\nactive / random: "
        + "; ".join(ratios),
        fontsize=9,
    )
    if units:
        fig.supxlabel(textwrap.fill(f"MSE: {units}", 110), fontsize=6)
    top = max(b.get_height() for b in ax.patches)
    ax.set_ylim(0, 1.3 * top if top > 0 else 1.0)
    ax.legend(frameon=False, ncol=2, loc="upper center")
    return fig


def plot_control_errors(results: Mapping[str, Any]) -> Figure:
    """Fig. 3 style: per setting, mean ± std over episodes of the control metrics.

    Panels: prediction MSE, |predicted − real| cumulative cost, real cumulative cost, re-plans
    per episode. ``results`` is a control results dict, or an entry of a control summary
    (anything with ``settings: {name: {"mean": {...}, "std": {...}}}``); a setting's optional
    ``per_seed: {metric: [values]}`` is drawn as one dot per seed.
    """
    settings = results.get("settings") or {}
    if not settings:
        raise ValueError("plot_control_errors needs results with at least one setting.")
    names = list(settings)
    fig = _figure(max(10.0, 1.0 * len(names) * 4 / 2.5), 3.6)
    axes = fig.subplots(1, len(CONTROL_PANELS))
    colors = [f"C{i % 10}" for i in range(len(names))]
    for ax, (key, label) in zip(axes, CONTROL_PANELS, strict=True):
        means = _nan_to_zero([settings[n]["mean"].get(key, float("nan")) for n in names])
        stds = _nan_to_zero([settings[n]["std"].get(key, float("nan")) for n in names])
        ax.bar(range(len(names)), means, yerr=stds, capsize=3, color=colors, alpha=0.85)
        for i, n in enumerate(names):  # a summary's per-seed means, as dots
            points = (settings[n].get("per_seed") or {}).get(key, [])
            if points:
                ax.plot([i] * len(points), points, "o", color="black", ms=3, alpha=0.7)
        ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=7)
        ax.set_title(label, fontsize=9)
        ax.tick_params(axis="y", labelsize=7)
    env = results.get("env", "")
    seed = results.get("seed")
    title = "Uncertainty-aware control"
    if env:
        title += f" — {env}"
    if seed is not None:
        title += f", seed {seed}"
    fig.suptitle(title + " (mean ± std over episodes)", fontsize=10)
    return fig


def _dims_to_show(real: np.ndarray, max_dims: int) -> list[int]:
    std = real.std(axis=0) if real.shape[0] > 1 else np.abs(real[0])
    order = np.argsort(-np.nan_to_num(std, nan=-1.0), kind="stable")
    return sorted(int(i) for i in order[:max_dims])


def plot_trajectory(example: Mapping[str, Any], max_dims: int = 4) -> Figure:
    """Fig. 2 style: predicted vs real state over one episode, u on a twin axis, re-plans marked.

    Shows the ``max_dims`` state dimensions that vary most in the real trajectory.
    ``example``: ``{"setting", "real": [[float]*N]*L, "predicted": [[float]*N]*L,
    "uncertainty": [float]*L, "replanned": [bool]*L, "state_names": [str]*N}``.
    """
    real = np.asarray(example["real"], dtype=float)
    predicted = np.asarray(example["predicted"], dtype=float)
    if real.ndim != 2 or real.shape != predicted.shape:
        raise ValueError(
            f"trajectory example: real {real.shape} and predicted {predicted.shape} must both be [L, N]."
        )
    length, n = real.shape
    u = np.asarray(example.get("uncertainty", []), dtype=float)
    replanned = np.asarray(example.get("replanned", []), dtype=bool)
    names = list(example.get("state_names") or [f"s{i}" for i in range(n)])
    dims = _dims_to_show(real, max_dims)
    fig = _figure(8.0, 1.9 * len(dims) + 0.6)
    axes = np.atleast_1d(fig.subplots(len(dims), 1, sharex=True))
    t = np.arange(length)
    for k, (ax, d) in enumerate(zip(axes, dims, strict=True)):
        ax.plot(t, real[:, d], color="black", lw=1.2, label="real")
        ax.plot(t, predicted[:, d], color="tab:blue", lw=1.2, ls="--", label="predicted")
        ax.set_ylabel(names[d] if d < len(names) else f"s{d}", fontsize=8)
        for i in np.flatnonzero(replanned[:length]):
            ax.axvline(
                i,
                color="tab:red",
                lw=0.7,
                alpha=0.6,
                label="re-plan" if i == np.flatnonzero(replanned)[0] else None,
            )
        if u.size:
            twin = ax.twinx()
            twin.plot(t[: u.size], u[:length], color="tab:green", lw=0.9, alpha=0.8, label="u")
            twin.set_ylabel("u", color="tab:green", fontsize=8)
            twin.tick_params(axis="y", labelsize=7, colors="tab:green")
            if k == 0:
                handles, labels = ax.get_legend_handles_labels()
                h2, l2 = twin.get_legend_handles_labels()
                ax.legend(
                    handles + h2, labels + l2, fontsize=7, ncol=4, loc="upper left", frameon=False
                )
        elif k == 0:
            ax.legend(fontsize=7, ncol=3, loc="upper left", frameon=False)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time step")
    fig.suptitle(
        f"Predicted vs real trajectory — setting {example.get('setting', '?')}", fontsize=10
    )
    return fig


CALIBRATION_PANELS = (
    (("spearman", "auroc_error_above_median"), "ranks the real error", False),
    (("ood_auroc_state_shift", "ood_auroc_action_bound"), "out-of-distribution AUROC", False),
    (("score_ratio_H{h}", "cem_ratio_H{h}"), "time relative to the autoencoder", True),
)


def plot_calibration(results: Mapping[str, Any]) -> Figure:
    """Estimators side by side: Spearman and AUROC of u against the real error, OOD AUROC
    (states moved, actions at the bound), and scoring / CEM time as ratios to the reference
    estimator at the first timed horizon (log scale)."""
    rows = results.get("estimators") or {}
    if not rows:
        raise ValueError("plot_calibration needs calibrate results with at least one estimator.")
    names, horizon = list(rows), (results.get("horizons") or [0])[0]
    fig = _figure(max(9.0, 1.2 * len(names) * 3), 3.6)
    axes = fig.subplots(1, len(CALIBRATION_PANELS))
    width = 0.38
    for ax, (keys, title, log) in zip(axes, CALIBRATION_PANELS, strict=True):
        for j, key in enumerate(keys):
            key = key.format(h=horizon)
            values = _nan_to_zero([rows[n].get(key, float("nan")) for n in names])
            x = np.arange(len(names)) + (j - 0.5) * width
            ax.bar(x, values, width, label=key, color=f"C{j}", alpha=0.85)
        ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=7)
        ax.set_title(title, fontsize=9)
        ax.tick_params(axis="y", labelsize=7)
        ax.legend(
            fontsize=6, frameon=False, loc="upper center", bbox_to_anchor=(0.5, -0.28), ncol=2
        )
        if log:
            ax.set_yscale("log")
            ax.axhline(1.0, color="k", lw=0.6)
    fig.suptitle(
        f"Uncertainty estimators — {results.get('env', '')}, seed {results.get('seed')}",
        fontsize=10,
    )
    return fig
