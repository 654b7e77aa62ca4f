"""Summaries across seeds that meet seeds of different shapes: calibrate runs with different
estimator lists, online runs with different iteration counts."""

from __future__ import annotations

import math

import pytest

from torchrl_recon.reports.calibrate import summarize_env, summary_table
from torchrl_recon.reports.online import summarize_env as online_summary
from torchrl_recon.reports.online import summary_table as online_table


def _run(seed: int, estimators: dict) -> dict:
    return {"experiment": "calibrate", "seed": seed, "horizons": [10], "estimators": estimators}


def test_each_estimators_numbers_are_averaged_over_the_seeds_that_ran_it():
    """Seed 0 (summarised first) lacks an estimator seed 1 has: it was dropped, silently."""
    runs = [
        _run(
            1,
            {
                "reconstruction": {"spearman": 0.8, "kind": "reconstruction"},
                "rnd": {"spearman": 0.2},
            },
        ),
        _run(0, {"reconstruction": {"spearman": 0.6, "kind": "reconstruction"}}),
    ]
    s = summarize_env(runs)
    assert s["seeds"] == [0, 1] and s["horizons"] == [10]
    rec = s["estimators"]["reconstruction"]
    assert rec["n_seeds"] == 2 and rec["mean"]["spearman"] == pytest.approx(0.7)
    assert rec["std"]["spearman"] == pytest.approx(math.sqrt(0.02))  # sample std, ddof = 1
    assert "kind" not in rec["mean"]  # text entries are not averaged
    rnd = s["estimators"]["rnd"]  # only seed 1 ran it: kept, over that seed
    assert rnd["n_seeds"] == 1 and math.isnan(rnd["std"]["spearman"])
    assert list(s["estimators"]) == ["reconstruction", "rnd"]
    table = summary_table({"envs": {"industrial_benchmark": s}})
    assert "industrial_benchmark, seeds [0, 1]: mean across seeds" in table
    assert any(line.startswith("reconstruction") and "0.7" in line for line in table.splitlines())


def test_an_entry_only_some_seeds_have_is_averaged_over_those():
    """The first seed's row had an entry the next lacked: a KeyError; one it lacked: dropped."""
    runs = [
        _run(0, {"reconstruction": {"spearman": 0.6, "cem_ratio_H10": 1.0}}),
        _run(1, {"reconstruction": {"spearman": 0.8, "explore_ratio": 0.9, "ok": True}}),
    ]
    mean = summarize_env(runs)["estimators"]["reconstruction"]["mean"]
    assert mean == pytest.approx({"spearman": 0.7, "cem_ratio_H10": 1.0, "explore_ratio": 0.9})


def test_an_online_summary_of_seeds_with_different_lengths_says_where_its_rows_stop():
    def run(seed: int, returns: list[float]) -> dict:
        iterations = [{"returns": [r], "env_steps": 10 * (i + 1)} for i, r in enumerate(returns)]
        return {
            "seed": seed,
            "iterations": iterations,
            "random": {"mean_return": -5.0},
            "mean_return_last_half": returns[-1],
        }

    same = online_summary([run(0, [1.0, 2.0]), run(1, [3.0, 4.0])])
    assert "iterations_per_seed" not in same and len(same["iterations"]) == 2
    cut = online_summary([run(0, [1.0, 2.0, 3.0]), run(1, [3.0, 4.0])])
    assert cut["iterations_per_seed"] == [3, 2] and len(cut["iterations"]) == 2
    assert cut["iterations"][1]["mean"] == pytest.approx(3.0)
    table = online_table({"envs": {"Pendulum-v1": cut}})
    assert (
        "(iterations per seed [3, 2]: the rows stop at 2; each seed's last half is its own)"
        in table
    )


def test_an_online_summary_draws_each_seeds_curve_and_their_mean(tmp_path):
    """``summarize --out`` of online seeds writes ``learning_curves_<env>.png``: one thin line
    per seed, their mean, the random policy; the mean stops where the shortest seed does."""
    from torchrl_recon.reports.online import summary_figures
    from torchrl_recon.reports.plots import plot_seed_curves

    def run(seed: int, returns: list[float]) -> dict:
        iterations = [{"returns": [r], "env_steps": 10 * (i + 1)} for i, r in enumerate(returns)]
        return {
            "env": "Reacher-v5",
            "seed": seed,
            "iterations": iterations,
            "random": {"mean_return": -40.0},
            "mean_return_last_half": returns[-1],
        }

    runs = [run(0, [-9.0, -6.0, -5.0]), run(1, [-7.0, -4.0])]
    [(name, figure)] = summary_figures({"envs": {"Reacher-v5": online_summary(runs)}}, runs)
    assert name == "learning_curves_Reacher-v5.png"
    lines = figure.axes[0].lines
    assert len(lines) == 4  # two seeds, their mean, the random policy
    mean = lines[2]
    assert list(mean.get_xdata()) == [10, 20] and list(mean.get_ydata()) == [-8.0, -5.0]
    assert list(lines[3].get_ydata()) == [-40.0, -40.0]
    figure.savefig(tmp_path / name)
    assert (tmp_path / name).stat().st_size > 0
    with pytest.raises(ValueError, match="at least one online results"):
        plot_seed_curves({"MPC": []})
