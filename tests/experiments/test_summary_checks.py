"""``summarize`` checks each results.json before it averages it (results are data too)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from tests.experiments.results_fixtures import (
    control_results,
    explore_results,
    known_explore,
    write_runs,
)
from torchrl_recon.cli import main
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.reports import check_results, find_results, save_summary, summarize


def _damage(path, change):
    results = json.loads(path.read_text())
    change(results)
    path.write_text(json.dumps(results))


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize(
    "value, words",
    [
        (float("nan"), "arms.active.mean is nan, not a finite number"),
        (1e30, "arms.active.mean is 1e+30, but the mean of its 2 per-retraining values"),
        (float("inf"), "arms.active.mean is inf, not a finite number"),
    ],
)
def test_a_damaged_arm_mean_is_refused_with_one_line_naming_the_file(
    tmp_path, capsys, value, words
):
    files = write_runs(tmp_path, known_explore())
    _damage(files[2], lambda r: r["arms"]["active"].__setitem__("mean", value))
    assert main(["summarize", str(tmp_path)]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"error: {files[2]}: ") and words in line, line
    assert "nan" not in capsys.readouterr().out  # no table was printed


def test_a_ratio_that_is_not_active_over_random_is_refused(tmp_path):
    files = write_runs(tmp_path, known_explore())
    _damage(files[0], lambda r: r.__setitem__("ratio", r["ratio"] * (1 + 1e-6)))
    with pytest.raises(DamagedFileError, match=r"seed0/results.json: ratio is .* but arms.active"):
        summarize([tmp_path])


def test_a_per_retraining_value_that_is_not_finite_is_refused(tmp_path):
    files = write_runs(tmp_path, known_explore())
    _damage(files[1], lambda r: r["arms"]["random"]["mse"].__setitem__(1, float("nan")))
    with pytest.raises(DamagedFileError, match=r"arms.random.mse\[1\] is nan"):
        summarize([tmp_path])


def test_float32_rounding_of_an_arm_mean_is_accepted():
    r = explore_results(0, [0.1, 0.2, 0.4], [0.3, 0.1, 0.2])
    r["arms"]["random"]["mean"] *= 1 + 2e-7  # what a float32 mean of float64 values is off by
    r["ratio"] = r["arms"]["active"]["mean"] / r["arms"]["random"]["mean"]
    check_results(r, "results.json")


def test_nan_where_an_experiment_writes_it_on_purpose_is_accepted():
    one = explore_results(0, [1.0], [2.0])  # one retraining: no std, no test
    one["test"] = {"name": "Welch", "statistic": float("nan"), "p_value": float("nan")}
    check_results(one, "results.json")
    two = explore_results(0, [1.0, 2.0], [2.0, 3.0])
    two["arms"]["active"]["std"] = float("nan")
    with pytest.raises(DamagedFileError, match="arms.active.std is nan with 2"):
        check_results(two, "results.json")
    # an episode without a planned step reports NaN metrics; the mean leaves it out
    check_results(control_results(0, {"baseline": [1.0, float("nan"), 3.0]}), "results.json")


def test_a_control_mean_that_is_not_the_mean_of_its_episodes_is_refused(tmp_path):
    files = write_runs(tmp_path, [control_results(s, {"baseline": [1.0, 3.0]}) for s in (0, 1)])
    _damage(files[1], lambda r: r["settings"]["baseline"]["mean"].__setitem__("real_cost", 2.5))
    with pytest.raises(
        DamagedFileError,
        match=r"seed1/results.json: settings.baseline.mean.real_cost is 2.5, but the mean over "
        r"its 2 episodes is 2.0",
    ):
        summarize([tmp_path])
    _damage(
        files[1],
        lambda r: r["settings"]["baseline"]["episodes"][0].__setitem__("cost_error", float("-inf")),
    )
    with pytest.raises(DamagedFileError, match=r"episodes\[0\].cost_error is -inf"):
        summarize([tmp_path])


def test_calibrate_numbers_outside_the_estimator_rows_must_be_finite():
    r = {"experiment": "calibrate", "estimators": {"ae": {"spearman": float("nan")}}}
    check_results(r, "results.json")
    with pytest.raises(DamagedFileError, match="world_model_val_loss is nan"):
        check_results({**r, "world_model_val_loss": float("nan")}, "results.json")
    with pytest.raises(DamagedFileError, match="estimators.ae.spearman is inf"):
        check_results({**r, "estimators": {"ae": {"spearman": math.inf}}}, "results.json")


def test_a_missing_arm_is_one_line_not_a_key_error(tmp_path):
    files = write_runs(tmp_path, known_explore())
    _damage(files[0], lambda r: r["arms"].pop("active"))
    with pytest.raises(DamagedFileError, match="it has no arms.active.mse"):
        summarize([tmp_path])


def test_summaries_record_paths_relative_to_the_output_folder(tmp_path, monkeypatch):
    write_runs(tmp_path / "runs", known_explore())
    monkeypatch.chdir(tmp_path)
    files = find_results(["runs"])
    assert [f.as_posix() for f in files][0] == "runs/drone/seed0/results.json"  # as given
    summary = summarize(files)
    path, *_ = save_summary(summary, [json.loads(f.read_text()) for f in files], "runs/summary")
    written = json.loads(path.read_text())
    assert written["files"][0] == "../drone/seed0/results.json"
    assert str(tmp_path) not in path.read_text()
    # given absolute, the files are still written relative to the summary
    summary = summarize([tmp_path / "runs"])
    path, *_ = save_summary(summary, [json.loads(f.read_text()) for f in files], tmp_path / "out")
    assert json.loads(path.read_text())["files"][4] == "../runs/drone/seed4/results.json"
    assert str(tmp_path) not in path.read_text()


def test_runs_inside_another_run_are_part_of_its_results_not_found_on_their_own(tmp_path):
    outer = write_runs(tmp_path, known_explore()[:2])
    inner = write_runs(outer[0].parent / "outcomes" / "x", known_explore()[:1])
    assert find_results([tmp_path]) == outer
    assert find_results([outer[0].parent / "outcomes"]) == inner  # asked for: found


def test_summarizing_two_variants_of_one_env_is_one_user_error(capsys):
    """docs/results/online holds several variants of InvertedPendulum-v5, each with seeds 0-4:
    pooled, a seed would count twice; the command says so (exit 2), one folder summarises."""
    online = Path(__file__).resolve().parents[2] / "docs" / "results" / "online"
    assert main(["summarize", str(online)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and "repeat a seed" in err[0] and "unexpected" not in err[0], err
    assert main(["summarize", str(online / "Pendulum-v1")]) == 0
    assert "online Pendulum-v1, seeds [0, 1, 2, 3, 4]" in capsys.readouterr().out
