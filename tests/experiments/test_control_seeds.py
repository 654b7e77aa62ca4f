"""The control experiment across seeds: per-seed means, paired tests, the trend over u bands."""

from __future__ import annotations

import math

import pytest

from torchrl_recon.evaluation.significance import paired_tests, trend_test
from torchrl_recon.reports import control
from torchrl_recon.reports.control import across_seeds

BANDS = {"u_low": (0.0, 0.33), "u_mid": (0.33, 0.66), "u_high": (0.66, 1.0)}


def _runs(seeds: int, errors: dict[str, float]) -> list[dict]:
    """Control results of ``seeds`` seeds: 2 episodes per setting, prediction MSE = errors[name]
    + seed / 10 (so every setting keeps its order within each seed)."""
    runs = []
    for s in range(seeds):
        settings = {}
        for name, error in errors.items():
            episodes = [
                {"prediction_mse": error + s / 10 + d, "real_cost": 10.0 + d + s} for d in (0, 0.02)
            ]
            band = BANDS.get(name)
            settings[name] = {
                "episodes": episodes,
                **({"band": {"low": band[0], "high": band[1], "kind": "quantile"}} if band else {}),
            }
        runs.append({"experiment": "control", "env": "drone", "seed": s, "settings": settings})
    return runs


ERRORS = {"baseline": 1.0, "u_high": 0.9, "u_low": 0.5, "u_mid": 0.7}


def test_per_seed_means_and_paired_tests_against_the_baseline():
    out = across_seeds(_runs(5, ERRORS), list(ERRORS))
    low = out["settings"]["u_low"]
    assert low["seeds"] == [0, 1, 2, 3, 4]
    assert low["per_seed"]["prediction_mse"] == pytest.approx([0.51, 0.61, 0.71, 0.81, 0.91])
    tests = low["vs_reference"]["prediction_mse"]
    assert tests["paired_t"]["n"] == 5 and tests["paired_t"]["p_value"] < 1e-6
    assert tests["wilcoxon"]["p_value"] == pytest.approx(0.0625)  # all 5 pairs one way
    assert (
        "vs_reference" in out["settings"]["baseline"]
        and not out["settings"]["baseline"]["vs_reference"]
    )


def test_trend_follows_the_bands_not_the_setting_order():
    out = across_seeds(_runs(3, ERRORS), list(ERRORS))
    trend = out["trend"]["prediction_mse"]
    assert trend["order"] == ["u_low", "u_mid", "u_high"] and trend["n"] == 3
    assert trend["p_value"] < 0.01  # low < mid < high in every seed
    reversed_errors = {"baseline": 1.0, "u_low": 0.9, "u_mid": 0.7, "u_high": 0.5}
    against = across_seeds(_runs(3, reversed_errors), list(reversed_errors))
    assert against["trend"]["prediction_mse"]["p_value"] > 0.9


def test_too_few_seeds_or_bands_is_said_not_computed():
    one = across_seeds(_runs(1, ERRORS), list(ERRORS))
    assert "not computed: needs at least 2 seeds, got 1" in one["trend"]["prediction_mse"]["note"]
    assert math.isnan(
        one["settings"]["u_low"]["vs_reference"]["prediction_mse"]["paired_t"]["p_value"]
    )
    assert "needs at least 3 banded settings" in trend_test({"a": {0: 1.0}}, ["a"])["note"]
    assert paired_tests([1.0] * 5, [1.0] * 5)["wilcoxon"]["p_value"] == 1.0


def test_summary_table_and_figure_show_the_seeds():
    runs = _runs(5, ERRORS)
    summary = {"envs": {"drone": control.summarize_env(runs)}}
    text = control.summary_table(summary)
    assert "per-seed means, mean ± std across seeds" in text
    assert "trend over the u bands (prediction_mse): u_low < u_mid < u_high" in text
    ((name, fig),) = control.summary_figures(summary, runs)
    assert name == "control_errors_drone.png"
    dots = [line for ax in fig.axes for line in ax.lines if line.get_marker() == "o"]
    assert (
        sum(len(d.get_xdata()) for d in dots) == 2 * 4 * 5
    )  # 2 metrics tested × 4 settings × 5 seeds
