"""The published results under docs/results: packed, verified, and free of machine paths."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from torchrl_recon.reports import summarize
from torchrl_recon.runs.archive import MANIFEST, read_manifest, read_members, verify_results

DOCS = Path(__file__).resolve().parents[2] / "docs"
RESULTS = DOCS / "results"
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(work|home|tmp|Users|root|mnt|scratch)/")

pytestmark = pytest.mark.skipif(not RESULTS.is_dir(), reason="no docs/results in this checkout")


def test_every_archive_matches_its_manifest_which_lists_every_results_file():
    folders = sorted(p.parent for p in RESULTS.glob(f"*/{MANIFEST}"))
    with_results = {
        RESULTS / f.relative_to(RESULTS).parts[0] for f in RESULTS.rglob("results.json")
    }
    assert folders == sorted(with_results)
    for folder in folders:
        files = sorted(folder.rglob("results.json"))
        (checked,) = verify_results(files)  # each member's and each results.json's SHA-256
        assert checked["results"] == len(files)
        listed = read_manifest(folder)["results"]
        assert sorted(listed) == sorted(f.relative_to(folder).as_posix() for f in files), folder
        for name, data in read_members(folder).items():  # read once: cached
            if name.endswith(".json"):
                assert not MACHINE_PATH.search(data.decode()), f"{folder.name}/{name}"


def test_no_loose_stage_records_and_every_figure_the_docs_show_is_a_file():
    assert not [p for p in RESULTS.rglob("stages") if p.is_dir()]
    for page in DOCS.glob("*.md"):
        for figure in re.findall(r"\(results/([^()\s]+\.png)\)", page.read_text()):
            assert (RESULTS / figure).is_file(), f"{page.name} shows {figure}"


def test_no_absolute_machine_path_in_the_published_results():
    for path in sorted(RESULTS.rglob("*")):
        if path.is_file() and path.suffix in (".json", ".yaml", ".md", ".py"):
            match = MACHINE_PATH.search(path.read_text())
            assert match is None, f"{path.relative_to(DOCS)} holds {match.group(0)}..."


def test_table_1_summarizes_to_the_published_numbers():
    envs = summarize([RESULTS / "explore"])["envs"]
    ratios = {env: round(s["ratio"], 3) for env, s in envs.items()}
    assert ratios == {"drone": 0.724, "industrial_benchmark": 0.93, "minitaur": 1.038}
    assert {env: s["seeds"] for env, s in envs.items()} == {env: [0, 1, 2, 3, 4] for env in envs}


def test_the_reproduction_pages_table_1_is_what_the_published_runs_give():
    """docs/reproduction.md's headline table is regenerated, not typed: each row equals
    ``docs/results/table1_20seeds/headline.py``'s for the runs published now."""
    from tests.scripts import load_script

    headline = load_script(RESULTS / "table1_20seeds" / "headline.py")
    page = (DOCS / "reproduction.md").read_text()
    for label, folder, env in headline.ROWS:
        assert headline.row(label, folder, env) in page, label
