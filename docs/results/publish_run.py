"""Copy the small, reviewable part of a run directory into ``docs/results/`` (no replay buffers).

Run: python docs/results/publish_run.py outputs/explore/drone/seed1 docs/results/explore/drone/seed1

It copies ``results.json``, ``config.yaml``, ``meta.json``, the plots (``*.png``) and the stage
records (``stages/*.json``), plus the per-episode records (``stages/<setting>/part_<i>.json``)
of control settings that have not finished, so ``control_tables.py`` can report them. Buffers,
checkpoints, logs and the wandb directory stay behind.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

SKIPPED_DIRS = ("buffers", "checkpoints", "wandb")
TOP_FILES = ("results.json", "config.yaml", "meta.json")


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


def publish(run: Path, dest: Path) -> list[Path]:
    """Copy the wanted files of ``run`` to ``dest`` (same layout); return the copied paths."""
    if not (run / "config.yaml").is_file():
        raise FileNotFoundError(f"{run} is not a run directory (no config.yaml)")
    copied = []
    for path in sorted(run.rglob("*")):
        rel = path.relative_to(run)
        if wanted(path, rel):
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, dest / rel)
            copied.append(dest / rel)
    return copied


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("dest", type=Path)
    args = parser.parse_args()
    print(f"{len(publish(args.run, args.dest))} files copied to {args.dest}")


if __name__ == "__main__":
    main()
