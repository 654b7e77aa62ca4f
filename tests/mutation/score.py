"""Mutation score per file from a mutmut run: ``python tests/mutation/score.py [MUTANTS_DIR] [GLOB...]``.

Reads mutmut's ``*.py.meta`` result files under ``MUTANTS_DIR`` (default ``mutants``) and prints,
per source file, how many mutants were killed (tests failed, or the mutant timed out), survived,
had no covering test, or were not run, with the score killed / (killed + survived + no tests).
With globs (mutmut mutant names, e.g. ``'torchrl_recon.policies.*'``) only matching mutants count.
"""

from __future__ import annotations

import fnmatch
import json
import sys
from collections import Counter
from pathlib import Path

KILLED = {1, 3, -24, 24, 36, 152, 255}  # test failure, pytest error, or timeout
SURVIVED, NO_TESTS = {0}, {5, 33}


def _kind(code: int | None) -> str:
    if code is None:
        return "not run"
    if code in KILLED:
        return "killed"
    if code in SURVIVED:
        return "survived"
    if code in NO_TESTS:
        return "no tests"
    return "other"


def main(argv: list[str]) -> int:
    root = Path(argv[0]) if argv else Path("mutants")
    globs = argv[1:]
    if not root.is_dir():
        print(f"error: no mutmut results in {root} (run `make mutation` first)", file=sys.stderr)
        return 2
    total: Counter[str] = Counter()
    print(f"{'file':48} killed survived no-tests not-run  score")
    for meta in sorted(root.rglob("*.py.meta")):
        codes = json.loads(meta.read_text())["exit_code_by_key"]
        chosen = {
            k: v for k, v in codes.items() if not globs or any(fnmatch.fnmatch(k, g) for g in globs)
        }
        if not chosen:
            continue
        counts = Counter(_kind(v) for v in chosen.values())
        total.update(counts)
        print(_row(str(meta.relative_to(root))[: -len(".meta")], counts))
    print(_row("total", total))
    return 0


def _row(name: str, c: Counter[str]) -> str:
    tested = c["killed"] + c["survived"] + c["no tests"]
    score = f"{100 * c['killed'] / tested:5.1f}%" if tested else "    -"
    return (
        f"{name:48} {c['killed']:6} {c['survived']:8} {c['no tests']:8} {c['not run']:7}  {score}"
    )


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
