"""Table 1's statistics across seeds, on synthetic results with known values."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.experiments.results_fixtures import ACTIVE, RANDOM, known_explore, write_runs
from torchrl_recon.evaluation.significance import (
    PAPER_RATIOS,
    bootstrap_ci,
    cohens_dz,
    directions,
    paired_t_power,
    power_statement,
    seeds_needed,
    significance,
)
from torchrl_recon.reports import format_table, save_summary, summarize

DIFF = np.subtract(ACTIVE, RANDOM)  # -3, -4, -3, -4, -3: mean -3.4, sample sd sqrt(0.3)


def test_the_paper_ratios_are_its_table_1():
    assert PAPER_RATIOS["industrial_benchmark"] == pytest.approx(0.585, abs=1e-3)
    assert PAPER_RATIOS["drone"] == pytest.approx(0.738, abs=1e-3)
    assert PAPER_RATIOS["minitaur"] == pytest.approx(0.853, abs=1e-3)


def test_effect_size_and_directions_have_their_known_values():
    assert cohens_dz(ACTIVE, RANDOM) == pytest.approx(-3.4 / math.sqrt(0.3))
    assert directions(ACTIVE, RANDOM) == {"active_lower": 5, "active_higher": 0, "equal": 0}
    assert directions([1.0, 3.0, 2.0], [2.0, 1.0, 2.0]) == {
        "active_lower": 1,
        "active_higher": 1,
        "equal": 1,
    }
    assert math.isnan(cohens_dz([1.0], [2.0])) and math.isnan(cohens_dz([1.0, 2.0], [2.0, 3.0]))


@pytest.mark.parametrize(
    "dz, n, power",  # two-sided paired / one-sample t-test at alpha 0.05 (Cohen 1988; G*Power)
    [(0.5, 34, 0.8078), (0.8, 15, 0.8213), (1.0, 10, 0.8031)],
)
def test_power_matches_the_textbook_values(dz, n, power):
    assert paired_t_power(dz, n) == pytest.approx(power, abs=5e-4)
    assert paired_t_power(-dz, n) == pytest.approx(power, abs=5e-4)  # two-sided: either sign
    assert seeds_needed(dz) == n
    assert paired_t_power(dz, n - 1) < 0.8 <= paired_t_power(dz, n)


def test_power_without_an_effect_is_alpha_and_no_seed_count_detects_none():
    assert paired_t_power(0.0, 20) == pytest.approx(0.05)
    assert seeds_needed(0.0) is None and seeds_needed(float("nan")) is None


def test_the_power_statement_puts_the_papers_effect_in_our_units():
    s = power_statement(ACTIVE, RANDOM, 0.5)
    # the paper's effect: (0.5 - 1) x mean(random) = -5.5, over the sd of our differences
    assert s["effect"] == pytest.approx(-5.5)
    assert s["sd_differences"] == pytest.approx(math.sqrt(0.3))
    assert s["effect_dz"] == pytest.approx(-5.5 / math.sqrt(0.3))
    assert s["seeds_needed"] == seeds_needed(5.5 / math.sqrt(0.3))
    assert s["observed_dz"] == pytest.approx(-3.4 / math.sqrt(0.3))
    assert f"needs {s['seeds_needed']} seeds" in s["note"] and "0.500" in s["note"]
    none = power_statement(ACTIVE, RANDOM, None)
    assert none["seeds_needed"] is None and "no ratio of the paper" in none["note"]
    flat = power_statement([1.0, 2.0], [2.0, 3.0], 0.5)  # differences do not vary
    assert flat["seeds_needed"] is None and flat["note"].startswith("not computed")


def test_the_bootstrap_interval_is_seeded_and_brackets_the_mean():
    ratios = np.divide(ACTIVE, RANDOM)
    ci = bootstrap_ci(ratios)
    assert ci == bootstrap_ci(ratios)  # the same numbers, the same interval
    assert ci["low"] < ratios.mean() < ci["high"]
    assert ratios.min() <= ci["low"] and ci["high"] <= ratios.max()
    assert bootstrap_ci(ratios, seed=1) != ci
    assert math.isnan(bootstrap_ci([0.9])["low"]) and "at least 2" in bootstrap_ci([0.9])["note"]
    assert bootstrap_ci([0.8, 0.8, 0.8])["low"] == pytest.approx(0.8)


def test_the_bootstrap_interval_covers_the_true_mean_about_95_percent_of_the_time():
    rng = np.random.default_rng(123)
    trials, covered = 200, 0
    for _ in range(trials):
        sample = rng.normal(0.8, 0.1, size=20)  # 20 seeds around a true mean ratio of 0.8
        ci = bootstrap_ci(sample, n_resamples=2000)
        covered += ci["low"] <= 0.8 <= ci["high"]
    # the percentile bootstrap of a mean of 20 covers ~93%; 200 trials: sd ~1.8 points
    assert 0.87 <= covered / trials <= 0.99


def test_significance_of_one_env_holds_all_parts():
    s = significance(ACTIVE, RANDOM, "industrial_benchmark")
    assert s["mean_ratio"] == pytest.approx(np.mean(np.divide(ACTIVE, RANDOM)))
    assert s["ratio_ci"]["confidence"] == 0.95 and s["ratio_ci"]["seed"] == 0
    assert s["effect_size"]["cohens_dz"] == pytest.approx(cohens_dz(ACTIVE, RANDOM))
    assert s["power"]["paper_ratio"] == PAPER_RATIOS["industrial_benchmark"]


def test_summarize_prints_and_stores_the_statistics_of_table_1(tmp_path):
    write_runs(tmp_path, known_explore("industrial_benchmark"))
    summary = summarize([tmp_path])
    s = summary["envs"]["industrial_benchmark"]
    t = s["tests"]["paired_t"]
    assert t["statistic"] == pytest.approx(-3.4 / (math.sqrt(0.3) / math.sqrt(5)))  # known t
    assert s["tests"]["wilcoxon"]["p_value"] == pytest.approx(2 / 32)  # 5 of 5 one way
    sig = s["significance"]
    assert sig["directions"]["active_lower"] == 5
    table = format_table(summary)
    ci = sig["ratio_ci"]
    assert "mean ratio [95% CI]" in table and "lower/higher" in table and "d_z" in table
    assert f"[{ci['low']:.3g}, {ci['high']:.3g}]" in table and "5/0" in table
    assert "power, industrial_benchmark: " in table and "80% power needs" in table
    path, *_ = save_summary(
        summary,
        [json.loads(f.read_text()) for f in tmp_path.rglob("results.json")],
        tmp_path / "summary",
    )
    stored = json.loads(path.read_text())["envs"]["industrial_benchmark"]["significance"]
    assert stored["power"]["seeds_needed"] == sig["power"]["seeds_needed"]
    assert stored["ratio_ci"]["low"] == pytest.approx(ci["low"])
