"""``torchrl-recon recipes``: each shipped recipe described by what it runs."""

from __future__ import annotations

import re

from torchrl_recon.cli import recipe_about, shipped_recipes


def test_every_recipe_says_what_it_runs_and_names_no_tracker_issue():
    recipes = shipped_recipes()
    assert len(recipes) > 30
    for _, name, about in recipes:
        assert about.endswith((".", "…")) or ":" in about, (name, about)
        assert not re.search(r"\bissue\s*#?\d+", about, re.IGNORECASE), (name, about)
        assert len(about) <= 112, (name, about)


def test_the_description_is_the_first_sentence_of_the_leading_comment():
    text = "# Fig. 3 on the Drone, eq. 4 too. Then more\n# of it.\n#   torchrl-recon ...\nseed: 0\n"
    assert recipe_about(text) == "Fig. 3 on the Drone, eq. 4 too."
    assert recipe_about("seed: 0\n") == ""
    long = "# " + " ".join(["word"] * 40) + "\n"
    assert recipe_about(long, width=30) == "word word word word word …"
