"""Bad recipe values checked several to a composition: a recipe's overrides of distinct top-level
keys share one run (each value's check is independent of the others' there), and each value's
words are looked for inside its own problem of the one error line. One Hydra composition per
group instead of one per value (each is ~0.5 s)."""

from __future__ import annotations

import re


def top_key(override: str) -> str:
    """The top-level key an override sets: ``guided`` for ``guided.ratio=nan``."""
    return override.lstrip("+~").split("=", 1)[0].split(".")[0]


def pack(cases: list[tuple[str, str, list[str]]], alone: set[str]) -> list[tuple[str, list]]:
    """``cases`` (recipe, override, words) as ``[(recipe, [(override, words), ...])]``: a case
    joins the first group of its recipe that sets none of its top-level keys; an override in
    ``alone`` (a wrong type, an unknown key, a choice not offered, a sweep: refused before the
    other checks, so the line names only it) runs by itself."""
    groups: list[tuple[str, list]] = []
    for recipe, override, words in cases:
        home = next(
            (
                g
                for r, g in groups
                if override not in alone
                and r == recipe
                and all(o not in alone and top_key(o) != top_key(override) for o, _ in g)
            ),
            None,
        )
        if home is None:
            groups.append((recipe, home := []))
        home.append((override, words))
    return groups


def problems(line: str) -> list[str]:
    """The problems of one error line: each starts with its quoted key after a ``"; "`` (a
    problem's own text may hold ``"; "`` too: ``unknown planner 'x'; expected one of ...``)."""
    return re.split(r"; (?=')", line)


def ids(groups: list[tuple[str, list]]) -> list[str]:
    """A group's test id: its recipe, its size and its first override."""
    return [f"{r.replace('/', '-')}-{len(c)}-{c[0][0]}" for r, c in groups]
