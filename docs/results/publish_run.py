"""Publish a run directory under ``docs/results/``: what is read stays a file, the rest is packed.

Run: python docs/results/publish_run.py outputs/explore/drone/seed1 docs/results/explore/drone/seed1

From the run it takes ``results.json``, ``config.yaml``, ``meta.json``, the plots (``*.png``)
and the stage records (``stages/*.json``), plus the per-episode records
(``stages/<setting>/part_<i>.json``) of control settings that have not finished; buffers,
checkpoints, logs and the wandb directory stay behind. Into DEST go ``results.json``,
``config.yaml``, ``meta.json`` and the plots the docs show (``docs/*.md`` links); the stage
records and the other plots become members of the experiment folder's ``records.tar.xz``
(``docs/results/<experiment>/``), whose ``records_manifest.json`` lists the SHA-256 of each
member and of each run's ``results.json`` (``torchrl-recon summarize`` checks them).

Absolute paths in the files kept (``run_dir`` and ``argv`` in ``meta.json``, ``output_dir`` in
``config.yaml``, ...) are written relative to ``--root``, the checkout the run was started
from (default: the current folder); publishing refuses a file that would still hold one.

Two more modes, for folders published before the archives:

    python docs/results/publish_run.py --relative docs/results --root <checkout of the runs>
    python docs/results/publish_run.py --pack docs/results/explore   # each experiment folder

``--relative`` rewrites the absolute paths of every kept file below the folder (summaries'
file lists relative to the summary); ``--pack`` moves an experiment folder's loose records into
its archive (and re-packs it with what is there).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path

from torchrl_recon.runs.archive import (
    ARCHIVE,
    MANIFEST,
    folder_of,
    pack,
    read_members,
    sha256_bytes,
)

RESULTS_ROOT = Path(__file__).resolve().parent
"""``docs/results``: each folder below it is an experiment folder with its own archive."""

DOCS = RESULTS_ROOT.parent

SKIPPED_DIRS = ("buffers", "checkpoints", "wandb")
TOP_FILES = ("results.json", "config.yaml", "meta.json")
KEPT_NAMES = (*TOP_FILES, "results_partial.json", "README.md", MANIFEST, ARCHIVE)
"""Files that stay files wherever they are (scripts, ``*.py`` and ``*.sh``, stay too)."""

ABSOLUTE = re.compile(r"(?<![\w.~/-])/(?=[\w.])[^\s\"',;}\]=]*")
"""An absolute POSIX path inside a text: a ``/`` not after a word character, then no space,
quote or separator."""

MACHINE_PATH = re.compile(r"(?<![\w.~-])/(work|home|tmp|Users|root|mnt|scratch)/")
"""What a published file must not hold: an absolute path of a machine."""


def wanted(path: Path, rel: Path) -> bool:
    """Whether ``path`` (``rel`` inside the run directory) belongs in the published copy."""
    parts = rel.parts
    if any(p in SKIPPED_DIRS for p in parts[:-1]) or not path.is_file():
        return False
    if path.name in TOP_FILES or path.suffix == ".png":
        return True
    if len(parts) >= 2 and parts[-2] == "stages" and path.suffix == ".json":
        return True
    unfinished = not (path.parent.parent / f"{path.parent.name}.json").exists()
    return (
        len(parts) >= 3 and parts[-3] == "stages" and path.name.startswith("part_") and unfinished
    )


def shown_figures(docs: Path = DOCS) -> set[str]:
    """The plots the docs link to, as paths relative to ``docs/results``."""
    found = set()
    for page in docs.glob("*.md"):
        found.update(re.findall(r"\(results/([^()\s]+\.png)\)", page.read_text()))
    return found


def kept(rel: str, shown: set[str]) -> bool:
    """Whether a file (``rel`` relative to ``docs/results``) stays a file, not an archive member:
    the files ``summarize`` and the scripts read, the plots the docs show, and summaries."""
    parts = rel.split("/")
    return (
        parts[-1] in KEPT_NAMES
        or rel.endswith((".py", ".sh"))
        or "summary" in parts[:-1]
        or rel in shown
    )


def relative_paths(text: str, root: Path, base: Path | None = None) -> str:
    """``text`` with each absolute path that shares its first folder with ``root`` written
    relative to ``base`` (default ``root``).

    Examples:
        >>> relative_paths('output_dir=/srv/runs/seed0", "/srv/main/x"', Path("/srv/main"))
        'output_dir=../runs/seed0", "x"'
        >>> relative_paths("active / random", Path("/srv/main"))
        'active / random'
    """
    base = root if base is None else base
    top = Path(root).parts[:2]

    def rewrite(match: re.Match) -> str:
        path = match.group(0)
        if Path(path).parts[:2] != top:
            return path
        return Path(os.path.relpath(path, base)).as_posix()

    return ABSOLUTE.sub(rewrite, text)


def check_no_machine_path(text: str, name: str) -> None:
    """Refuse to publish ``text`` (the file ``name``) when it holds an absolute machine path."""
    match = MACHINE_PATH.search(text)
    if match:
        line = text[: match.start()].count("\n") + 1
        raise ValueError(
            f"{name}:{line} still holds an absolute path ({text[match.start() :].split()[0]}); "
            "publish with --root set to the checkout the run was started from."
        )


def experiment_folder(dest: Path, results_root: Path) -> Path:
    """The experiment folder (``docs/results/<experiment>``) that ``dest`` lies in."""
    dest, results_root = dest.resolve(), results_root.resolve()
    if not dest.is_relative_to(results_root) or len(dest.relative_to(results_root).parts) < 2:
        raise ValueError(
            f"{dest.name}: publish a run into an experiment folder, "
            "docs/results/<experiment>/<...>/<run>"
        )
    return results_root / dest.relative_to(results_root).parts[0]


def _results_hashes(folder: Path) -> dict[str, str]:
    return {
        p.relative_to(folder).as_posix(): sha256_bytes(p.read_bytes())
        for p in sorted(folder.rglob("results.json"))
    }


def repack(
    folder: Path,
    added: dict[str, bytes] | None = None,
    *,
    replaced: str | None = None,
    results_root: Path = RESULTS_ROOT,
) -> list[Path]:
    """Pack ``folder``'s archive again: its members (less those below ``replaced``), ``added``,
    and the loose files the folder does not keep (deleted once the archive reads back); record
    every ``results.json``'s hash. Returns the loose files packed."""
    members = read_members(folder) if (folder / MANIFEST).is_file() else {}
    if replaced is not None:
        members = {k: v for k, v in members.items() if not k.startswith(f"{replaced}/")}
    members.update(added or {})
    shown = shown_figures(results_root.parent)
    loose = [
        p
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not kept(p.relative_to(results_root).as_posix(), shown)
    ]
    for p in loose:
        members[p.relative_to(folder).as_posix()] = p.read_bytes()
    pack(folder, members, _results_hashes(folder))
    read_members(folder)  # read back and checked before anything is deleted
    for p in loose:
        p.unlink()
    for d in sorted((d for d in folder.rglob("*") if d.is_dir()), reverse=True):
        if not any(d.iterdir()):
            d.rmdir()
    return loose


def publish(
    run: Path, dest: Path, *, root: Path | None = None, results_root: Path = RESULTS_ROOT
) -> list[Path]:
    """Publish ``run`` at ``dest``: kept files copied (absolute paths under ``root`` made
    relative), the rest added to the experiment folder's archive (replacing what an earlier
    publication at ``dest`` put there). Returns the files written into ``dest``."""
    if not (run / "config.yaml").is_file():
        raise FileNotFoundError(f"{run} is not a run directory (no config.yaml)")
    root = Path.cwd() if root is None else root
    results_root = results_root.resolve()
    dest = dest.resolve()
    folder = experiment_folder(dest, results_root)
    shown = shown_figures(results_root.parent)
    in_folder = dest.relative_to(folder).as_posix()
    copied, added = [], {}
    for path in sorted(run.rglob("*")):
        rel = path.relative_to(run)
        if not wanted(path, rel):
            continue
        if not kept(dest.relative_to(results_root).joinpath(rel).as_posix(), shown):
            added[f"{in_folder}/{rel.as_posix()}"] = path.read_bytes()
            continue
        data = path.read_bytes()
        if path.suffix in (".json", ".yaml"):
            text = relative_paths(data.decode(), root)
            check_no_machine_path(text, rel.as_posix())
            data = text.encode()
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        (dest / rel).write_bytes(data)
        copied.append(dest / rel)
    repack(folder, added, replaced=in_folder, results_root=results_root)
    return copied


def relativize(folder: Path, root: Path) -> list[Path]:
    """Rewrite the absolute paths of the kept text files below ``folder`` relative to ``root``
    (a summary's file list relative to the summary's folder); return the files changed."""
    checkout = RESULTS_ROOT.parent.parent
    changed = []
    for path in sorted(folder.rglob("*")):
        if not path.is_file() or path.suffix not in (".json", ".yaml") or path.name == MANIFEST:
            continue
        text = path.read_text()
        base = None
        if path.name.startswith("summary_"):
            base = root / path.parent.resolve().relative_to(checkout.resolve())
        new = relative_paths(text, root, base)
        check_no_machine_path(new, str(path))
        if new != text:
            if path.suffix == ".json":
                json.loads(new)  # still JSON
            path.write_text(new)
            changed.append(path)
    return changed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, nargs="?", help="the run directory to publish")
    parser.add_argument("dest", type=Path, nargs="?", help="where, below docs/results/<experiment>")
    parser.add_argument("--root", type=Path, default=None, help="the checkout the run started from")
    parser.add_argument("--relative", type=Path, help="rewrite a published folder's paths")
    parser.add_argument("--pack", type=Path, nargs="+", help="pack experiment folders' records")
    args = parser.parse_args()
    if args.relative is not None:
        if args.root is None:
            sys.exit("error: --relative needs --root, the checkout the runs were started from")
        changed = relativize(args.relative, args.root)
        print(f"{len(changed)} files rewritten below {args.relative}")
    elif args.pack:
        for folder in args.pack:
            packed = repack(folder.resolve())
            print(f"{folder}: {len(packed)} files packed into {folder / ARCHIVE}")
    elif args.run is not None and args.dest is not None:
        copied = publish(args.run, args.dest, root=args.root)
        folder = folder_of(args.dest)
        print(f"{len(copied)} files copied to {args.dest}; the other records in {folder / ARCHIVE}")
    else:
        parser.error("give RUN DEST, --relative FOLDER --root DIR, or --pack FOLDER...")


if __name__ == "__main__":
    main()
