"""docs/results/variant_table.py: exploration variants against a base, paired by seed."""

from __future__ import annotations

import json
from pathlib import Path


def _write(root: Path, variant: str, seed: int, ratio: float) -> None:
    results = {
        "ratio": ratio,
        "arms": {"random": {"mse": [1.0, 1.0]}, "active": {"mse": [ratio, ratio]}},
        "data": {"active_feasible_fraction": 0.5},
    }
    path = root / variant / f"seed{seed}" / "results.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(results))


def test_variants_are_paired_with_the_base_by_seed(tmp_path, results_script):
    for seed, (base, other) in enumerate([(1.0, 0.8), (1.1, 0.85), (0.9, 0.7)]):
        _write(tmp_path, "base", seed, base)
        _write(tmp_path, "other", seed, other)
    _write(tmp_path, "same_as_base", 0, 1.0)
    _write(tmp_path, "same_as_base", 1, 1.1)
    tables = results_script("variant_table")
    text = tables.table(tables.load(tmp_path))
    lines = text.splitlines()
    assert lines[2].startswith("| base | 1.000, 1.100, 0.900 | 1.000 ± 0.100 | – | 0.50 | 1.000 |")
    other = next(line for line in lines if line.startswith("| other "))
    assert "| 0.783 ± 0.076 | 0.0059 |" in other  # paired t: diffs .2,.25,.2 → t = 13, 2 dof
    assert "| same |" in next(line for line in lines if line.startswith("| same_as_base "))


def test_the_base_can_come_from_another_directory(tmp_path, results_script):
    for seed, ratio in enumerate([1.0, 1.1]):
        path = tmp_path / "main" / f"seed{seed}" / "results.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"ratio": ratio, "arms": {}, "data": {}}))
    tables = results_script("variant_table")
    assert tables.load_seeds(tmp_path / "main") == {
        0: {"ratio": 1.0, "arms": {}, "data": {}},
        1: {"ratio": 1.1, "arms": {}, "data": {}},
    }
    assert tables.load_seeds(tmp_path / "missing") == {}


def test_a_directory_of_seeds_is_one_variant(tmp_path, results_script):
    for seed, ratio in enumerate([0.9, 0.8]):
        _write(tmp_path, "population", seed, ratio)
    tables = results_script("variant_table")
    runs = tables.load(tmp_path / "population")
    assert list(runs) == ["population"] and sorted(runs["population"]) == [0, 1]
