"""Figures of the experiments (matplotlib, Agg canvas; no pyplot state, nothing shown): Table 1
as bars, Fig. 3's control errors, Fig. 2's predicted vs real trajectory, and the uncertainty
estimators side by side, and the online learning curve. matplotlib is imported when a figure is
first drawn, not with the package (it costs every command line start about 0.2 s)."""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

ARM_COLORS = {"random": "tab:gray", "active": "tab:orange"}
CONTROL_PANELS = (
    ("prediction_mse", "prediction MSE\n(predicted vs real states)"),
    ("cost_error", "|predicted − real|\ncumulative cost"),
    ("real_cost", "real cumulative cost"),
    ("replans", "re-plans per episode"),
)
CALIBRATION_PANELS = (
    (("spearman", "auroc_error_above_median"), "ranks the real error", False),
    (("ood_auroc_state_shift", "ood_auroc_action_bound"), "out-of-distribution AUROC", False),
    (("score_ratio_H{h}", "cem_ratio_H{h}"), "time relative to the autoencoder", True),
)


def _figure(width: float, height: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _finite(values: Sequence[float]) -> list[float]:
    """The values with None, NaN and ±inf drawn as 0."""
    return [0.0 if v is None or not math.isfinite(float(v)) else float(v) for v in values]


def _name_axis(ax, names: Sequence[str], title: str, rotation: int) -> None:
    ax.set_xticks(range(len(names)), names, rotation=rotation, ha="right", fontsize=7)
    ax.set_title(title, fontsize=9)
    ax.tick_params(axis="y", labelsize=7)


def plot_table1(results: Sequence[Mapping[str, Any]]) -> Figure:
    """Bars of the validation MSE of random vs active exploration (Table 1), one group per env:
    of several seeds, mean ± std across seeds of the per-seed arm means, with each seed as a dot;
    of one, mean ± std over its retrainings, with each retraining as a dot."""
    if not results:
        raise ValueError("plot_table1 needs at least one explore results dict.")
    by_env: dict[str, list[Mapping[str, Any]]] = {}
    for res in results:
        if res.get("experiment") != "explore":
            raise ValueError(f"plot_table1 takes explore results, got {res.get('experiment')!r}.")
        by_env.setdefault(res["env"], []).append(res)
    fig = _figure(max(5.5, 2.2 * len(by_env) + 1.5), 4.2)
    ax, width, ratios = fig.add_subplot(), 0.38, []
    for i, (env, runs) in enumerate(by_env.items()):
        means = {}
        for j, arm in enumerate(ARM_COLORS):
            if len(runs) == 1:  # one seed: its retrainings
                one = runs[0]["arms"][arm]
                points, mean, std = [float(v) for v in one["mse"]], one["mean"], one["std"]
            else:  # several seeds: the per-seed means
                points = [float(r["arms"][arm]["mean"]) for r in runs]
                mean, std = np.mean(points), np.std(points, ddof=1)
            means[arm], std, x = float(mean), float(std), i + (j - 0.5) * width
            yerr, label = std if math.isfinite(std) else 0.0, arm if i == 0 else None
            style = dict(yerr=yerr, capsize=4, color=ARM_COLORS[arm], label=label, alpha=0.85)
            ax.bar(x, means[arm], width, **style)
            jitter = np.linspace(-0.08, 0.08, len(points)) if len(points) > 1 else [0.0]
            ax.scatter(x + np.asarray(jitter), points, s=10, color="black", zorder=3, linewidths=0)
        ratio = means["active"] / means["random"] if means["random"] else float("nan")
        ratios.append(f"{env} {ratio:.3g} ({len(runs)} seed{'s' if len(runs) > 1 else ''})")
    ax.set_xticks(range(len(by_env)), list(by_env))
    ax.set_ylabel("validation MSE")
    title = "Table 1: validation MSE, random vs active exploration\nactive / random: "
    ax.set_title(title + "; ".join(ratios), fontsize=9)
    if units := results[0].get("mse_units", ""):
        fig.supxlabel(textwrap.fill(f"MSE: {units}", 110), fontsize=6)
    top = max(b.get_height() for b in ax.patches)
    ax.set_ylim(0, 1.3 * top if top > 0 else 1.0)
    ax.legend(frameon=False, ncol=2, loc="upper center")
    return fig


def plot_control_errors(results: Mapping[str, Any]) -> Figure:
    """Fig. 3 style: per setting, mean ± std over episodes of the :data:`CONTROL_PANELS` metrics,
    of a control results dict or an env of a summary (``settings: {name: {"mean", "std"}}``),
    with the per-seed means of a summary's ``across_seeds`` as dots."""
    if not (settings := results.get("settings") or {}):
        raise ValueError("plot_control_errors needs results with at least one setting.")
    names, seeds = list(settings), (results.get("across_seeds") or {}).get("settings", {})
    fig = _figure(max(10.0, 1.0 * len(names) * 4 / 2.5), 3.6)
    colors = [f"C{i % 10}" for i in range(len(names))]
    for ax, (key, label) in zip(fig.subplots(1, len(CONTROL_PANELS)), CONTROL_PANELS, strict=True):
        means = _finite([settings[n]["mean"].get(key, math.nan) for n in names])
        stds = _finite([settings[n]["std"].get(key, math.nan) for n in names])
        ax.bar(range(len(names)), means, yerr=stds, capsize=3, color=colors, alpha=0.85)
        for i, n in enumerate(names):  # a summary's per-seed means, as dots
            if points := seeds.get(n, {}).get("per_seed", {}).get(key, []):
                ax.plot([i] * len(points), points, "o", color="black", ms=3, alpha=0.7)
        _name_axis(ax, names, label, rotation=45)
    env, seed = results.get("env", ""), results.get("seed")
    title = "Uncertainty-aware control" + (f" — {env}" if env else "")
    title += f", seed {seed}" if seed is not None else ""
    fig.suptitle(title + " (mean ± std over episodes)", fontsize=10)
    return fig


def plot_trajectory(example: Mapping[str, Any], max_dims: int = 4) -> Figure:
    """Fig. 2 style: predicted vs real state over one episode (the ``max_dims`` dimensions that
    vary most), u on a twin axis, re-plans marked. ``example``: ``{"setting", "real": [L, N],
    "predicted": [L, N], "uncertainty": [L], "replanned": [L], "state_names": [N]}``."""
    real = np.asarray(example["real"], dtype=float)
    predicted = np.asarray(example["predicted"], dtype=float)
    if real.ndim != 2 or real.shape != predicted.shape:
        raise ValueError(
            f"trajectory example: real {real.shape} and predicted {predicted.shape} must both be [L, N]."
        )
    length, n = real.shape
    u = np.asarray(example.get("uncertainty", []), dtype=float)
    replans = np.flatnonzero(np.asarray(example.get("replanned", []), dtype=bool)[:length])
    names = list(example.get("state_names") or [f"s{i}" for i in range(n)])
    spread = np.nan_to_num(real.std(axis=0) if length > 1 else np.abs(real[0]), nan=-1.0)
    dims = sorted(int(i) for i in np.argsort(-spread, kind="stable")[:max_dims])
    fig = _figure(8.0, 1.9 * len(dims) + 0.6)
    axes = np.atleast_1d(fig.subplots(len(dims), 1, sharex=True))
    t = np.arange(length)
    for k, (ax, d) in enumerate(zip(axes, dims, strict=True)):
        ax.plot(t, real[:, d], color="black", lw=1.2, label="real")
        ax.plot(t, predicted[:, d], color="tab:blue", lw=1.2, ls="--", label="predicted")
        ax.set_ylabel(names[d] if d < len(names) else f"s{d}", fontsize=8)
        for i in replans:
            label = "re-plan" if i == replans[0] else None
            ax.axvline(i, color="tab:red", lw=0.7, alpha=0.6, label=label)
        handles, labels = ax.get_legend_handles_labels()
        if u.size:
            twin = ax.twinx()
            twin.plot(t[: u.size], u[:length], color="tab:green", lw=0.9, alpha=0.8, label="u")
            twin.set_ylabel("u", color="tab:green", fontsize=8)
            twin.tick_params(axis="y", labelsize=7, colors="tab:green")
            h2, l2 = twin.get_legend_handles_labels()
            handles, labels = handles + h2, labels + l2
        if k == 0:
            ncol = 4 if u.size else 3
            ax.legend(handles, labels, fontsize=7, ncol=ncol, loc="upper left", frameon=False)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time step")
    fig.suptitle(
        f"Predicted vs real trajectory — setting {example.get('setting', '?')}", fontsize=10
    )
    return fig


def plot_calibration(results: Mapping[str, Any]) -> Figure:
    """Estimators side by side: Spearman and AUROC of u against the real error, OOD AUROC
    (states moved, actions at the bound), and scoring / CEM time as ratios to the reference
    estimator at the first timed horizon (log scale)."""
    if not (rows := results.get("estimators") or {}):
        raise ValueError("plot_calibration needs calibrate results with at least one estimator.")
    names, horizon, width = list(rows), (results.get("horizons") or [0])[0], 0.38
    fig = _figure(max(9.0, 1.2 * len(names) * 3), 3.6)
    panels = zip(fig.subplots(1, len(CALIBRATION_PANELS)), CALIBRATION_PANELS, strict=True)
    for ax, (keys, title, log) in panels:
        for j, key in enumerate(k.format(h=horizon) for k in keys):
            values = _finite([rows[n].get(key, math.nan) for n in names])
            x = np.arange(len(names)) + (j - 0.5) * width
            ax.bar(x, values, width, label=key, color=f"C{j}", alpha=0.85)
        _name_axis(ax, names, title, rotation=30)
        ax.legend(
            fontsize=6, frameon=False, loc="upper center", bbox_to_anchor=(0.5, -0.28), ncol=2
        )
        if log:
            ax.set_yscale("log")
            ax.axhline(1.0, color="k", lw=0.6)
    seed = results.get("seed")  # a summary of several seeds has none
    title = f"Uncertainty estimators — {results.get('env', '')}"
    fig.suptitle(title + (f", seed {seed}" if seed is not None else ""), fontsize=10)
    return fig


def plot_learning_curve(results: Mapping[str, Any]) -> Figure:
    """Return of each episode against the env steps when it ended, beside the random policy's."""
    figure = _figure(6, 3.5)
    ax = figure.add_subplot()
    for it in results["iterations"]:
        steps = np.full(len(it["returns"]), it["env_steps"])
        ax.plot(steps, it["returns"], "o", color="C0", alpha=0.6)
    means = zip(*_iteration_means(results), strict=True)  # NaN where no episode ended
    if means := [(steps, mean) for steps, mean in means if np.isfinite(mean)]:
        ax.plot(*zip(*means, strict=True), "-", color="C0", label="MPC (mean per iteration)")
    ax.axhline(results["random"]["mean_return"], color="C3", ls="--", label="random policy")
    ax.set(xlabel="env steps", ylabel="episode return", title=f"online {results['env']}")
    ax.legend(loc="lower right")
    return figure


def plot_seed_curves(
    variants: Mapping[str, Sequence[Mapping[str, Any]]],
    *,
    references: Mapping[str, float] | None = None,
    title: str = "",
) -> Figure:
    """Online learning curves over seeds: for each variant (a name -> its seeds' online results),
    each seed's mean return per iteration (thin) and their mean over seeds (thick), against the
    env steps; the random policy's mean over every run (dashed) and any ``references`` (a label ->
    a return, e.g. a published anchor; dotted).

    Examples:
        >>> run = {"env": "Pendulum-v1", "random": {"mean_return": -1200.0},
        ...        "iterations": [{"env_steps": 400, "returns": [-900.0]},
        ...                       {"env_steps": 600, "returns": [-300.0, -200.0]}]}
        >>> fig = plot_seed_curves({"beta=0": [run, run]}, references={"anchor": -150.0})
        >>> len(fig.axes[0].lines)  # 2 seeds, their mean, random, the anchor
        5
    """
    if not any(variants.values()):
        raise ValueError("plot_seed_curves needs at least one online results dict.")
    figure = _figure(6, 3.5)
    ax = figure.add_subplot()
    for color, (name, runs) in enumerate(variants.items()):
        curves = [_iteration_means(run) for run in runs]
        for steps, means in curves:
            ax.plot(steps, means, "-", color=f"C{color}", lw=0.7, alpha=0.5)
        count = min((len(steps) for steps, _ in curves), default=0)
        if count:  # the mean over seeds, up to the iterations every seed has
            mean = np.nanmean([means[:count] for _, means in curves], axis=0)
            label = f"{name} ({len(runs)} seed{'s' if len(runs) > 1 else ''})"
            ax.plot(curves[0][0][:count], mean, "-", color=f"C{color}", lw=2, label=label)
    random = [run["random"]["mean_return"] for runs in variants.values() for run in runs]
    ax.axhline(float(np.mean(random)), color="tab:gray", ls="--", label="random policy")
    for index, (label, value) in enumerate((references or {}).items()):
        ax.axhline(value, color=f"C{len(variants) + index}", ls=":", label=label)
    env = next(run["env"] for runs in variants.values() for run in runs)
    ax.set(xlabel="env steps", ylabel="mean episode return", title=title or f"online {env}")
    ax.legend(loc="best", fontsize=7)
    return figure


def _iteration_means(results: Mapping[str, Any]) -> tuple[list[int], list[float]]:
    """``(env steps, mean return)`` of each iteration of one online run (NaN where none ended)."""
    its = results["iterations"]
    means = [float(np.mean(it["returns"])) if it["returns"] else math.nan for it in its]
    return [it["env_steps"] for it in its], means
