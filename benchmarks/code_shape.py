"""The shape measures of issue 59 over ``torchrl_recon/``, measured from the source each time.

Prints one line per measure: its value now and its target. Counts a file once however often it
spells the pattern; reads only ``.py`` files; needs no install beyond the package itself. Each
speed path is counted twice: in code (docstrings, comments and other strings left out: where the
path is a branch or a call) and in any text (where it is also only named in prose).

    python benchmarks/code_shape.py            # the table
    python benchmarks/code_shape.py --longest 5  # and the five longest function bodies
"""

from __future__ import annotations

import argparse
import ast
import functools
import io
import re
import tokenize
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchrl_recon"
SPELLINGS = {  # measure -> (regex, target): files that spell the speed path
    "files that spell CUDA-graph capture": (r"CUDAGraph|cuda_graph|torch\.cuda\.graph", 3),
    "files that spell CPU row-block threads": (
        r"run_aside|run_blocks|threaded_pass|blocks_in_threads|cpu_threads",
        2,
    ),
    "files that spell torch.compile or its helpers": (
        r"torch\.compile\b|torch\.compiler\.|torch\._dynamo|compile_mode|\bmark_dynamic|maybe_mark_dynamic",
        5,
    ),
}
LONGEST_TARGET = 60
EXPORTS_TARGET = 16
ROOT_TARGET = 5


def sources() -> list[Path]:
    """Every ``.py`` file of the package, sorted."""
    return sorted(PACKAGE.rglob("*.py"))


def code_only(text: str) -> str:
    """``text`` (Python source) with its comments and string literals, docstrings included,
    blanked out (f-strings whole): what is left is the code.

    Examples:
        >>> code_only('x = torch.compile(f)  # torch.compile\ny = "torch.compile"\n')
        'x = torch.compile(f)                 \ny =                \n'
    """
    lines = text.splitlines(keepends=True)
    dropped = {tokenize.COMMENT, tokenize.STRING, getattr(tokenize, "FSTRING_START", -1)}
    depth = 0  # inside an f-string (Python >= 3.12 tokenizes its parts)
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        depth += tok.type == getattr(tokenize, "FSTRING_START", -1)
        inside = depth > 0
        depth -= tok.type == getattr(tokenize, "FSTRING_END", -1)
        if tok.type in dropped or inside:
            (row, col), (end_row, end_col) = tok.start, tok.end
            for r in range(row, end_row + 1):
                line = lines[r - 1]
                a = col if r == row else 0
                b = end_col if r == end_row else len(line.rstrip("\n"))
                lines[r - 1] = line[:a] + " " * (b - a) + line[b:]
    return "".join(lines)


@functools.cache
def texts(code: bool) -> dict[Path, str]:
    """Every source's text (with ``code``, its code only), read and blanked once per run."""
    return {p: code_only(p.read_text()) if code else p.read_text() for p in sources()}


def files_spelling(pattern: str, *, code: bool = False) -> list[Path]:
    """The files whose text (with ``code``, whose code only) matches ``pattern``."""
    found = re.compile(pattern)
    return [p for p, text in texts(code).items() if found.search(text)]


def body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines of a function's body, its docstring left out."""
    body = node.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        if isinstance(body[0].value.value, str):
            body = body[1:]
    if not body:
        return 0
    return body[-1].end_lineno - body[0].lineno + 1


def function_bodies() -> list[tuple[int, str]]:
    """``(body lines, "path:line name")`` of every function and method, longest first."""
    rows = []
    for path in sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                where = f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {node.name}"
                rows.append((body_lines(node), where))
    return sorted(rows, reverse=True)


def planners_exports() -> int:
    """``len(torchrl_recon.planners.__all__)``, read from its source (nothing imported)."""
    tree = ast.parse((PACKAGE / "planners" / "__init__.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            return len(ast.literal_eval(node.value))
    return 0


def root_modules() -> list[str]:
    """Modules at the package root, ``__init__`` aside."""
    return sorted(p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--longest", type=int, default=0, help="list this many longest bodies")
    parser.add_argument("--files", action="store_true", help="list the files each path counts")
    args = parser.parse_args(argv)
    bodies = function_bodies()
    rows = []
    for name, (rx, target) in SPELLINGS.items():
        rows.append((f"{name} in code", len(files_spelling(rx, code=True)), target))
        rows.append((f"{name} in any text", len(files_spelling(rx)), target))
    rows += [
        ("longest function body (lines, docstring excluded)", bodies[0][0], LONGEST_TARGET),
        ("names torchrl_recon.planners exports", planners_exports(), EXPORTS_TARGET),
        ("modules at the package root", len(root_modules()), ROOT_TARGET),
    ]
    for name, value, target in rows:
        print(f"{name}: {value} (target <= {target})")
    for name, (rx, _) in SPELLINGS.items() if args.files else ():
        code = {p.relative_to(PACKAGE.parent) for p in files_spelling(rx, code=True)}
        for path in sorted(p.relative_to(PACKAGE.parent) for p in files_spelling(rx)):
            print(f"  {name}: {path}" + ("" if path in code else " (text only)"))
    for lines, where in bodies[: args.longest]:
        print(f"  {lines:4d}  {where}")


if __name__ == "__main__":
    main()
